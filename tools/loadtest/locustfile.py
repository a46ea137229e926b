"""The load test's request cycle as Locust users, for teams that load-test with Locust.

    pip install "vgq-cnn[locust]"
    locust -f tools/loadtest/locustfile.py --host http://127.0.0.1:8000 \\
        --headless --users 8 --spawn-rate 8 --run-time 30s

Each user repeats the cycle of ``python -m tools.loadtest`` (same workload module): upload a
fresh depth image, score K grasps against it SCORES times, one one-shot call with a fresh
image. Settings from the environment: VGQ_LOADTEST_K (grasps per call, default 128),
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
        image_id = None
        for _ in range(MIX.upload):
            with self.client.post(
                "/v1/images",
                data=self.fresh.next_npy(),
                headers={"content-type": "application/x-npy"},
                name="upload",
                catch_response=True,
            ) as r:
                try:
                    image_id = r.json()["image_id"] if r.status_code == 200 else None
                    if image_id is None:
                        r.failure(f"HTTP {r.status_code}: {r.text[:160]}")
                except (ValueError, KeyError):
                    r.failure("answer without an image_id")
        for _ in range(MIX.score if image_id else 0):
            self._scores("score", f"/v1/images/{image_id}/scores", GRASP_BYTES, OCTET)
        for _ in range(MIX.once):
            self._scores("score_once", "/v1/score", self.fresh.next_npz(WORK.grasps), "application/x-npz")
