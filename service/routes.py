"""The HTTP routes (one APIRouter). Guarded routes take the ``Service`` through the
``authorized`` dependency (API key, then readiness); bodies are read by ``service.body``,
one-shot bodies parsed by ``service.oneshot``, numbers by ``service.numbers``.

The scoring path avoids pydantic: bodies are parsed with orjson / numpy and responses are
written as bytes. Its two routes are served by ``ScoringFastPath`` (a pure ASGI middleware, no
router or dependency resolution) through the same steps (``score_cached`` / ``score_one_shot``);
the routes below stay for the OpenAPI document and any request the fast path passes on."""

from __future__ import annotations

import dataclasses
import hmac
from typing import Annotated

import anyio
import numpy as np
import orjson
from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from starlette.datastructures import QueryParams

from vgq.camera import FOCAL_RATIO_RANGE
from vgq.ood import OOD_FLAGS

from . import openapi as doc
from .body import BODY_COMPLETE, read_asgi_body, read_body
from .cache import image_id
from .camera import focal_range
from .depth_io import DEPTH_TYPES, decode_depth
from .errors import ApiError, redact_paths
from .grasps import parse_binary, parse_json
from .media import JSON, MULTIPART, NPZ, OCTET, accepts, media_type
from .numbers import LEVEL, UPLOAD_NUMBERS, parse_all, parse_flag, request_key
from .oneshot import parse_multipart, parse_npz
from .scoring import Scores, Service

router = APIRouter()


def json_response(obj, status: int = 200, headers: dict | None = None) -> Response:
    return Response(
        orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY), status_code=status, media_type=JSON, headers=headers
    )


def service_of(request: Request) -> Service:
    return request.app.state.service


async def authorized(request: Request) -> Service:
    """The dependency of guarded routes: header X-API-Key when a key is configured (401), then
    a loaded model (503). Async, so it runs on the event loop, not in a thread."""
    svc = service_of(request)
    check_access(svc, request.headers.get("x-api-key", ""))
    return svc


def check_access(svc: Service, api_key: str) -> None:
    """``authorized``'s checks, given the request's X-API-Key header ("" when absent)."""
    key = svc.settings.api_key
    if key and not hmac.compare_digest(api_key.encode(), key.encode()):
        raise ApiError(401, "missing or wrong API key (header X-API-Key)")
    if not svc.ready:
        raise ApiError(
            503,
            "model not ready" + (f": {svc.load_error}" if svc.load_error else "; retry shortly"),
            headers={"retry-after": "1"},
        )


Authorized = Annotated[Service, Depends(authorized)]


OCTET_HEADER = (b"content-type", OCTET.encode())


class RawResponse(Response):
    """A Response given its header list encoded already (``(name, value)`` latin-1 bytes, lower
    case, content-length and content-type included), skipping Response's per-request header
    building. Answers exactly as a Response with those headers."""

    def __init__(self, body: bytes, raw_headers: list[tuple[bytes, bytes]], status_code: int = 200):
        self.status_code, self.body, self.raw_headers, self.background = status_code, body, raw_headers, None


def _scores_response(
    accept: str | None, svc: Service, image_id: str, cached: bool | None, entry, s: Scores
) -> Response:
    """JSON (``image_id``, ``cached`` when given, ``model_version``, the camera, then
    ``p_success``, ``raw_score``, ``ood``, ``ood_mask`` per grasp) or, with ``Accept:
    application/octet-stream``, little-endian float32 ``p_success`` (k,) with the rest in headers:
    ``x-calibrated``, ``x-ood-count`` (grasps with a flag; their flags need the JSON answer); a
    placement model's also ``x-placement-known`` (grasps whose placement row is known)."""
    if accepts(accept, OCTET):
        body = s.p_success.astype("<f4").tobytes()
        headers = [
            (b"x-image-id", image_id.encode("latin-1")),
            (b"x-calibrated", b"true" if svc.calibration is not None else b"false"),
            (b"x-ood-count", b"%d" % np.count_nonzero(s.ood_mask)),
            (b"x-windows-encoded", b"%d" % s.windows_encoded),
            (b"content-length", b"%d" % len(body)),
            OCTET_HEADER,
        ]
        if s.placement_known is not None:
            headers.insert(4, (b"x-placement-known", b"%d" % np.count_nonzero(s.placement_known)))
        return RawResponse(body, headers)
    payload = {"image_id": image_id} if cached is None else {"image_id": image_id, "cached": cached}
    payload.update(model_version=svc.model.version, **svc.camera_info(entry), **svc.scores_info(s))
    return json_response(payload)


def _strict(request: Request) -> bool:
    if not request.scope.get("query_string"):
        return False  # no query: nothing to parse
    return parse_flag("strict", request.query_params.get("strict"))


