"""A small Python client of the service (needs only numpy and httpx).

    from service.client import ServiceClient
    c = ServiceClient("http://127.0.0.1:8000")
    image_id = c.upload(depth, intrinsics=(615.0, 615.0, 319.5, 239.5))  # (H, W) float32 metres; fx, fy, cx, cy px
    p = c.score(image_id, grasps)               # (k, 7): u, v, z, qw, qx, qy, qz anywhere in the image -> (k,)
    r = c.score_details(image_id, grasps)       # + raw_score, ood (names per grasp), ood_mask, calibrated

Intrinsics: a tuple (fx, fy, cx, cy), a dict with those keys (any subset) or a
``vgq.camera.Intrinsics``; omitted, the service assumes the model's (``last_upload`` says so).
"""

from __future__ import annotations

import io

import httpx
import numpy as np


class ServiceError(RuntimeError):
    def __init__(self, status: int, message: str, details: dict | None = None):
        super().__init__(f"HTTP {status}: {message}")
        self.status, self.message, self.details = status, message, details or {}


def intrinsics_params(intrinsics) -> dict:
    """``{"fx": ..., "fy": ..., "cx": ..., "cy": ...}`` of a tuple, dict or Intrinsics (None: {})."""
    if intrinsics is None:
        return {}
    if hasattr(intrinsics, "fx"):
        return {k: float(getattr(intrinsics, k)) for k in ("fx", "fy", "cx", "cy")}
    if isinstance(intrinsics, dict):
        return {k: float(v) for k, v in intrinsics.items() if k in ("fx", "fy", "cx", "cy") and v is not None}
    return dict(zip(("fx", "fy", "cx", "cy"), (float(x) for x in intrinsics)))


class ServiceClient:
    def __init__(self, url: str = "http://127.0.0.1:8000", api_key: str | None = None, timeout: float = 10.0):
        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout)
        self.last_upload: dict = {}
        self.last_ood_count = 0

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

    def upload(self, depth: np.ndarray, center: tuple[float, float] | None = None, intrinsics=None) -> str:
        """Upload a (H, W) depth image in metres; returns its id. ``intrinsics``: the camera's
        (fx, fy, cx, cy) px. ``center``: one fixed crop window centre (u, v) px (default: grasps
        anywhere, windows placed by the service)."""
        params = {} if center is None else {"center_u": center[0], "center_v": center[1]}
        params.update(intrinsics_params(intrinsics))
        r = self.http.post("/v1/images", content=self._npy(depth), params=params,
                           headers={"content-type": "application/x-npy"})
        self._raise(r)
        self.last_upload = r.json()
        return self.last_upload["image_id"]

    @staticmethod
    def _strict(strict: bool) -> dict:
        return {"strict": "true"} if strict else {}

    def score(self, image_id: str, grasps: np.ndarray, strict: bool = False) -> np.ndarray:
        """Score (k, 7) grasps (u, v, z, qw, qx, qy, qz) against an uploaded image -> (k,) float32
        p_success. ``last_ood_count``: how many were flagged (``score_details`` says why);
        ``strict``: a flagged grasp raises ServiceError 422."""
        body = np.ascontiguousarray(grasps, dtype="<f4").tobytes()
        r = self.http.post(f"/v1/images/{image_id}/scores", content=body, params=self._strict(strict),
                           headers={"content-type": "application/octet-stream", "accept": "application/octet-stream"})
        self._raise(r)
        self.last_ood_count = int(r.headers.get("x-ood-count", 0))
        return np.frombuffer(r.content, dtype="<f4").copy()

    def score_details(self, image_id: str, grasps: np.ndarray, strict: bool = False) -> dict:
        """Like ``score``, with everything the service answers: ``p_success`` (calibrated when
        ``calibrated``), ``raw_score`` (the network's output), ``ood`` (flag names per grasp),
        ``ood_mask`` (bits), ``windows``, ``windows_encoded``; arrays as numpy."""
        body = np.ascontiguousarray(grasps, dtype="<f4").tobytes()
        r = self.http.post(f"/v1/images/{image_id}/scores", content=body, params=self._strict(strict),
                           headers={"content-type": "application/octet-stream"})
        self._raise(r)
        return self._details(r.json())

    @staticmethod
    def _details(d: dict) -> dict:
        d["p_success"] = np.asarray(d["p_success"], np.float64)
        d["raw_score"] = np.asarray(d["raw_score"], np.float32)
        d["ood_mask"] = np.asarray(d["ood_mask"], np.uint8)
        return d

    def score_once(self, depth: np.ndarray, grasps: np.ndarray, center: tuple[float, float] | None = None,
                   intrinsics=None, strict: bool = False, details: bool = False):
        """Upload + score in one request (fills the service's cache too): (k,) float32 p_success,
        or the whole answer (see ``score_details``) with ``details=True``."""
        arrays = {"depth": np.asarray(depth, np.float32), "grasps": np.asarray(grasps, np.float32)}
        if center is not None:
            arrays["center"] = np.asarray(center, np.float64)
        intr = intrinsics_params(intrinsics)
        if intr:
            if len(intr) != 4:
                raise ValueError("score_once needs all four intrinsics (fx, fy, cx, cy) or none")
            arrays["intrinsics"] = np.array([intr[k] for k in ("fx", "fy", "cx", "cy")], np.float64)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        accept = {} if details else {"accept": "application/octet-stream"}
        r = self.http.post("/v1/score", content=buf.getvalue(), params=self._strict(strict),
                           headers={"content-type": "application/x-npz", **accept})
        self._raise(r)
        if details:
            return self._details(r.json())
        self.last_ood_count = int(r.headers.get("x-ood-count", 0))
        return np.frombuffer(r.content, dtype="<f4").copy()

    def model(self) -> dict:
        r = self.http.get("/v1/model")
        self._raise(r)
        return r.json()
