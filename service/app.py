"""The HTTP API (FastAPI). Endpoints:

* ``POST /v1/images``: upload a depth image; it is cropped (vgq.crop), encoded once and cached
  under a content-addressed id.
* ``POST /v1/images/{image_id}/scores``: score k grasps against a cached image.
* ``POST /v1/score``: one-shot, depth + grasps in one request (multipart or .npz).
* ``GET /healthz``, ``/readyz``, ``/v1/model``, ``/v1/cache``, ``/metrics``, ``/docs``.

The scoring path avoids pydantic: bodies are parsed with orjson / numpy and responses are
written as bytes. Client errors are ApiError -> ``{"error": {"status", "message", "details"}}``.
"""

from __future__ import annotations

import asyncio
import gc
import hmac
import logging
import threading
import time
from contextlib import asynccontextmanager

import numpy as np
import orjson
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from vgq.crop import crop, window_center, window_origin

from . import logs
from .cache import CachedImage, MemoryCache, image_id
from .config import Settings
from .depth_io import DEPTH_TYPES, decode_depth, parse_npy, read_npz, validate_depth
from .errors import ApiError
from .grasps import GRASP_WIDTH, parse_binary, parse_json, to_network_poses
from .metrics import Metrics
from .openapi import ERROR_RESPONSES, ONE_SHOT_BODY, SCORE_BODY, SCORE_RESPONSE, UPLOAD_BODY, UPLOAD_RESPONSE
from .runtime import FastModel

JSON = "application/json"
OCTET = "application/octet-stream"
INTRINSICS_TOLERANCE = 0.02  # relative focal length mismatch accepted
_timeout = getattr(asyncio, "timeout", None)


def _json(obj, status: int = 200) -> Response:
    return Response(orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY), status_code=status, media_type=JSON)


def _endpoint(path: str) -> str:
    if path.startswith("/v1/images/") and path.endswith("/scores"):
        return "score"
    return {"/v1/images": "upload", "/v1/score": "score_once", "/metrics": "metrics", "/healthz": "healthz",
            "/readyz": "readyz", "/v1/model": "model", "/v1/cache": "cache"}.get(path, "other")


class _MetricsMiddleware:
    """Pure ASGI middleware: request counts and latency per endpoint, optional access log."""

    def __init__(self, app, metrics: Metrics, log: logging.Logger, access_log: bool):
        self.app, self.metrics, self.log, self.access_log = app, metrics, log, access_log

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = [500]

        async def send_status(msg):
            if msg["type"] == "http.response.start":
                status[0] = msg["status"]
            await send(msg)

        try:
            await self.app(scope, receive, send_status)
        finally:
            dt = time.perf_counter() - t0
            ep = _endpoint(scope["path"])
            self.metrics.latency.labels(ep).observe(dt)
            self.metrics.requests.labels(ep, str(status[0])).inc()
            if self.access_log:
                logs.event(self.log, "request", method=scope["method"], path=scope["path"], status=status[0], ms=round(dt * 1e3, 3))