async def _body(request: Request, svc: Service):
    s = svc.settings
    return await read_body(request, s.max_body_bytes, s.request_timeout_s)


# ---- open routes ------------------------------------------------------------------------------
@router.get("/healthz", summary="Liveness: the process answers", responses=doc.errors(doc.PROTOCOL))
async def healthz():
    return json_response({"status": "alive"})


@router.get(
    "/readyz",
    summary="Readiness: the model is loaded and warmed up",
    responses={200: doc.STATUS_RESPONSE, 503: doc.NOT_READY, **doc.errors(doc.PROTOCOL)},
)
async def readyz(request: Request):
    svc = service_of(request)
    if svc.ready:
        return json_response({"status": "ready", "model_version": svc.model.version})
    return json_response(
        redact_paths({"status": "loading" if svc.load_error is None else "failed", "error": svc.load_error}), 503
    )


@router.get(
    "/v1/model",
    summary="Model card and service limits",
    responses={200: doc.MODEL_RESPONSE, **doc.errors(doc.PROTOCOL + (503,))},
)
async def model_info(request: Request):
    svc = service_of(request)
    if not svc.ready:
        raise ApiError(503, "model not ready", headers={"retry-after": "1"})
    s = svc.settings
    limits = {
        name: getattr(s, name)
        for name in (
            "max_grasps",
            "max_body_bytes",
            "max_buffered_bytes",
            "max_inflight",
            "max_image_side",
            "max_header_bytes",
            "max_headers",
            "max_url_bytes",
            "request_timeout_s",
            "max_concurrent_plans",
            "max_queued_plans",
        )
    }
    card = svc.model.card
    lo, hi = svc.z_range
    return json_response(
        redact_paths(
            {
                "model_card": card.to_dict(),
                "head_precision": svc.model.head_precision,
                "encoder": svc.model.encoder_info,
                "limits": limits,
                "depth_content_types": list(DEPTH_TYPES),
                "camera": {
                    "intrinsics": card.intrinsics.to_dict(),
                    "focal_range_px": focal_range(card.intrinsics),
                    "focal_ratio_range": list(FOCAL_RATIO_RANGE),
                    "tilt_range_deg": [float(np.degrees(t)) for t in svc.tilt_range],
                },
                "calibrated": svc.calibration is not None,
                "calibration": card.calibration or None,
                "ood": {
                    "flags": {str(bit): name for bit, name in OOD_FLAGS.items()},
                    "z_range": [lo, hi],
                    "z_range_source": svc.z_range_source,
                    "window_missing_fraction": s.ood_window_missing,
                },
            }
        )
    )


@router.get(
    "/v1/cache", summary="Image cache statistics", responses={200: doc.CACHE_RESPONSE, **doc.errors(doc.PROTOCOL)}
)
async def cache_stats(request: Request):
    return json_response(redact_paths(service_of(request).cache.stats()))


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}, **doc.errors(doc.PROTOCOL)},
)
async def metrics(request: Request):
    return Response(service_of(request).metrics.render(), media_type="text/plain; version=0.0.4")


# ---- guarded routes -----------------------------------------------------------------------------
@router.post(
    "/v1/images",
    summary="Upload a depth image: crop, encode once, cache",
    openapi_extra={
        "requestBody": doc.UPLOAD_BODY,
        "parameters": [n.query_parameter() for n in (*UPLOAD_NUMBERS, LEVEL)],
    },
    responses={200: doc.UPLOAD_RESPONSE, **doc.errors(doc.BODY_ERRORS)},
)
async def upload(request: Request, svc: Authorized):
    """Body: the depth image (see the content types). ``fx``, ``fy``, ``cx``, ``cy``: the camera's
    intrinsics (px); the image is resampled to the model's focal length (omitted: the model's are
    assumed, and the answer's ``intrinsics_assumed`` says so). Grasps may then lie anywhere in the
    image: each gets a window on the training grid, encoded when first needed. ``center_u`` /
    ``center_v`` (image px): one fixed window instead, encoded now; grasps must lie within
    ``kappa_px`` of it. ``width`` / ``height``: only for raw float32 bodies. ``up_x``, ``up_y``,
    ``up_z``: the world's up in the camera frame, to turn the image level; or ``level=table``: read
    it from the table plane in the image."""
    n = parse_all(UPLOAD_NUMBERS, request.query_params)
    n[LEVEL.name] = LEVEL.parse(request.query_params.get(LEVEL.name))
    body = await _body(request, svc)
    ct = media_type(request.headers.get("content-type"))
    key = image_id(body, request_key(ct, n), svc.model.version)
    entry = svc.cache.get(key)
    if entry is not None:
        return json_response(svc.image_info(key, entry, True))
    depth = decode_depth(body, ct, width=n["width"], height=n["height"], max_side=svc.settings.max_image_side)
    entry = svc.prepare_image(depth, n)
    svc.encode_fixed_window(entry)  # with center_u / center_v: encoded now, its missing depth checked (422)
    if svc.placement:  # a placement model's only: the image as uploaded, off the event loop (0.8 s at 2048 px)
        await anyio.to_thread.run_sync(svc.analyse_placement, entry, depth)
    svc.put(key, entry)
    return json_response(svc.image_info(key, entry, False))


