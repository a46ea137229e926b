"""The load test's request cycle as Locust users, for teams that load-test with Locust.

    pip install "vgq-cnn[locust]"
    locust -f tools/loadtest/locustfile.py --host http://127.0.0.1:8000 \\
        --headless --users 8 --spawn-rate 8 --run-time 30s

Each user repeats the cycle of ``python -m tools.loadtest`` (same workload module): upload a
fresh depth image, score K grasps against it SCORES times (the first, ``score_first``, encodes
its windows; the others, ``score``, find them cached), one one-shot call with a fresh image.
With ``upload=0`` each user uploads and scores one image at its start, untimed by the mix
(``pin``), and then sends only cached score calls. Settings from the environment: VGQ_LOADTEST_K (grasps per call, default 128),
VGQ_LOADTEST_MIX (default ``upload=1,score=8,once=1``). Answers are checked as in the load
test (image id present, 4 bytes per grasp); a wrong answer is a Locust failure.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
from locust import HttpUser, task

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # locust loads this file by path
from tools.loadtest.workload import OCTET, FreshImages, Mix, load_workload  # noqa: E402

K = int(os.environ.get("VGQ_LOADTEST_K", "128"))
MIX = Mix.parse(os.environ.get("VGQ_LOADTEST_MIX", "upload=1,score=8,once=1"))
WORK = load_workload(K)
GRASP_BYTES = np.ascontiguousarray(WORK.grasps, "<f4").tobytes()


class ScoringUser(HttpUser):
    """One closed-loop client of the scoring service."""

    def on_start(self) -> None:
        self.fresh = FreshImages(WORK.depth)
        self.pinned = None
        if MIX.pinned:  # cached-score-only mix: one image, its windows encoded before the cycles
            self.pinned = self._upload("pin")
            if self.pinned:
                self._scores("pin", f"/v1/images/{self.pinned}/scores", GRASP_BYTES, OCTET)

    def _upload(self, name: str) -> str | None:
        with self.client.post(
            "/v1/images",
            data=self.fresh.next_npy(),
            headers={"content-type": "application/x-npy"},
            name=name,
            catch_response=True,
        ) as r:
            try:
                image_id = r.json()["image_id"] if r.status_code == 200 else None
                if image_id is None:
                    r.failure(f"HTTP {r.status_code}: {r.text[:160]}")
                return image_id
            except (ValueError, KeyError):
                r.failure("answer without an image_id")
                return None

    def _scores(self, name: str, path: str, body: bytes, content_type: str) -> None:
        with self.client.post(
            path, data=body, headers={"content-type": content_type, "accept": OCTET}, name=name, catch_response=True
        ) as r:
            if r.status_code != 200:
                r.failure(f"HTTP {r.status_code}: {r.text[:160]}")
            elif len(r.content) != 4 * K:
                r.failure(f"answer of {len(r.content)} bytes, expected {4 * K}")

    @task
    def cycle(self) -> None:
        image_id = self.pinned
        for _ in range(MIX.upload):
            image_id = self._upload("upload") or image_id
        for i in range(MIX.score if image_id else 0):
            name = "score_first" if i == 0 and not MIX.pinned else "score"
            self._scores(name, f"/v1/images/{image_id}/scores", GRASP_BYTES, OCTET)
        for _ in range(MIX.once):
            self._scores("score_once", "/v1/score", self.fresh.next_npz(WORK.grasps), "application/x-npz")
