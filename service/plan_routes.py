"""``POST /v1/plan``: the best k grasps on a depth image (``planning.policy.plan``), and
``POST /v1/images/{image_id}/plan``: the same on an image uploaded before (``POST /v1/images``).

The body of ``/v1/plan`` is a depth image in any upload format (service/depth_io.py), or JSON
``{"image_id": ...}`` naming an uploaded one; every number comes from the query through
service/numbers.py. An uploaded image is planned on as the cache holds it (its depth at the
model's focal lengths, ``planning.policy.plan_resampled``), with the camera given at upload:
``fx`` .. ``cy`` in the query may repeat it but not change it (422 naming the field). The
windows the planner needs are taken from the cache when encoded before (by a plan or a score
request, on this replica or, with Redis, another) and the ones it encodes are added to it,
except those mostly missing, which the score route refuses (setting max_missing_fraction).
Planning takes tens of milliseconds on a 300 x 300 image, about a second and 0.35 GB on a 2048 x
2048 one and four seconds and 1.5 GB on a 4096 x 4096 one, so it runs in a worker thread, off the event loop, at most ``max_concurrent_plans`` at once
(setting; others wait their turn without holding a thread, under the in-flight bound of
service/limits.py). A :class:`planning.types.PlanningError` answers 422 naming its field; an image
with nothing to grasp answers 200 with no grasps and a ``reason``.

A model whose head reads placement rows (``vgq.placement``) scores each candidate with its row from
the planner's image (``planning.policy.window_scorer``).
"""

from __future__ import annotations

import dataclasses
import math

import anyio
import numpy as np
import orjson
from fastapi import APIRouter, Request

from planning.policy import camera_for, plan, plan_resampled
from planning.types import MAX_K, PlanningError, PlanParams
from vgq.camera import CameraMismatch, describe_level

from . import openapi as doc
from .body import ClientGone, read_body
from .cache import CachedImage, EncodedWindow
from .camera import check_resampled_side, client_level, client_up, level_and_up
from .depth_io import decode_depth
from .errors import ApiError
from .limits import RETRY_AFTER_S
from .media import JSON, media_type
from .numbers import HEIGHT, LEVEL, UP, WIDTH, Number, parse_all
from .routes import Authorized, json_response
from .scoring import Service

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
PLAN_NUMBERS = (K, FX, FY, CX, CY, SEED, CEM, WIDTH, HEIGHT, *UP)
#: the query of a plan on an uploaded image (no body to describe: no width / height)
IMAGE_PLAN_NUMBERS = (K, FX, FY, CX, CY, SEED, CEM, *UP)


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
    return tuple(number.parse(part) for number, part in zip(ROI, parts))  # an empty part: 422 naming it


def plan_parameters(numbers=PLAN_NUMBERS) -> list[dict]:
    return [n.query_parameter() for n in numbers] + [LEVEL.query_parameter(), roi_parameter()]


def image_plan_parameters() -> list[dict]:
    """The query of ``POST /v1/images/{image_id}/plan``: the camera may only repeat the upload's."""
    out = plan_parameters(IMAGE_PLAN_NUMBERS)
    for p in out:
        if p["name"] in ("fx", "fy", "cx", "cy"):
            p["description"] = p["schema"]["description"] = (
                f"{p['name']} (px) of the camera the image was uploaded with; optional, and when given it must "
                "equal the upload's (the answer's intrinsics)"
            )
        elif p["name"] == LEVEL.name:
            p["description"] = p["schema"]["description"] = (
                "table: only for an image uploaded with level=table (the plan uses the upload's up direction)"
            )
        elif p["name"].startswith("up_"):
            p["description"] = p["schema"]["description"] = (
                f"{p['name']} of the up direction the image was uploaded with; optional, and when given it must "
                "equal the upload's (the answer's level.up)"
            )
    return out


def unknown_image(image_id: str) -> ApiError:
    return ApiError(404, f"unknown or evicted image id {image_id[:64]!r}; upload the image again (POST /v1/images)")


def body_image_id(body: bytes) -> str:
    """The ``image_id`` of a JSON body ``{"image_id": "..."}`` (400 for bad JSON, 422 otherwise)."""
    try:
        doc_ = orjson.loads(body)
    except orjson.JSONDecodeError as e:
        raise ApiError(400, f'body is not valid JSON ({e}); send {{"image_id": "..."}} or a depth image') from None
    if not isinstance(doc_, dict) or not isinstance(doc_.get("image_id"), str):
        raise ApiError(422, 'a JSON body must be {"image_id": "<id from POST /v1/images>"}', {"field": "image_id"})
    extra = sorted(set(doc_) - {"image_id"})
    if extra:
        raise ApiError(
            422,
            f"a JSON body holds only image_id; got {', '.join(map(repr, extra[:5]))} too "
            "(k, seed, roi, cem and the camera go in the query)",
            {"field": extra[0]},
        )
    return doc_["image_id"]


