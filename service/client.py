"""A small Python client of the service (needs only numpy and httpx).

    from service.client import ServiceClient
    c = ServiceClient("http://127.0.0.1:8000")
    image_id = c.upload(depth)                  # (H, W) float32 metres
    p = c.score(image_id, grasps)               # (k, 7): u, v, z, qw, qx, qy, qz -> (k,) probabilities
    plan = c.plan(depth, k=5)                   # the best 5 grasps: plan.rows (n, 7), plan.poses (n, 4, 4)
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from dataclasses import dataclass, field

import httpx
import numpy as np


class ServiceError(RuntimeError):
    def __init__(self, status: int, message: str, details: dict | None = None):
        super().__init__(f"HTTP {status}: {message}")
        self.status, self.message, self.details = status, message, details or {}


@dataclass(frozen=True)
class Plan:
    """The answer of ``POST /v1/plan``: ``grasps`` best first, each a dict with ``row`` (u, v,
    z, qw, qx, qy, qz), ``pose`` (4 x 4, camera frame, metres), ``width`` (m), ``contacts``
    (2 x 3, camera frame, m), ``score``, ``ood_flags`` and ``ood``; ``reason`` says why when
    there are none; ``intrinsics`` the camera planned with (px); ``answer`` the whole JSON."""

    grasps: list[dict]
    reason: str | None
    intrinsics: dict
    model_version: str
    seconds: dict = field(default_factory=dict)
    answer: dict = field(default_factory=dict, repr=False)

    @property
    def rows(self) -> np.ndarray:
        """(n, 7) grasp rows, best first: what ``score`` takes."""
        return np.array([g["row"] for g in self.grasps], dtype=np.float64).reshape(-1, 7)

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) grasp frames in the camera frame (x = jaw axis, z = approach), metres."""
        return np.array([g["pose"] for g in self.grasps], dtype=np.float64).reshape(-1, 4, 4)

    @property
    def scores(self) -> np.ndarray:
        return np.array([g["score"] for g in self.grasps], dtype=np.float64)


class ServiceClient:
    def __init__(self, url: str = "http://127.0.0.1:8000", api_key: str | None = None, timeout: float = 10.0):
        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout)
        self.last_upload: dict = {}

    def close(self) -> None:
        self.http.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @staticmethod
    def _raise(r: httpx.Response) -> None:
        if r.status_code >= 400:
            try:
                e = r.json()["error"]
                raise ServiceError(r.status_code, e["message"], e.get("details"))
            except (ValueError, KeyError, TypeError):
                raise ServiceError(r.status_code, r.text) from None

    @staticmethod
    def _npy(a: np.ndarray) -> bytes:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(a, dtype=np.float32), allow_pickle=False)
        return buf.getvalue()

    def upload(self, depth: np.ndarray, center: tuple[float, float] | None = None) -> str:
        """Upload a (H, W) depth image in metres; returns its id. ``center``: crop window centre (u, v) px."""
        params = {} if center is None else {"center_u": center[0], "center_v": center[1]}
        r = self.http.post("/v1/images", content=self._npy(depth), params=params,
                           headers={"content-type": "application/x-npy"})
        self._raise(r)
        self.last_upload = r.json()
        return self.last_upload["image_id"]

    def score(self, image_id: str, grasps: np.ndarray) -> np.ndarray:
        """Score (k, 7) grasps (u, v, z, qw, qx, qy, qz) against an uploaded image -> (k,) float32."""
        body = np.ascontiguousarray(grasps, dtype="<f4").tobytes()
        r = self.http.post(f"/v1/images/{image_id}/scores", content=body,
                           headers={"content-type": "application/octet-stream", "accept": "application/octet-stream"})
        self._raise(r)
        return np.frombuffer(r.content, dtype="<f4").copy()

    def score_once(self, depth: np.ndarray, grasps: np.ndarray, center: tuple[float, float] | None = None) -> np.ndarray:
        """Upload + score in one request (fills the service's cache too)."""
        arrays = {"depth": np.asarray(depth, np.float32), "grasps": np.asarray(grasps, np.float32)}
        if center is not None:
            arrays["center"] = np.asarray(center, np.float64)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        r = self.http.post("/v1/score", content=buf.getvalue(),
                           headers={"content-type": "application/x-npz", "accept": "application/octet-stream"})
        self._raise(r)
        return np.frombuffer(r.content, dtype="<f4").copy()

    def plan(self, depth: np.ndarray, k: int = 5, intrinsics=None, roi=None, seed: int = 0, cem: int = 0) -> Plan:
        """The best ``k`` grasps on a (H, W) depth image in metres (0 = no reading).
        ``intrinsics``: the camera's fx, fy, cx, cy in px (a mapping or an object with those
        attributes, e.g. ``vgq.camera.Intrinsics``; default: the model's); ``roi``: (u0, v0,
        u1, v1) px where grasps may lie; ``seed``: repeatable sampling; ``cem``: refinement
        iterations. Raises ServiceError (422 naming the field) for input it cannot plan on."""
        params: dict = {"k": k, "seed": seed, "cem": cem}
        if intrinsics is not None:
            for name in ("fx", "fy", "cx", "cy"):
                v = intrinsics[name] if isinstance(intrinsics, Mapping) else getattr(intrinsics, name)
                params[name] = repr(float(v))
        if roi is not None:
            params["roi"] = ",".join(repr(float(x)) for x in roi)
        r = self.http.post("/v1/plan", content=self._npy(depth), params=params, headers={"content-type": "application/x-npy"})
        self._raise(r)
        d = r.json()
        return Plan(d["grasps"], d["reason"], d["intrinsics"], d["model_version"], d.get("seconds", {}), d)

    def model(self) -> dict:
        r = self.http.get("/v1/model")
        self._raise(r)
        return r.json()