class Service:
    """State of one service instance: settings, model, cache, metrics."""

    def __init__(self, settings: Settings, model: FastModel | None = None, cache=None):
        self.settings = settings
        self.log = logs.setup(settings.log_level)
        self.model = model
        self.cache = cache if cache is not None else make_cache(settings, self.log)
        self.metrics = Metrics(self.cache)
        self.ready = False
        self.load_error: str | None = None

    def load(self) -> None:
        """Load (unless given) and warm up the model; then mark ready."""
        try:
            if self.model is None:
                self.model = FastModel(self.settings.model_dir, threads=self.settings.ort_threads,
                                       head_precision=self.settings.head_precision, encoder_precision=self.settings.encoder_precision)
            self.model.warm_up()
            gc.collect()
            gc.freeze()  # start-up objects out of the collector's way: no GC pauses on them later
            self.ready = True
            self.metrics.ready.set(1)
            logs.event(self.log, "ready", model_version=self.model.version, head=self.model.head_precision, encoder=self.model.encoder_info,
                       threads=self.settings.ort_threads,
                       cache=self.cache.backend)
        except Exception as e:  # reported by /readyz and the log; the process stays up for diagnosis
            self.load_error = str(e)
            logs.event(self.log, "model load failed", logging.ERROR, error=str(e))

    # ---- request helpers -------------------------------------------------------------
    def check(self, request: Request) -> None:
        key = self.settings.api_key
        if key and not hmac.compare_digest(request.headers.get("x-api-key", "").encode(), key.encode()):
            raise ApiError(401, "missing or wrong API key (header X-API-Key)")
        if not self.ready:
            raise ApiError(503, "model not ready" + (f": {self.load_error}" if self.load_error else "; retry shortly"))

    async def body(self, request: Request) -> bytes:
        limit = self.settings.max_body_bytes
        cl = request.headers.get("content-length")
        if cl is not None:
            try:
                if int(cl) > limit:
                    raise ApiError(413, f"request body of {cl} bytes exceeds the limit of {limit} bytes")
            except ValueError:
                raise ApiError(400, "invalid Content-Length header") from None

        async def read() -> bytes:
            chunks, n = [], 0
            async for c in request.stream():
                n += len(c)
                if n > limit:
                    raise ApiError(413, f"request body exceeds the limit of {limit} bytes")
                chunks.append(c)
            return b"".join(chunks)

        try:
            if _timeout is not None:  # asyncio.timeout (3.11+): no extra task per request, unlike wait_for
                async with _timeout(self.settings.request_timeout_s):
                    body = await read()
            else:
                body = await asyncio.wait_for(read(), self.settings.request_timeout_s)
        except asyncio.TimeoutError:
            raise ApiError(408, f"request body not received within {self.settings.request_timeout_s} s") from None
        request._body = body  # lets Starlette's form parser reuse what was read
        return body

    def requested_center(self, shape, center_u, center_v) -> np.ndarray:
        h, w = shape
        cu = (w - 1) / 2 if center_u is None else center_u
        cv = (h - 1) / 2 if center_v is None else center_v
        if not (np.isfinite(cu) and np.isfinite(cv) and 0 <= cu <= w - 1 and 0 <= cv <= h - 1):
            raise ApiError(422, f"window centre ({cu}, {cv}) must lie inside the {h}x{w} image (u in [0, {w - 1}], v in [0, {h - 1}])")
        return np.array([cu, cv], dtype=np.float64)

    def check_intrinsics(self, fx, fy) -> None:
        intr = self.model.card.intrinsics
        for name, given, trained in (("fx", fx, intr.fx), ("fy", fy, intr.fy)):
            if given is not None and not (np.isfinite(given) and abs(given / trained - 1) <= INTRINSICS_TOLERANCE):
                raise ApiError(422, f"{name} = {given} px, but the model was trained for {name} = {trained} px "
                                    f"(within {INTRINSICS_TOLERANCE:.0%}); resample the image to that focal length")

    def encode_image(self, key: str, depth: np.ndarray, center) -> CachedImage:
        geom = self.model.geometry
        img, actual = crop(depth, center, geom)
        term = self.model.encode(img)
        self.metrics.encoder.observe(self.model.encode_seconds)
        entry = CachedImage(term, actual, depth.shape)
        self.cache.put(key, entry)
        return entry

    def score(self, entry: CachedImage, grasps: np.ndarray) -> np.ndarray:
        poses = to_network_poses(grasps, entry.window_center, self.model.geometry, self.settings.max_grasps)
        p = self.model.score(entry.image_term, poses)
        self.metrics.head.observe(self.model.score_seconds)
        self.metrics.grasps.observe(len(p))
        return p

    def image_info(self, key: str, entry: CachedImage, cached: bool) -> dict:
        c, k = entry.window_center, self.model.geometry.kappa_px
        return {"image_id": key, "cached": cached, "model_version": self.model.version,
                "image_shape": list(entry.image_shape), "window_center": [float(c[0]), float(c[1])],
                "grasp_range": {"u": [float(c[0] - k), float(c[0] + k)], "v": [float(c[1] - k), float(c[1] + k)]}}


