"""The load test's workload: what each client sends (fresh depth images, grasps, the request
mix, malformed requests). Depth in metres, grasps (k, 7) float32 u, v (px), z (m), qw, qx, qy, qz."""

from __future__ import annotations

import io
import json
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
OCTET = "application/octet-stream"


@dataclass(frozen=True)
class Mix:
    """Requests per client cycle: uploads of a fresh image, score calls per upload, one-shots,
    plans (``POST /v1/plan`` on a fresh image: the planner, encoder and head) and bad requests
    (malformed on purpose; each must get a 4xx naming the problem).

    The first score call after an upload encodes the image's crop windows (lazily: encoder +
    head) and is reported as ``score_first``; the others find them encoded (head only) and are
    reported as ``score``. ``upload=0`` with ``score=N``: a cached-score-only mix; each client
    uploads one image and scores it once before the run (not timed), then every cycle is N
    cached score calls against it."""

    upload: int = 1
    score: int = 8
    once: int = 1
    plan: int = 0
    bad: int = 0

    @classmethod
    def parse(cls, text: str) -> Mix:
        """``"upload=1,score=8,once=1,plan=0,bad=0"`` (missing keys keep their defaults)."""
        kw = {}
        for part in filter(None, (p.strip() for p in text.split(","))):
            name, _, value = part.partition("=")
            if name not in ("upload", "score", "once", "plan", "bad") or not value.strip().isdigit():
                raise ValueError(
                    f"bad --mix entry {part!r}; expected upload=N, score=N, once=N, plan=N, bad=N (N >= 0)"
                )
            kw[name] = int(value)
        mix = cls(**kw)
        if not (mix.upload or mix.score or mix.once or mix.plan or mix.bad):
            raise ValueError("--mix: nothing to do (upload, score, once, plan and bad are all 0)")
        return mix

    @property
    def pinned(self) -> bool:
        """Score calls against one image per client, uploaded and warmed before the run."""
        return self.score > 0 and self.upload == 0

    def endpoints(self) -> tuple[str, ...]:
        """The report's rows this mix sends, in report order."""
        sent = {
            "upload": self.upload > 0,
            "score_first": self.score > 0 and self.upload > 0,
            "score": self.score > (1 if self.upload else 0),
            "score_once": self.once > 0,
            "plan": self.plan > 0,
            "bad": self.bad > 0,
        }
        return tuple(e for e, on in sent.items() if on)


@dataclass
class Workload:
    depth: np.ndarray  # (H, W) float32 metres
    grasps: np.ndarray  # (k, 7) float32 u, v, z, qw, qx, qy, qz
    source: str


def synthetic_scene(
    h: int = 300, w: int = 300, table: float = 0.7, box=(120, 180, 130, 170), height: float = 0.05
) -> np.ndarray:
    """Depth (metres) of a table seen from above with a box on it."""
    d = np.full((h, w), table, np.float32)
    d[box[0] : box[1], box[2] : box[3]] = table - height
    return d


def synthetic_grasps(k: int, center=(149.5, 149.5), spread: float = 30.0, z: float = 0.66, seed: int = 0) -> np.ndarray:
    """k grasps within +/- spread px of ``center``, depth z metres, random unit quaternions."""
    rng = np.random.default_rng(seed)
    g = np.zeros((k, 7), np.float32)
    g[:, :2] = np.asarray(center) + rng.uniform(-spread, spread, (k, 2))
    g[:, 2] = z
    q = rng.standard_normal((k, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g[:, 3:] = np.where(q[:, :1] < 0, -q, q)
    return g


def load_workload(k: int, examples: Path = EXAMPLES) -> Workload:
    """The example image and grasps (tiled to k rows) if present, else the synthetic scene."""
    dpath, gpath = examples / "depth_example.npy", examples / "grasps_example.json"
    if dpath.is_file() and gpath.is_file():
        try:
            depth = np.load(dpath, allow_pickle=False).astype(np.float32)
            g = np.asarray(json.loads(gpath.read_text())["grasps"], np.float32).reshape(-1, 7)
            if depth.ndim == 2 and len(g):
                return Workload(
                    depth,
                    np.resize(g, (k, 7)),
                    str(dpath.relative_to(ROOT)) if dpath.is_relative_to(ROOT) else str(dpath),
                )
        except (OSError, ValueError, KeyError) as e:
            print(f"loadtest: cannot use {examples} ({e}); using the synthetic scene", file=sys.stderr)
    return Workload(synthetic_scene(), synthetic_grasps(k), "synthetic table + box")


class FreshImages:
    """Distinct depth images (a counter and a per-run salt in pixel (0, 0)), as .npy bytes."""

    def __init__(self, depth: np.ndarray, seed: int | None = None):
        self.depth = np.array(depth, np.float32)
        self.salt = np.random.default_rng(seed).uniform(0.5, 1.0)
        self.n = 0

    def next_array(self) -> np.ndarray:
        self.n += 1
        self.depth[0, 0] = np.float32(self.salt + (self.n % (1 << 20)) * 2.0**-22)
        self.depth[0, 1] = np.float32(0.5 + (self.n >> 20) * 2.0**-22)
        return self.depth

    def next_npy(self) -> bytes:
        return _npy_bytes(self.next_array())

    def next_npz(self, grasps: np.ndarray) -> bytes:
        return _npz_bytes(depth=self.next_array(), grasps=grasps)


def bad_requests(work: Workload) -> list[tuple[str, bytes, dict]]:
    """Malformed requests the service must answer with a 4xx naming the problem:
    (path, body, headers). NaN depth, truncated .npy, corrupt PNG, a zip-bomb .npz (40 MB of
    zeros declared, ~40 kB sent), malformed JSON, zero quaternion, an unknown image id."""
    npy_h, octet = {"content-type": "application/x-npy"}, {"content-type": OCTET}
    nan = np.array(work.depth, np.float32)
    nan[100:110, 100:110] = np.nan
    good = _npy_bytes(np.asarray(work.depth, np.float32))
    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("depth.npy", "w") as f:
            np.save(f, np.zeros((5000, 2000), np.float32))
    zero_q = np.array(work.grasps[:4], "<f4")
    zero_q[1, 3:] = 0
    unknown = "/v1/images/" + "0" * 64 + "/scores"
    return [
        ("/v1/images", _npy_bytes(nan), npy_h),
        ("/v1/images", good[: len(good) // 2], npy_h),
        ("/v1/images", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4, {"content-type": "image/png"}),
        ("/v1/score", bomb.getvalue(), {"content-type": "application/x-npz"}),
        (unknown, b'{"grasps": [[1, 2,', {"content-type": "application/json"}),
        (
            "/v1/score",
            _npz_bytes(depth=np.asarray(work.depth, np.float32), grasps=zero_q),
            {"content-type": "application/x-npz"},
        ),
        (unknown, np.ascontiguousarray(work.grasps, "<f4").tobytes(), octet),
    ]


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()
