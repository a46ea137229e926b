"""The HTTP routes (one APIRouter). Guarded routes take the ``Service`` through the
``authorized`` dependency (API key, then readiness); bodies are read by ``service.body``,
one-shot bodies parsed by ``service.oneshot``, numbers by ``service.numbers``.

The scoring path avoids pydantic: bodies are parsed with orjson / numpy and responses are
written as bytes."""

from __future__ import annotations

import hmac
from typing import Annotated

import numpy as np
import orjson
from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response

from . import openapi as doc
from .body import read_body
from .cache import image_id
from .depth_io import DEPTH_TYPES, decode_depth
from .errors import ApiError, redact_paths
from .grasps import parse_binary, parse_json
from .media import JSON, MULTIPART, NPZ, OCTET, accepts, media_type
from .numbers import UPLOAD_NUMBERS, parse_all
from .oneshot import parse_multipart, parse_npz
from .scoring import Service

router = APIRouter()


def json_response(obj, status: int = 200, headers: dict | None = None) -> Response:
    return Response(orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY), status_code=status, media_type=JSON, headers=headers)


def service_of(request: Request) -> Service:
    return request.app.state.service


async def authorized(request: Request) -> Service:
    """The dependency of guarded routes: header X-API-Key when a key is configured (401), then
    a loaded model (503). Async, so it runs on the event loop, not in a thread."""
    svc = service_of(request)
    key = svc.settings.api_key
    if key and not hmac.compare_digest(request.headers.get("x-api-key", "").encode(), key.encode()):
        raise ApiError(401, "missing or wrong API key (header X-API-Key)")
    if not svc.ready:
        raise ApiError(503, "model not ready" + (f": {svc.load_error}" if svc.load_error else "; retry shortly"),
                       headers={"retry-after": "1"})
    return svc


Authorized = Annotated[Service, Depends(authorized)]


def _scores_response(request: Request, payload: dict, p: np.ndarray) -> Response:
    if accepts(request.headers.get("accept"), OCTET):
        return Response(p.astype("<f4").tobytes(), media_type=OCTET, headers={"x-image-id": payload["image_id"]})
    payload["p_success"] = p
    return json_response(payload)


async def _body(request: Request, svc: Service):
    s = svc.settings
    return await read_body(request, s.max_body_bytes, s.request_timeout_s)


# ---- open routes ------------------------------------------------------------------------------
@router.get("/healthz", summary="Liveness: the process answers", responses=doc.errors(doc.PROTOCOL))
async def healthz():
    return json_response({"status": "alive"})


@router.get("/readyz", summary="Readiness: the model is loaded and warmed up",
            responses={200: doc.STATUS_RESPONSE, 503: doc.NOT_READY, **doc.errors(doc.PROTOCOL)})
async def readyz(request: Request):
    svc = service_of(request)
    if svc.ready:
        return json_response({"status": "ready", "model_version": svc.model.version})
    return json_response(redact_paths({"status": "loading" if svc.load_error is None else "failed", "error": svc.load_error}), 503)


@router.get("/v1/model", summary="Model card and service limits",
            responses={200: doc.MODEL_RESPONSE, **doc.errors(doc.PROTOCOL + (503,))})
async def model_info(request: Request):
    svc = service_of(request)
    if not svc.ready:
        raise ApiError(503, "model not ready", headers={"retry-after": "1"})
    s = svc.settings
    limits = {name: getattr(s, name) for name in ("max_grasps", "max_body_bytes", "max_buffered_bytes", "max_inflight",
                                                   "max_image_side", "max_header_bytes", "max_headers", "max_url_bytes",
                                                   "request_timeout_s")}
    return json_response(redact_paths({"model_card": svc.model.card.to_dict(), "head_precision": svc.model.head_precision,
                                       "encoder": svc.model.encoder_info, "limits": limits, "depth_content_types": list(DEPTH_TYPES)}))


@router.get("/v1/cache", summary="Image cache statistics", responses={200: doc.CACHE_RESPONSE, **doc.errors(doc.PROTOCOL)})
async def cache_stats(request: Request):
    return json_response(redact_paths(service_of(request).cache.stats()))


@router.get("/metrics", summary="Prometheus metrics",
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}, **doc.errors(doc.PROTOCOL)})
async def metrics(request: Request):
    return Response(service_of(request).metrics.render(), media_type="text/plain; version=0.0.4")


