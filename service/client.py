"""A small Python client of the service (needs only numpy and httpx).

    from service.client import ServiceClient
    c = ServiceClient("http://127.0.0.1:8000")
    image_id = c.upload(depth)                  # (H, W) float32 metres
    p = c.score(image_id, grasps)               # (k, 7): u, v, z, qw, qx, qy, qz -> (k,) probabilities
"""

from __future__ import annotations

import io

import httpx
import numpy as np


class ServiceError(RuntimeError):
    def __init__(self, status: int, message: str, details: dict | None = None):
        super().__init__(f"HTTP {status}: {message}")
        self.status, self.message, self.details = status, message, details or {}


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

    def model(self) -> dict:
        r = self.http.get("/v1/model")
        self._raise(r)
        return r.json()