def check_upload_camera(image_id: str, entry: CachedImage, numbers: dict) -> None:
    """422 naming the first of ``fx``, ``fy``, ``cx``, ``cy`` given in the query that differs
    from the camera the image was uploaded with, or ``up_x`` for an up direction other than the
    upload's (a cached image is planned with that camera, turned level as it was at upload)."""
    if numbers.get(LEVEL.name) == "table" and entry.up_from != "table":
        raise ApiError(
            422,
            f"field level: image {image_id[:64]!r} was uploaded without level=table; a plan on it uses the upload's "
            "up direction: omit level, or upload the image again with level=table",
            {"field": "level"},
        )
    up, _ = client_up(numbers)
    if numbers.get(LEVEL.name) == "table":
        if up is not None:
            raise level_and_up()
    elif up is not None and (entry.up is None or not np.allclose(up, entry.up, rtol=1e-9, atol=1e-12)):
        was = "without up (taken as level)" if entry.up is None else f"with up {list(entry.up)}"
        raise ApiError(
            422,
            f"field up_x: image {image_id[:64]!r} was uploaded {was}, not up {list(up)}; a plan on it uses the "
            "upload's: omit up_x, up_y, up_z, or upload the image again with this up direction",
            {"field": "up_x"},
        )
    for name in ("fx", "fy", "cx", "cy"):
        v, was = numbers.get(name), float(getattr(entry.camera, name))
        if v is not None and not math.isclose(v, was, rel_tol=1e-9, abs_tol=1e-9):
            how = " (assumed: not given at upload)" if name in entry.assumed else ""
            raise ApiError(
                422,
                f"field {name}: image {image_id[:64]!r} was uploaded with {name} {was:g}{how}, not {v:g}; a plan on "
                f"it uses the upload's camera: omit {name}, or upload the image again with this camera",
                {"field": name},
            )


class CachedWindows:
    """The planner's window store (``planning.policy.WindowStore``) on a cached image: its
    encoded windows (fetched from Redis when another replica encoded them) are reused; the
    ones the planner encodes are added, unless more than ``max_missing_fraction`` of them is
    missing (the score route answers 422 for those rather than score them) or the image was
    uploaded with one fixed window (``center_u`` / ``center_v``: its grasps are scored in that
    window only, and its answers describe that window)."""

    def __init__(self, svc: Service, key: str, entry: CachedImage):
        self.svc, self.key, self.entry = svc, key, entry

    def lookup(self, origins):
        want = [o for o in origins if o not in self.entry.windows]
        if want:
            self.svc.cache.fetch_windows(self.key, self.entry, want)
        held = self.entry.windows
        return {o: (held[o].term, held[o].missing_fraction) for o in origins if o in held}

    def keep(self, new) -> None:
        if self.entry.fixed_center is not None:
            return
        cap = self.svc.settings.max_missing_fraction
        add = {
            o: EncodedWindow(np.asarray(term, np.float32).reshape(1, -1).copy(), float(frac))
            for o, (term, frac) in new.items()
            if frac <= cap
        }
        if add:
            self.svc.cache.add_windows(self.key, self.entry, add)


def plan_params(n: dict) -> tuple[int, int, PlanParams]:
    k = 5 if n["k"] is None else n["k"]
    seed = 0 if n["seed"] is None else n["seed"]
    return k, seed, dataclasses.replace(PlanParams(), cem_iterations=n["cem"] or 0)


async def run_plan(svc: Service, request: Request, fn, *args):
    """``fn(*args)`` in a worker thread once one of the service's plan slots
    (``max_concurrent_plans``) is free: many large plans at once would take memory and cores
    the other requests need. At most ``max_queued_plans`` wait; one more is a 503 with
    Retry-After. A plan whose client left while it waited is not computed.

    The first look at the connection resumes reading it (the server pauses reading under a
    large body), so that a client closing it while the plan waits is seen by the second."""
    await request.is_disconnected()
    slots, queue = svc.plan_slots, svc.settings.max_queued_plans
    if slots.available_tokens == 0 and slots.statistics().tasks_waiting >= queue:
        raise ApiError(
            503,
            f"{slots.total_tokens:g} plans computing and {queue} waiting (limits max_concurrent_plans, "
            "max_queued_plans); retry shortly",
            headers={"retry-after": str(RETRY_AFTER_S)},
        )
    async with slots:
        if await request.is_disconnected():
            raise ClientGone("while its plan waited for a plan slot")
        return await anyio.to_thread.run_sync(fn, *args)


def plan_answer(svc: Service, result, k: int, seed: int, params: PlanParams, intrinsics: dict, **extra):
    svc.metrics.observe_plan(result.seconds.get("total", 0.0), len(result.grasps))
    return json_response(
        {**result.to_dict(), "k": k, "seed": seed, "cem": params.cem_iterations, "intrinsics": intrinsics, **extra}
    )


