"""``POST /v1/plan``: the best k grasps on an uploaded depth image (``planning.policy.plan``).

The body is a depth image in any upload format (service/depth_io.py); every number comes
from the query through service/numbers.py. Planning takes tens of milliseconds on a 300 x 300
image and about a second on a 2048 x 2048 one, so it runs in a worker thread, off the event loop (the in-flight bound of service/limits.py caps how many
run at once). A :class:`planning.types.PlanningError` answers 422 naming its field; an image
with nothing to grasp answers 200 with no grasps and a ``reason``.

Planning from an uploaded image's id is not offered: the image cache keeps each image's
encoded window, not its depth.
"""

from __future__ import annotations

import dataclasses

from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from planning.policy import camera_for, plan
from planning.types import MAX_K, PlanningError, PlanParams

from . import openapi as doc
from .body import read_body
from .depth_io import DEPTH_TYPES, decode_depth
from .errors import ApiError
from .media import JSON, media_type
from .numbers import HEIGHT, WIDTH, Number, parse_all
from .routes import Authorized, json_response

router = APIRouter()

#: CEM refinement iterations one request may ask for (each scores ``cem_samples`` more grasps)
MAX_CEM = 10

K = Number("k", f"grasps to return, best first (1 to {MAX_K})", integer=True, minimum=1, maximum=MAX_K)
FX = Number("fx", "the camera's focal length along u (px); default: the model's", exclusive_minimum=0.0)
FY = Number("fy", "the camera's focal length along v (px); default: the model's", exclusive_minimum=0.0)
CX = Number(
    "cx",
    "principal point, column (px); default: the model's for an image of its size, else the image centre",
    minimum=0.0,
)
CY = Number(
    "cy", "principal point, row (px); default: the model's for an image of its size, else the image centre", minimum=0.0
)
SEED = Number(
    "seed",
    "sampling seed: the same image, parameters and seed plan the same grasps (default 0)",
    integer=True,
    minimum=0,
)
CEM = Number(
    "cem",
    f"cross-entropy refinement iterations of the approach angle (0 to {MAX_CEM}, default 0)",
    integer=True,
    minimum=0,
    maximum=MAX_CEM,
)
ROI = tuple(
    Number(f"roi[{i}]", f"region of interest {name} (px)", minimum=0.0)
    for i, name in enumerate(("u0", "v0", "u1", "v1"))
)
PLAN_NUMBERS = (K, FX, FY, CX, CY, SEED, CEM, WIDTH, HEIGHT)


def roi_parameter() -> dict:
    """The ``roi`` query parameter: ``u0,v0,u1,v1`` (an OpenAPI array, form style, not exploded)."""
    return {
        "name": "roi",
        "in": "query",
        "required": False,
        "style": "form",
        "explode": False,
        "description": "region of interest u0,v0,u1,v1 (px, inclusive corners, clipped to the image); "
        "grasps lie in it. Default: the whole image",
        "schema": {"type": "array", "items": ROI[0].schema() | {"description": "px"}, "minItems": 4, "maxItems": 4},
    }


def parse_roi(raw: str | None) -> tuple[float, float, float, float] | None:
    """``"u0,v0,u1,v1"`` -> four finite pixel coordinates >= 0 (None when absent); 422 naming ``roi``."""
    if raw is None:
        return None
    parts = raw.split(",")
    if len(parts) != 4:
        raise ApiError(
            422, f"field roi must be four numbers u0,v0,u1,v1 (px), got {len(parts)} value(s)", {"field": "roi"}
        )
    values = []
    for number, part in zip(ROI, parts):
        v = number.parse(part)
        if v is None:
            raise ApiError(422, f"field {number.name} is empty; roi is four numbers u0,v0,u1,v1 (px)", {"field": "roi"})
        values.append(v)
    return tuple(values)


def plan_parameters() -> list[dict]:
    return [n.query_parameter() for n in PLAN_NUMBERS] + [roi_parameter()]


@router.post(
    "/v1/plan",
    summary="Plan the best k grasps on a depth image",
    openapi_extra={"requestBody": doc.PLAN_BODY, "parameters": plan_parameters()},
    responses={200: doc.PLAN_RESPONSE, **doc.errors(doc.PLAN_ERRORS)},
)
async def plan_grasps(request: Request, svc: Authorized):
    """Body: the depth image (metres, 0 = no reading) as for ``POST /v1/images``. Query: ``k``,
    the camera (``fx``, ``fy``, ``cx``, ``cy``; each defaults to the model's), ``roi``, ``seed``,
    ``cem``; ``width`` / ``height`` for raw float32 bodies. Answers the grasps best first: the
    grasp row (u, v, z, qw, qx, qy, qz), the 4 x 4 grasp frame in the camera frame (x = jaw
    axis, z = approach, origin at the TCP), the contacts (camera frame, metres), the jaw
    width, the network's score and out-of-distribution flags; ``reason`` says why when none."""
    n = parse_all(PLAN_NUMBERS, request.query_params)
    roi = parse_roi(request.query_params.get("roi"))
    s = svc.settings
    body = await read_body(request, s.max_body_bytes, s.request_timeout_s)
    ct = media_type(request.headers.get("content-type"))
    if ct == JSON:
        raise ApiError(
            415,
            "POST /v1/plan takes the depth image itself (one of "
            f"{', '.join(DEPTH_TYPES)}); planning on an uploaded image's id is not offered",
        )
    depth = decode_depth(body, ct, width=n["width"], height=n["height"], max_side=s.max_image_side)
    k = 5 if n["k"] is None else n["k"]
    seed = 0 if n["seed"] is None else n["seed"]
    params = dataclasses.replace(PlanParams(), cem_iterations=n["cem"] or 0)
    try:
        intr = camera_for(depth.shape, svc.model.card.intrinsics, n["fx"], n["fy"], n["cx"], n["cy"])
        result = await run_in_threadpool(plan, depth, intr, svc.model, k, roi, seed, params)
    except PlanningError as e:
        raise ApiError(422, f"{e.field}: {e}", {"field": e.field}) from None
    svc.metrics.observe_plan(result.seconds.get("total", 0.0), len(result.grasps))
    return json_response(
        {**result.to_dict(), "k": k, "seed": seed, "cem": params.cem_iterations, "intrinsics": intr.to_dict()}
    )
