"""The HTTP API (FastAPI), wired together: settings -> ``Service`` (scoring.py), the routes
(routes.py), the limits middleware (limits.py), error handlers, offline docs. Endpoints:

* ``POST /v1/images``: upload a depth image (+ camera intrinsics); it is resampled to the
  model's focal length (vgq.camera) and cached under a content-addressed id.
* ``POST /v1/images/{image_id}/scores``: score k grasps anywhere in a cached image; the crop
  windows they need (vgq.crop's grid) are encoded once, lazily, in one batch.
* ``POST /v1/score``: one-shot, depth + grasps in one request (multipart or .npz).
* ``POST /v1/plan``: the best k grasps on a depth image, or on an uploaded image named by a
  JSON ``{"image_id": ...}``; ``POST /v1/images/{image_id}/plan``: the same on an uploaded
  image (service/plan_routes.py).
* ``GET /healthz``, ``/readyz``, ``/v1/model``, ``/v1/cache``, ``/metrics``, ``/docs``, ``/redoc``.

Client errors answer ``{"error": {"status", "message", "details"}}``; so do the HTTP layer's
own refusals (service/protocol.py).
"""

from __future__ import annotations

import logging
import threading
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi_offline import FastAPIOffline
from starlette.exceptions import HTTPException as StarletteHTTPException

from vgq.pose import PoseError

from . import logs
from .body import ClientGone
from .config import Settings
from .errors import ApiError
from .limits import LimitsMiddleware
from .plan_routes import router as plan_router
from .routes import ScoringFastPath, json_response, router
from .runtime import FastModel
from .scoring import Service

GUARDED = ("/v1/images", "/v1/images/{image_id}/scores", "/v1/score", "/v1/plan", "/v1/images/{image_id}/plan")
DESCRIPTION = (
    "Upload a depth image once, with the camera's intrinsics (fx, fy, cx, cy; it is resampled to the model's focal "
    "length and cached), then score batches of 6-DOF grasps (u, v, z, qw, qx, qy, qz) anywhere in it: each grasp's "
    "crop window (on the grid the network was trained with) is encoded by Fast-VGQ-CNN's encoder once, when first "
    "needed. Each score comes with its raw network output and out-of-distribution flags. "
    "Units: u, v image pixels (u = column), z metres in the camera frame, quaternion (w, x, y, z) in the camera frame."
)


def _error(e: ApiError):
    return json_response(e.to_dict(), e.status, e.headers)


def add_error_handlers(app: FastAPI, log: logging.Logger) -> None:
    @app.exception_handler(ClientGone)
    async def _gone(request: Request, e: ClientGone):
        return _error(e)  # nobody reads it; counted as 499 and logged at INFO by the limits middleware

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, e: ApiError):
        return _error(e)

    @app.exception_handler(PoseError)
    async def _pose_error(request: Request, e: PoseError):
        return _error(ApiError(422, str(e), {"grasps": e.indices} if e.indices else None))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, e: RequestValidationError):
        msgs = "; ".join(f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}" for err in e.errors())
        return _error(ApiError(422, f"invalid request: {msgs}"))

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, e: StarletteHTTPException):
        return _error(ApiError(e.status_code, str(e.detail), headers=dict(e.headers or {})))  # keeps 405's Allow

    @app.exception_handler(Exception)
    async def _internal(request: Request, e: Exception):
        logs.event(log, "internal error", logging.ERROR, path=request.url.path, error=repr(e))
        return _error(ApiError(500, "internal error"))


def _openapi_with_security(app: FastAPI, api_key: bool):
    """The OpenAPI document; declares the X-API-Key scheme on the guarded operations when a key is set."""
    base = app.openapi

    def openapi():
        if app.openapi_schema is None:
            spec = base()
            if api_key:
                spec.setdefault("components", {}).setdefault("securitySchemes", {})["ApiKey"] = {
                    "type": "apiKey",
                    "in": "header",
                    "name": "X-API-Key",
                }
                for path in GUARDED:
                    spec["paths"][path]["post"]["security"] = [{"ApiKey": []}]
            app.openapi_schema = spec
        return app.openapi_schema

    return openapi


def create_app(
    settings: Settings | None = None, model: FastModel | None = None, cache=None, load_in_background: bool = True
) -> FastAPI:
    settings = settings or Settings()
    svc = Service(settings, model, cache)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if load_in_background:
            threading.Thread(target=svc.load, name="model-load", daemon=True).start()
        else:
            svc.load()
        yield

    # Swagger UI and ReDoc from the fastapi-offline package's files: /docs works without a CDN
    app = FastAPIOffline(
        title="VGQ-CNN grasp quality service",
        version="0.1.0",
        description=DESCRIPTION,
        lifespan=lifespan,
        telemetry=None if settings.otel else {"tracing": False, "metrics": False, "logs": False},
    )
    app.state.service = svc
    app.add_middleware(ScoringFastPath, fastapi_app=app)  # inside the limits (added after: outermost)
    app.add_middleware(
        LimitsMiddleware,
        metrics=svc.metrics,
        log=svc.log,
        access_log=settings.access_log,
        max_inflight=settings.max_inflight,
        max_buffered_bytes=settings.max_buffered_bytes,
    )
    add_error_handlers(app, svc.log)
    app.include_router(router)
    app.include_router(plan_router)
    app.openapi = _openapi_with_security(app, bool(settings.api_key))
    return app