@router.post(
    "/v1/images/{image_id}/scores",
    summary="Score k grasps against an uploaded image",
    openapi_extra={"requestBody": doc.SCORE_BODY, "parameters": [doc.STRICT]},
    responses={200: doc.SCORE_RESPONSE, **doc.errors(doc.BODY_ERRORS)},
)
async def score(image_id: str, request: Request, svc: Authorized):
    """Body: JSON ``{"grasps": [[u, v, z, qw, qx, qy, qz], ...]}`` or little-endian float32 k x 7
    (``application/octet-stream``), u, v in the uploaded image's pixels. Returns per grasp, in the
    order given, ``p_success`` (calibrated; the raw score when the model has no calibration),
    ``raw_score``, ``ood`` (names) and ``ood_mask`` (bits); binary float32 ``p_success`` with
    ``Accept: application/octet-stream``. ``strict=true``: any flagged grasp is a 422."""
    strict = _strict(request)
    body = await _body(request, svc)
    return score_cached(svc, image_id, body, request.headers.get("content-type"), request.headers.get("accept"), strict)


@router.post(
    "/v1/score",
    summary="One-shot: upload + score in one request (fills the cache)",
    openapi_extra={"requestBody": doc.ONE_SHOT_BODY, "parameters": [doc.STRICT, LEVEL.query_parameter()]},
    responses={200: doc.SCORE_RESPONSE, **doc.errors(doc.BODY_ERRORS)},
)
async def score_once(request: Request, svc: Authorized):
    """``multipart/form-data`` with parts ``depth`` (a file: .npy, 16-bit PNG, or raw float32 with
    ``width``/``height`` fields) and ``grasps`` (JSON text or a float32 k x 7 file), optional fields
    ``fx``, ``fy``, ``cx``, ``cy``, ``center_u``, ``center_v``; or ``application/x-npz`` with arrays
    ``depth`` (H, W) metres, ``grasps`` (k, 7) and optional ``intrinsics`` (4,) = fx, fy, cx, cy and
    ``center`` (2,), ``up`` (3,). Answers as the score route; ``strict=true`` likewise; ``level=table``
    (query) as for an upload."""
    strict = _strict(request)
    level = LEVEL.parse(request.query_params.get(LEVEL.name)) if request.scope.get("query_string") else None
    body = await _body(request, svc)
    ct, accept = request.headers.get("content-type", ""), request.headers.get("accept")
    return score_one_shot(svc, body, ct, accept, strict, level)


# ---- the scoring routes without the router ---------------------------------------------------------
SCORES_PREFIX, SCORES_SUFFIX = "/v1/images/", "/scores"


