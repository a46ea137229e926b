"""A small Python client of the service (needs only numpy and httpx).

    from service.client import ServiceClient
    c = ServiceClient("http://127.0.0.1:8000")
    image_id = c.upload(depth, intrinsics=(615.0, 615.0, 319.5, 239.5))  # (H, W) float32 metres; fx, fy, cx, cy px
    p = c.score(image_id, grasps)               # (k, 7): u, v, z, qw, qx, qy, qz anywhere in the image -> (k,)
    r = c.score_details(image_id, grasps)       # + raw_score, ood (names per grasp), ood_mask, calibrated
    plan = c.plan(depth, k=5)                   # the best 5 grasps: plan.rows (n, 7), plan.poses (n, 4, 4)
    plan = c.plan(image_id=image_id, k=5)       # the same on the uploaded image (its camera, its cached windows)

Intrinsics: a tuple (fx, fy, cx, cy), a dict with those keys (any subset) or a
``vgq.camera.Intrinsics``; omitted, the service assumes the model's (``last_upload`` says so).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field

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


def up_params(up) -> dict:
    """``{"up_x": ..., "up_y": ..., "up_z": ...}`` of the world's up direction (3 numbers, camera
    frame), ``{"level": "table"}`` for ``up="table"`` (the service reads it from the image's table
    plane); None: {}."""
    if up is None:
        return {}
    if isinstance(up, str):
        if up != "table":
            raise ValueError(f"up must be 3 numbers or 'table', got {up!r}")
        return {"level": "table"}
    u = [float(x) for x in np.asarray(up, dtype=np.float64).reshape(-1)]
    if len(u) != 3:
        raise ValueError(f"up must be 3 numbers (the world's up direction in the camera frame), got {len(u)}")
    return dict(zip(("up_x", "up_y", "up_z"), u))


@dataclass(frozen=True)
class Plan:
    """The answer of ``POST /v1/plan`` (or ``/v1/images/{id}/plan``): ``grasps`` best first,
    each a dict with ``row`` (u, v, z, qw, qx, qy, qz), ``pose`` (4 x 4, camera frame,
    metres), ``width`` (m), ``contacts`` (2 x 3, camera frame, m), ``score``, ``ood_flags``,
    ``ood`` and ``p_hold`` (the probability it holds through the oracle's lift and shake; None
    when the model has no planner calibration); ``reason`` says why when there are none; ``intrinsics`` the camera planned
    with (px); ``ranked_by`` "ranker" (the model's planner ranker ordered the grasps) or "score";
    ``answer`` the whole JSON."""

    grasps: list[dict]
    reason: str | None
    intrinsics: dict
    model_version: str
    seconds: dict = field(default_factory=dict)
    answer: dict = field(default_factory=dict, repr=False)
    image_id: str | None = None  # the uploaded image planned on (``plan(image_id=...)``)

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

    @property
    def ranked_by(self) -> str:
        return self.answer.get("ranked_by", "score")

    @property
    def p_hold(self) -> np.ndarray:
        """(n,) each grasp's p_hold, NaN where the model has no planner calibration."""
        return np.array([np.nan if g.get("p_hold") is None else g["p_hold"] for g in self.grasps], dtype=np.float64)


#: how long one wait before a retry may be (s), whatever Retry-After says
MAX_RETRY_WAIT_S = 5.0


class ServiceClient:
    """``retries``: how often a request is sent again after a 503 (the model still loading,
    the service at its in-flight, body or plan limits: waits as Retry-After says, at most
    ``MAX_RETRY_WAIT_S``) or a connection that failed (a replica restarting: waits 0.1, 0.2,
    0.4 ... s). Every call is safe to repeat: an upload is addressed by its content, a score
    and a plan (seeded) give the same answer twice. 0: no retries."""

    def __init__(
        self,
        url: str = "http://127.0.0.1:8000",
        api_key: str | None = None,
        timeout: float = 10.0,
        retries: int = 3,
        transport: httpx.BaseTransport | None = None,
    ):
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
            raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout, transport=transport)
        self.retries = retries
        self.last_upload: dict = {}
        self.last_ood_count = 0

    def _request(self, method: str, url: str, **kw) -> httpx.Response:
        """``self.http.request`` with the retries above; the last answer (or error) stands."""
        attempt = 0
        while True:
            try:
                r = self.http.request(method, url, **kw)
            except (httpx.ConnectError, httpx.RemoteProtocolError):
                if attempt == self.retries:
                    raise
                wait = 0.1 * 2**attempt
            else:
                if r.status_code != 503 or attempt == self.retries:
                    return r
                try:
                    wait = max(float(r.headers.get("retry-after", "1")), 0.0)
                except ValueError:
                    wait = 1.0
            time.sleep(min(wait, MAX_RETRY_WAIT_S))
            attempt += 1

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

    def upload(self, depth: np.ndarray, center: tuple[float, float] | None = None, intrinsics=None, up=None) -> str:
        """Upload a (H, W) depth image in metres; returns its id. ``intrinsics``: the camera's
        (fx, fy, cx, cy) px. ``center``: one fixed crop window centre (u, v) px (default: grasps
        anywhere, windows placed by the service). ``up``: the world's up direction in the camera
        frame, e.g. ``R_world_camera.T @ (0, 0, 1)``, or ``"table"``: the service reads it from the
        table plane in the image (default: the camera is taken as level)."""
        params = {} if center is None else {"center_u": center[0], "center_v": center[1]}
        params.update(intrinsics_params(intrinsics))
        params.update(up_params(up))
        r = self._request(
            "POST", "/v1/images", content=self._npy(depth), params=params, headers={"content-type": "application/x-npy"}
        )
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
        r = self._request(
            "POST",
            f"/v1/images/{image_id}/scores",
            content=body,
            params=self._strict(strict),
            headers={"content-type": "application/octet-stream", "accept": "application/octet-stream"},
        )
        self._raise(r)
        self.last_ood_count = int(r.headers.get("x-ood-count", 0))
        return np.frombuffer(r.content, dtype="<f4").copy()

    def score_details(self, image_id: str, grasps: np.ndarray, strict: bool = False) -> dict:
        """Like ``score``, with everything the service answers: ``p_success`` (calibrated when
        ``calibrated``), ``raw_score`` (the network's output), ``ood`` (flag names per grasp),
        ``ood_mask`` (bits), ``windows``, ``windows_encoded``; arrays as numpy."""
        body = np.ascontiguousarray(grasps, dtype="<f4").tobytes()
        r = self._request(
            "POST",
            f"/v1/images/{image_id}/scores",
            content=body,
            params=self._strict(strict),
            headers={"content-type": "application/octet-stream"},
        )
        self._raise(r)
        return self._details(r.json())

    @staticmethod
    def _details(d: dict) -> dict:
        d["p_success"] = np.asarray(d["p_success"], np.float64)
        d["raw_score"] = np.asarray(d["raw_score"], np.float32)
        d["ood_mask"] = np.asarray(d["ood_mask"], np.uint8)
        return d

    def score_once(
        self,
        depth: np.ndarray,
        grasps: np.ndarray,
        center: tuple[float, float] | None = None,
        intrinsics=None,
        strict: bool = False,
        details: bool = False,
        up=None,
    ):
        """Upload + score in one request (fills the service's cache too): (k,) float32 p_success,
        or the whole answer (see ``score_details``) with ``details=True``. ``up`` as for ``upload``."""
        arrays = {"depth": np.asarray(depth, np.float32), "grasps": np.asarray(grasps, np.float32)}
        if center is not None:
            arrays["center"] = np.asarray(center, np.float64)
        intr = intrinsics_params(intrinsics)
        if intr:
            if len(intr) != 4:
                raise ValueError("score_once needs all four intrinsics (fx, fy, cx, cy) or none")
            arrays["intrinsics"] = np.array([intr[k] for k in ("fx", "fy", "cx", "cy")], np.float64)
        level = up_params(up) if isinstance(up, str) else {}  # a query parameter
        if up is not None and not level:
            arrays["up"] = np.array(list(up_params(up).values()), np.float64)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        accept = {} if details else {"accept": "application/octet-stream"}
        r = self._request(
            "POST",
            "/v1/score",
            content=buf.getvalue(),
            params={**self._strict(strict), **level},
            headers={"content-type": "application/x-npz", **accept},
        )
        self._raise(r)
        if details:
            return self._details(r.json())
        self.last_ood_count = int(r.headers.get("x-ood-count", 0))
        return np.frombuffer(r.content, dtype="<f4").copy()

    def plan(
        self,
        depth: np.ndarray | None = None,
        k: int = 5,
        intrinsics=None,
        roi=None,
        seed: int = 0,
        cem: int = 0,
        *,
        image_id: str | None = None,
        up=None,
    ) -> Plan:
        """The best ``k`` grasps on a (H, W) depth image in metres (0 = no reading), or on the
        image ``upload`` answered ``image_id`` for (one of the two; nothing is sent again and
        windows encoded before are reused). ``intrinsics``: the camera's fx, fy, cx, cy in px
        (as for ``upload``: a tuple, a mapping or ``vgq.camera.Intrinsics``; default:
        the model's; with ``image_id`` the upload's, which they may repeat, not change);
        ``roi``: (u0, v0, u1, v1) px where grasps may lie; ``seed``: repeatable sampling;
        ``cem``: refinement iterations; ``up``: the world's up direction in the camera frame or
        "table" (as for ``upload``; with ``image_id`` the upload's, which it may repeat, not
        change). Raises ServiceError (422 naming the field) for input
        it cannot plan on, 404 for an unknown or evicted ``image_id``."""
        if (depth is None) == (image_id is None):
            raise ValueError("plan needs a depth image or an image_id (one of the two)")
        params: dict = {"k": k, "seed": seed, "cem": cem}
        params.update({name: repr(v) for name, v in intrinsics_params(intrinsics).items()})
        params.update({name: v if isinstance(v, str) else repr(v) for name, v in up_params(up).items()})
        if roi is not None:
            params["roi"] = ",".join(repr(float(x)) for x in roi)
        if image_id is not None:
            r = self._request("POST", f"/v1/images/{image_id}/plan", params=params)
        else:
            r = self._request(
                "POST",
                "/v1/plan",
                content=self._npy(depth),
                params=params,
                headers={"content-type": "application/x-npy"},
            )
        self._raise(r)
        d = r.json()
        return Plan(
            d["grasps"], d["reason"], d["intrinsics"], d["model_version"], d.get("seconds", {}), d, d.get("image_id")
        )

    def model(self) -> dict:
        r = self._request("GET", "/v1/model")
        self._raise(r)
        return r.json()