# ---- guarded routes -----------------------------------------------------------------------------
@router.post("/v1/images", summary="Upload a depth image: crop, encode once, cache",
             openapi_extra={"requestBody": doc.UPLOAD_BODY, "parameters": [n.query_parameter() for n in UPLOAD_NUMBERS]},
             responses={200: doc.UPLOAD_RESPONSE, **doc.errors(doc.BODY_ERRORS)})
async def upload(request: Request, svc: Authorized):
    """Body: the depth image (see the content types). ``center_u`` / ``center_v``: the crop window centre
    in image pixels (default: image centre); grasps must lie within ``kappa_px`` of it. ``width`` / ``height``:
    only for raw float32 bodies. ``fx`` / ``fy``: the camera's focal lengths, checked against the model's."""
    n = parse_all(UPLOAD_NUMBERS, request.query_params)
    svc.check_intrinsics(n["fx"], n["fy"])
    body = await _body(request, svc)
    ct = media_type(request.headers.get("content-type"))
    key = image_id(body, f"{ct};{n['width']};{n['height']};{n['center_u']};{n['center_v']}", svc.model.version)
    entry = svc.cache.get(key)
    if entry is not None:
        return json_response(svc.image_info(key, entry, True))
    depth = decode_depth(body, ct, width=n["width"], height=n["height"], max_side=svc.settings.max_image_side)
    entry = svc.encode_image(key, depth, svc.requested_center(depth.shape, n["center_u"], n["center_v"]))
    return json_response(svc.image_info(key, entry, False))


@router.post("/v1/images/{image_id}/scores", summary="Score k grasps against an uploaded image",
             openapi_extra={"requestBody": doc.SCORE_BODY}, responses={200: doc.SCORE_RESPONSE, **doc.errors(doc.BODY_ERRORS)})
async def score(image_id: str, request: Request, svc: Authorized):
    """Body: JSON ``{"grasps": [[u, v, z, qw, qx, qy, qz], ...]}`` or little-endian float32 k x 7
    (``application/octet-stream``). Returns ``p_success`` in the order given (binary float32 with
    ``Accept: application/octet-stream``)."""
    body = await _body(request, svc)
    entry = svc.cache.get(image_id)
    if entry is None:
        raise ApiError(404, f"unknown or evicted image id {image_id[:64]!r}; upload the image again (POST /v1/images)")
    ct = media_type(request.headers.get("content-type"))
    if ct == JSON:
        grasps = parse_json(body)
    elif ct == OCTET:
        grasps = parse_binary(body)
    else:
        raise ApiError(415, f"unsupported grasp content type {ct!r}; use {JSON} or {OCTET}")
    p = svc.score(entry, grasps)
    return _scores_response(request, {"image_id": image_id, "model_version": svc.model.version}, p)


@router.post("/v1/score", summary="One-shot: upload + score in one request (fills the cache)",
             openapi_extra={"requestBody": doc.ONE_SHOT_BODY}, responses={200: doc.SCORE_RESPONSE, **doc.errors(doc.BODY_ERRORS)})
async def score_once(request: Request, svc: Authorized):
    """``multipart/form-data`` with parts ``depth`` (a file: .npy, 16-bit PNG, or raw float32 with
    ``width``/``height`` fields) and ``grasps`` (JSON text or a float32 k x 7 file), optional fields
    ``center_u``, ``center_v``; or ``application/x-npz`` with arrays ``depth`` (H, W) metres,
    ``grasps`` (k, 7) and optional ``center`` (2,)."""
    s = svc.settings
    body = await _body(request, svc)
    header = request.headers.get("content-type", "")
    ct = media_type(header)
    if ct == MULTIPART:
        shot = parse_multipart(body, header)
    elif ct == NPZ:
        shot = parse_npz(body, s.max_body_bytes, s.max_image_side, s.max_grasps)
    else:
        raise ApiError(415, f"unsupported content type {ct!r} for one-shot scoring; use {MULTIPART} or {NPZ}")
    key = image_id(shot.depth_body, shot.cache_params(), svc.model.version)
    entry = svc.cache.get(key)
    cached = entry is not None
    if entry is None:
        depth = shot.decode(s.max_image_side)
        center = svc.requested_center(depth.shape, shot.numbers["center_u"], shot.numbers["center_v"])
        svc.check_grasps(shot.grasps, center)  # a bad batch costs no inference
        entry = svc.encode_image(key, depth, center)
    p = svc.score(entry, shot.grasps)
    return _scores_response(request, {"image_id": key, "cached": cached, "model_version": svc.model.version,
                                      "missing_fraction": entry.missing_fraction}, p)