async def plan_cached(svc: Service, request: Request, image_id: str, n: dict, roi):
    """Plan on the cached image ``image_id``: 404 when unknown or evicted, 422 naming a field."""
    entry = svc.cache.get(image_id)
    if entry is None:
        raise unknown_image(image_id)
    check_upload_camera(image_id, entry, n)
    k, seed, params = plan_params(n)
    store = CachedWindows(svc, image_id, entry)
    try:
        result = await run_plan(
            svc,
            request,
            plan_resampled,
            entry.depth,
            entry.resampled,
            entry.camera,
            svc.model,
            k,
            roi,
            seed,
            params,
            store,
            None,
            entry.up,
        )
    except PlanningError as e:
        raise ApiError(422, f"{e.field}: {e}", {"field": e.field}) from None
    return plan_answer(
        svc,
        result,
        k,
        seed,
        params,
        entry.camera.to_dict(),
        image_id=image_id,
        intrinsics_assumed=list(entry.assumed),
        level=describe_level(entry.up, entry.roll, entry.up_from),
    )


@router.post(
    "/v1/plan",
    summary="Plan the best k grasps on a depth image (or an uploaded image's id)",
    openapi_extra={"requestBody": doc.PLAN_BODY, "parameters": plan_parameters()},
    responses={200: doc.PLAN_RESPONSE, **doc.errors(doc.PLAN_ERRORS)},
)
async def plan_grasps(request: Request, svc: Authorized):
    """Body: the depth image (metres, 0 = no reading) as for ``POST /v1/images``, or JSON
    ``{"image_id": ...}`` naming an uploaded image (as ``POST /v1/images/{image_id}/plan``).
    Query: ``k``, the camera (``fx``, ``fy``, ``cx``, ``cy``; each defaults to the model's;
    for an image id, the upload's), ``roi``, ``seed``, ``cem``; ``width`` / ``height`` for raw
    float32 bodies. Answers the grasps best first: the grasp row (u, v, z, qw, qx, qy, qz), the
    4 x 4 grasp frame in the camera frame (x = jaw axis, z = approach, origin at the TCP), the
    contacts (camera frame, metres), the jaw width, the network's score and out-of-distribution
    flags; ``reason`` says why when none."""
    n = parse_all(PLAN_NUMBERS, request.query_params)
    n[LEVEL.name] = LEVEL.parse(request.query_params.get(LEVEL.name))
    roi = parse_roi(request.query_params.get("roi"))
    s = svc.settings
    body = await read_body(request, s.max_body_bytes, s.request_timeout_s)
    ct = media_type(request.headers.get("content-type"))
    if ct == JSON:
        return await plan_cached(svc, request, body_image_id(body), n, roi)
    depth = decode_depth(body, ct, width=n["width"], height=n["height"], max_side=s.max_image_side)
    k, seed, params = plan_params(n)
    try:
        intr = camera_for(depth.shape, svc.model.card.intrinsics, n["fx"], n["fy"], n["cx"], n["cy"])
        up, roll, up_from = client_level(n, depth, intr)
        try:
            check_resampled_side(intr, svc.model.card.intrinsics, s.max_image_side, roll)  # as for uploads
        except CameraMismatch:
            pass  # the planner names it (field intrinsics)
        result = await run_plan(svc, request, plan, depth, intr, svc.model, k, roi, seed, params, up)
    except PlanningError as e:
        raise ApiError(422, f"{e.field}: {e}", {"field": e.field}) from None
    return plan_answer(svc, result, k, seed, params, intr.to_dict(), level=describe_level(up, roll, up_from))


@router.post(
    "/v1/images/{image_id}/plan",
    summary="Plan the best k grasps on an uploaded image",
    openapi_extra={"parameters": image_plan_parameters()},
    responses={200: doc.IMAGE_PLAN_RESPONSE, **doc.errors(doc.IMAGE_PLAN_ERRORS)},
)
async def plan_image(image_id: str, request: Request, svc: Authorized):
    """No body: the image is the one ``POST /v1/images`` answered ``image_id`` for, planned
    with the camera given at upload (``fx``, ``fy``, ``cx``, ``cy`` may repeat it, not change
    it: 422 naming the field). Query and answer as ``POST /v1/plan``, plus ``image_id`` and
    ``intrinsics_assumed``; windows encoded before for this image are reused, the new ones
    cached. The same depth, camera, parameters and seed plan the same grasps as ``POST
    /v1/plan`` with the depth in the body. Unknown or evicted id: 404, upload again."""
    n = parse_all(IMAGE_PLAN_NUMBERS, request.query_params)
    n[LEVEL.name] = LEVEL.parse(request.query_params.get(LEVEL.name))
    roi = parse_roi(request.query_params.get("roi"))
    s = svc.settings
    body = await read_body(request, s.max_body_bytes, s.request_timeout_s)
    if body:
        raise ApiError(
            422,
            f"POST /v1/images/{{image_id}}/plan takes no body ({len(body)} bytes sent): the image is the uploaded "
            "one, the parameters go in the query",
            {"field": "body"},
        )
    return await plan_cached(svc, request, image_id, n, roi)