def make_cache(settings: Settings, log: logging.Logger):
    if settings.cache_backend == "redis":
        from .redis_cache import RedisCache

        return RedisCache(settings.redis_url, settings.cache_entries, settings.cache_bytes, log, ttl_s=settings.cache_ttl_s)
    return MemoryCache(settings.cache_entries, settings.cache_bytes)


def _want_binary(request: Request) -> bool:
    return OCTET in request.headers.get("accept", "")


def _scores_response(request: Request, payload: dict, p: np.ndarray) -> Response:
    if _want_binary(request):
        return Response(p.astype("<f4").tobytes(), media_type=OCTET, headers={"x-image-id": payload["image_id"]})
    payload["p_success"] = p
    return _json(payload)


def create_app(settings: Settings | None = None, model: FastModel | None = None, cache=None, load_in_background: bool = True) -> FastAPI:
    settings = settings or Settings()
    svc = Service(settings, model, cache)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if load_in_background:
            threading.Thread(target=svc.load, name="model-load", daemon=True).start()
        else:
            svc.load()
        yield

    app = FastAPI(
        title="VGQ-CNN grasp quality service",
        version="0.1.0",
        description=(
            "Upload a depth image once (it is cropped and encoded by Fast-VGQ-CNN's encoder and cached), "
            "then score batches of 6-DOF grasps (u, v, z, qw, qx, qy, qz) against it. "
            "Units: u, v image pixels (u = column), z metres in the camera frame, quaternion (w, x, y, z) in the camera frame."
        ),
        lifespan=lifespan,
    )
    app.state.service = svc
    app.add_middleware(_MetricsMiddleware, metrics=svc.metrics, log=svc.log, access_log=settings.access_log)

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, e: ApiError):
        return _json(e.to_dict(), e.status)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, e: RequestValidationError):
        msgs = "; ".join(f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}" for err in e.errors())
        return _json(ApiError(422, f"invalid request: {msgs}").to_dict(), 422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, e: StarletteHTTPException):
        return _json(ApiError(e.status_code, str(e.detail)).to_dict(), e.status_code)

    @app.exception_handler(Exception)
    async def _internal(request: Request, e: Exception):
        logs.event(svc.log, "internal error", logging.ERROR, path=request.url.path, error=repr(e))
        return _json(ApiError(500, "internal error").to_dict(), 500)

    @app.get("/healthz", summary="Liveness: the process answers")
    async def healthz():
        return _json({"status": "alive"})

    @app.get("/readyz", summary="Readiness: the model is loaded and warmed up", responses={503: {"description": "not ready"}})
    async def readyz():
        if svc.ready:
            return _json({"status": "ready", "model_version": svc.model.version})
        return _json({"status": "loading" if svc.load_error is None else "failed", "error": svc.load_error}, 503)

    @app.get("/v1/model", summary="Model card and service limits", responses={503: {"description": "not ready"}})
    async def model_info():
        if not svc.ready:
            raise ApiError(503, "model not ready")
        return _json({"model_card": svc.model.card.to_dict(), "head_precision": svc.model.head_precision, "encoder": svc.model.encoder_info, "limits": {
            "max_grasps": settings.max_grasps, "max_body_bytes": settings.max_body_bytes,
            "max_image_side": settings.max_image_side, "request_timeout_s": settings.request_timeout_s},
            "depth_content_types": list(DEPTH_TYPES)})

    @app.get("/v1/cache", summary="Image cache statistics")
    async def cache_stats():
        return _json(svc.cache.stats())

    @app.get("/metrics", summary="Prometheus metrics", responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
    async def metrics():
        return Response(svc.metrics.render(), media_type="text/plain; version=0.0.4")

    @app.post("/v1/images", summary="Upload a depth image: crop, encode once, cache", status_code=200,
              openapi_extra={"requestBody": UPLOAD_BODY}, responses={200: UPLOAD_RESPONSE, **ERROR_RESPONSES})
    async def upload(request: Request, center_u: float | None = None, center_v: float | None = None,
                     width: int | None = None, height: int | None = None, fx: float | None = None, fy: float | None = None):
        """Body: the depth image (see the content types). ``center_u`` / ``center_v``: the crop window centre
        in image pixels (default: image centre); grasps must lie within ``kappa_px`` of it. ``width`` / ``height``:
        only for raw float32 bodies. ``fx`` / ``fy``: the camera's focal lengths, checked against the model's."""
        svc.check(request)
        body = await svc.body(request)
        ct = request.headers.get("content-type", "").split(";")[0].strip().lower()
        svc.check_intrinsics(fx, fy)
        key = image_id(body, f"{ct};{width};{height};{center_u};{center_v}", svc.model.version)
        entry = svc.cache.get(key)
        if entry is not None:
            return _json(svc.image_info(key, entry, True))
        depth = decode_depth(body, ct, width=width, height=height, max_side=settings.max_image_side)
        entry = svc.encode_image(key, depth, svc.requested_center(depth.shape, center_u, center_v))
        return _json(svc.image_info(key, entry, False))

    @app.post("/v1/images/{image_id}/scores", summary="Score k grasps against an uploaded image",
              openapi_extra={"requestBody": SCORE_BODY}, responses={200: SCORE_RESPONSE, **ERROR_RESPONSES})
    async def score(image_id: str, request: Request):
        """Body: JSON ``{"grasps": [[u, v, z, qw, qx, qy, qz], ...]}`` or little-endian float32 k x 7
        (``application/octet-stream``). Returns ``p_success`` in the order given (binary float32 with
        ``Accept: application/octet-stream``)."""
        svc.check(request)
        body = await svc.body(request)
        entry = svc.cache.get(image_id)
        if entry is None:
            raise ApiError(404, f"unknown or evicted image id {image_id!r}; upload the image again (POST /v1/images)")
        ct = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ct == JSON:
            grasps = parse_json(body)
        elif ct == OCTET:
            grasps = parse_binary(body)
        else:
            raise ApiError(415, f"unsupported grasp content type {ct!r}; use {JSON} or {OCTET}")
        p = svc.score(entry, grasps)
        return _scores_response(request, {"image_id": image_id, "model_version": svc.model.version}, p)

    @app.post("/v1/score", summary="One-shot: upload + score in one request (fills the cache)",
              openapi_extra={"requestBody": ONE_SHOT_BODY}, responses={200: SCORE_RESPONSE, **ERROR_RESPONSES})
    async def score_once(request: Request):
        """``multipart/form-data`` with parts ``depth`` (a file: .npy, 16-bit PNG, or raw float32 with
        ``width``/``height`` fields) and ``grasps`` (JSON text or a float32 k x 7 file), optional fields
        ``center_u``, ``center_v``; or ``application/x-npz`` with arrays ``depth`` (H, W) metres,
        ``grasps`` (k, 7) and optional ``center`` (2,)."""
        svc.check(request)
        body = await svc.body(request)
        ct = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ct == "multipart/form-data":
            depth_body, depth_ct, grasps, params = await _one_shot_multipart(request, settings)
        elif ct == "application/x-npz":
            depth_body, depth_ct, grasps, params = _one_shot_npz(body, settings)
        else:
            raise ApiError(415, f"unsupported content type {ct!r} for one-shot scoring; use multipart/form-data or application/x-npz")
        key = image_id(depth_body, f"{depth_ct};{params['width']};{params['height']};{params['center_u']};{params['center_v']}",
                       svc.model.version)
        entry = svc.cache.get(key)
        cached = entry is not None
        if entry is None:
            depth = params.pop("array", None)
            if depth is None:
                depth = decode_depth(depth_body, depth_ct, width=params["width"], height=params["height"],
                                     max_side=settings.max_image_side)
            center = svc.requested_center(depth.shape, params["center_u"], params["center_v"])
            # grasps are checked before the encoder runs: a bad batch costs no inference
            geom = svc.model.geometry
            to_network_poses(grasps, window_center(window_origin(center, geom), geom), geom, settings.max_grasps)
            entry = svc.encode_image(key, depth, center)
        p = svc.score(entry, grasps)
        return _scores_response(request, {"image_id": key, "cached": cached, "model_version": svc.model.version}, p)

    return app


def _float_or_none(v, name: str):
    if v is None or v == "":
        return None
    try:
        return float(v)
    except (TypeError, ValueError):
        raise ApiError(422, f"field {name} must be a number, got {v!r}") from None


def _int_or_none(v, name: str):
    f = _float_or_none(v, name)
    if f is None:
        return None
    if f != int(f):
        raise ApiError(422, f"field {name} must be an integer, got {v!r}")
    return int(f)


async def _one_shot_multipart(request: Request, settings: Settings):
    try:
        form = await request.form(max_files=4, max_fields=16)
    except Exception as e:
        raise ApiError(400, f"malformed multipart body: {e}") from None
    depth_part, grasps_part = form.get("depth"), form.get("grasps")
    if depth_part is None or isinstance(depth_part, str):
        raise ApiError(422, 'multipart body needs a file part "depth"')
    if grasps_part is None:
        raise ApiError(422, 'multipart body needs a part "grasps" (JSON text or float32 k x 7 file)')
    depth_body = await depth_part.read()
    depth_ct = (depth_part.content_type or "").split(";")[0].strip().lower()
    if isinstance(grasps_part, str):
        grasps = parse_json(grasps_part.encode())
    else:
        gb = await grasps_part.read()
        gct = (grasps_part.content_type or "").split(";")[0].strip().lower()
        grasps = parse_binary(gb) if gct == OCTET else parse_json(gb)
    params = {"width": _int_or_none(form.get("width"), "width"), "height": _int_or_none(form.get("height"), "height"),
              "center_u": _float_or_none(form.get("center_u"), "center_u"),
              "center_v": _float_or_none(form.get("center_v"), "center_v")}
    return depth_body, depth_ct, grasps, params


def _one_shot_npz(body: bytes, settings: Settings):
    members = read_npz(body, settings.max_body_bytes)
    for need in ("depth", "grasps"):
        if need not in members:
            raise ApiError(422, f".npz body needs an array {need!r} (has {sorted(members)})")
    side = settings.max_image_side
    depth = parse_npy(members["depth"], "depth", side * side)
    if depth.ndim != 2 or not (32 <= depth.shape[0] <= side and 32 <= depth.shape[1] <= side):
        raise ApiError(422, f"depth has shape {depth.shape}; expected (H, W) with sides in [32, {side}]")
    depth = validate_depth(np.ascontiguousarray(depth, dtype=np.float32))
    grasps = parse_npy(members["grasps"], "grasps", settings.max_grasps * GRASP_WIDTH + GRASP_WIDTH)
    if grasps.ndim != 2 or grasps.shape[1] != GRASP_WIDTH:
        raise ApiError(422, f"grasps has shape {grasps.shape}; expected (k, 7)")
    center = None
    if "center" in members:
        center = parse_npy(members["center"], "center", 2).reshape(-1)
        if center.shape != (2,):
            raise ApiError(422, "center must hold 2 values (u, v)")
    params = {"width": None, "height": None, "center_u": None if center is None else float(center[0]),
              "center_v": None if center is None else float(center[1]), "array": depth}
    return members["depth"], "application/x-npy", grasps.astype(np.float64), params