class ScoringFastPath:
    """Pure ASGI middleware: ``POST /v1/images/{image_id}/scores`` and ``POST /v1/score`` served
    without FastAPI's router, dependency resolution and route wrappers (about half of what HTTP
    added to a cached score call). Same steps as the routes above (``authorized``, ``strict``, the
    body, ``score_cached`` / ``score_one_shot``); an exception with a handler in the app (ApiError,
    PoseError, ...) is answered by that handler, anything else propagates to the app's 500
    handler, as it does from a route. Every other request goes to the app."""

    def __init__(self, app, fastapi_app):
        self.app, self.fastapi_app = app, fastapi_app
        self._handlers: dict | None = None

    def _handler(self, e: Exception):
        if self._handlers is None:  # the app's handlers, as Starlette's ExceptionMiddleware sees them
            self._handlers = {k: v for k, v in self.fastapi_app.exception_handlers.items() if k not in (500, Exception)}
        for cls in type(e).__mro__:
            if cls in self._handlers:
                return self._handlers[cls]
        return None

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http" and scope["method"] == "POST" and not scope.get("root_path"):
            path = scope["path"]
            if path == "/v1/score":
                return await self._serve(scope, receive, send, None)
            if path.startswith(SCORES_PREFIX) and path.endswith(SCORES_SUFFIX):
                image_id = path[len(SCORES_PREFIX) : -len(SCORES_SUFFIX)]
                if image_id and "/" not in image_id:
                    return await self._serve(scope, receive, send, image_id)
        return await self.app(scope, receive, send)

    async def _serve(self, scope, receive, send, image_id: str | None) -> None:
        # no Starlette Request unless an error handler needs one: the few headers read in one pass
        try:
            svc = self.fastapi_app.state.service
            headers = _request_headers(scope)
            check_access(svc, headers.get(b"x-api-key", ""))
            query = QueryParams(scope["query_string"]) if scope.get("query_string") else None
            strict = parse_flag("strict", query.get("strict")) if query else False
            level = LEVEL.parse(query.get(LEVEL.name)) if query and image_id is None else None
            s = svc.settings
            body = await read_asgi_body(
                receive,
                headers.get(b"content-length"),
                scope.get("vgq.reservation"),
                s.max_body_bytes,
                s.request_timeout_s,
                scope.get(BODY_COMPLETE, False),
            )
            ct, accept = headers.get(b"content-type"), headers.get(b"accept")
            if image_id is None:
                response = score_one_shot(svc, body, ct or "", accept, strict, level)
            else:
                response = score_cached(svc, image_id, body, ct, accept, strict)
        except Exception as e:
            handler = self._handler(e)
            if handler is None:
                raise
            response = await handler(Request(scope, receive), e)
            return await response(scope, receive, send)
        # the answer (a Response or RawResponse, no background task) as the ASGI messages it would send
        await send({"type": "http.response.start", "status": response.status_code, "headers": response.raw_headers})
        await send({"type": "http.response.body", "body": response.body})


#: the request headers the scoring routes read (names as ASGI servers give them: lower case)
FAST_PATH_HEADERS = frozenset({b"content-type", b"content-length", b"accept", b"x-api-key"})


def _request_headers(scope) -> dict[bytes, str]:
    """The first value of each of FAST_PATH_HEADERS the request sent (as Starlette's
    ``Request.headers.get`` reads them), in one pass over its headers."""
    out: dict[bytes, str] = {}
    for name, value in scope["headers"]:
        if name in FAST_PATH_HEADERS and name not in out:
            out[name] = value.decode("latin-1")
    return out


# ---- the scoring steps after the body is read (sync: they run on the event loop; also timed
# in process by tools.loadtest.overhead) -----------------------------------------------------------
def score_cached(svc: Service, image_id: str, body, content_type: str | None, accept: str | None, strict: bool):
    """``POST /v1/images/{image_id}/scores`` once its body is in memory."""
    entry = svc.cache.get(image_id)
    if entry is None:
        raise ApiError(404, f"unknown or evicted image id {image_id[:64]!r}; upload the image again (POST /v1/images)")
    ct = media_type(content_type)
    if ct == JSON:
        grasps = parse_json(body)
    elif ct == OCTET:
        grasps = parse_binary(body)
    else:
        raise ApiError(415, f"unsupported grasp content type {ct!r}; use {JSON} or {OCTET}")
    result = svc.score(image_id, entry, grasps, strict)
    return _scores_response(accept, svc, image_id, None, entry, result)


def score_one_shot(svc: Service, body, header: str, accept: str | None, strict: bool, level: str | None = None):
    """``POST /v1/score`` once its body is in memory (``header``: the request's Content-Type;
    ``level``: the query's, see ``service.numbers.LEVEL``)."""
    s = svc.settings
    ct = media_type(header)
    if ct == MULTIPART:
        shot = parse_multipart(body, header)
    elif ct == NPZ:
        shot = parse_npz(body, s.max_body_bytes, s.max_image_side, s.max_grasps)
    else:
        raise ApiError(415, f"unsupported content type {ct!r} for one-shot scoring; use {MULTIPART} or {NPZ}")
    shot.numbers[LEVEL.name] = level
    key = image_id(shot.depth_body, shot.cache_params(), svc.model.version)
    entry = svc.cache.get(key)
    cached = entry is not None
    placed, encoded = None, 0
    if entry is None:
        depth = shot.decode(s.max_image_side)
        entry = svc.prepare_image(depth, shot.numbers)
        placed = svc.place(entry, shot.grasps)  # a bad batch costs no inference and fills no cache
        # a placement model's only: the image as uploaded, analysed while the batch's windows are
        # encoded (a strict batch is checked before any inference: then one after the other)
        encoded = svc.analyse_placement(entry, depth, key, None if strict else placed)
        svc.put(key, entry)
    result = svc.score(key, entry, shot.grasps, strict, placed)
    if encoded:  # encoded beside the analysis, for this request all the same
        result = dataclasses.replace(result, windows_encoded=result.windows_encoded + encoded)
    return _scores_response(accept, svc, key, cached, entry, result)
