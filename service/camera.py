"""The client's camera at the HTTP edge: intrinsics from the request (the model's assumed
where omitted) and, optionally, the world's up direction in its frame, checked and applied by
the shared contract (``vgq.camera``: the image is resampled to the model's focal lengths and
turned level); ``CameraMismatch`` becomes a 422 naming the field."""

from __future__ import annotations

from math import degrees

import numpy as np

from vgq.camera import (
    FOCAL_RATIO_RANGE,
    CameraMismatch,
    Intrinsics,
    check_client_intrinsics,
    focal_lengths,
    level_depth,
    level_roll,
    leveled_intrinsics,
    resample_depth,
    resampled_intrinsics,
)

from .errors import ApiError


def client_camera(numbers: dict, shape: tuple[int, int], model: Intrinsics) -> tuple[Intrinsics, tuple[str, ...]]:
    """Intrinsics of the camera that took an (H, W) image, from the request's ``fx``, ``fy``,
    ``cx``, ``cy`` (already checked finite, focal lengths > 0). Omitted: fx the model's, fy
    = fx, (cx, cy) the image centre. Returns (intrinsics, names of the assumed values)."""
    h, w = shape
    fx, fy, cx, cy = (numbers.get(k) for k in ("fx", "fy", "cx", "cy"))
    assumed = tuple(k for k, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)) if v is None)
    fx, fy = focal_lengths(fx, fy, model)
    cx = (w - 1) / 2 if cx is None else cx
    cy = (h - 1) / 2 if cy is None else cy
    try:
        return Intrinsics(fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), width=w, height=h), assumed
    except ValueError as e:  # already excluded by service.numbers; kept as a 422, never a 500
        raise ApiError(422, f"invalid intrinsics: {e}") from None


def client_up(numbers: dict) -> tuple[tuple[float, float, float] | None, float]:
    """(the request's ``up_x``, ``up_y``, ``up_z`` or None, the roll in radians that levels the
    camera: ``vgq.camera.level_roll``). 422 naming the field when only some are given or the
    vector is zero."""
    names = ("up_x", "up_y", "up_z")
    vals = [numbers.get(k) for k in names]
    if all(v is None for v in vals):
        return None, 0.0
    missing = [k for k, v in zip(names, vals) if v is None]
    if missing:
        raise ApiError(
            422,
            f"field {missing[0]}: the up direction needs all three of up_x, up_y, up_z "
            "(the world's up in the camera frame), or none",
            {"field": missing[0]},
        )
    try:
        return (float(vals[0]), float(vals[1]), float(vals[2])), level_roll(vals)
    except ValueError as e:
        raise ApiError(422, f"field up_x: {e}", {"field": "up_x"}) from None


def level_and_up() -> ApiError:
    """The 422 for a request with both ``level=table`` and ``up_x``, ``up_y``, ``up_z``."""
    return ApiError(
        422, "field level: give level=table or up_x, up_y, up_z (the up direction), not both", {"field": "level"}
    )


def client_level(numbers: dict, depth: np.ndarray, camera: Intrinsics) -> tuple[tuple | None, float, str | None]:
    """(up or None, roll in radians, where up came from: "client", "table" or None) of a request:
    ``up_x``, ``up_y``, ``up_z`` as sent (:func:`client_up`), or with ``level`` "table" read from
    the table plane of ``depth`` (H, W, metres) seen by ``camera`` (:func:`planning.level.table_level`).
    422 (field ``level``) for both at once, or when the image shows no table."""
    up, roll = client_up(numbers)
    if numbers.get("level") != "table":
        return up, roll, None if up is None else "client"
    if up is not None:
        raise level_and_up()
    from planning.level import PARAMS, table_level  # the planner's table fit (numpy + SciPy)

    found = table_level(depth, camera)
    if found is None:
        raise ApiError(
            422,
            f"field level: level=table found no table in the image (no plane holds {PARAMS.min_table_fraction:.0%} "
            "of its valid pixels); send the world's up direction in the camera frame (up_x, up_y, up_z) instead",
            {"field": "level"},
        )
    return tuple(float(x) for x in found.up), found.roll, "table"


def focal_range(model: Intrinsics) -> dict:
    """Focal lengths (px) this model serves, per axis: the image is resampled by model / camera."""
    lo, hi = FOCAL_RATIO_RANGE
    return {"fx": [model.fx / hi, model.fx / lo], "fy": [model.fy / hi, model.fy / lo]}


def check_resampled_side(camera: Intrinsics, model: Intrinsics, max_side: int, roll: float = 0.0) -> None:
    """422 (field ``fx``) when ``camera``'s image resampled to ``model``'s focal lengths would
    exceed ``max_side`` px a side (a camera with a shorter focal length is resampled up: the
    bound on uploads holds for what is computed on), or (field ``up_x``) when turning it level
    by ``roll`` radians would. CameraMismatch when the model cannot serve the camera."""
    sx, sy = check_client_intrinsics(camera, model)
    dst = resampled_intrinsics(camera, sx, sy)
    lev = leveled_intrinsics(dst, roll)
    for img, what, field in (
        (dst, "resampled to the model's focal length", "fx"),
        (lev, f"turned level (roll {degrees(roll):.1f} deg)", "up_x"),
    ):
        if max(img.width, img.height) > max_side:
            raise ApiError(
                422,
                f"the image {what} would be {img.width}x{img.height} px, over max_image_side {max_side}; "
                "send a smaller image",
                {"field": field},
            )


def to_model_camera(
    depth: np.ndarray,
    camera: Intrinsics,
    model: Intrinsics,
    max_side: int,
    assumed: tuple[str, ...] = (),
    roll: float = 0.0,
) -> tuple[np.ndarray, Intrinsics]:
    """(depth at the model's focal lengths, turned level by ``roll`` radians, its intrinsics);
    422 naming the field the model cannot serve (focal length outside the range, principal
    point outside the image) or when the image computed on would exceed ``max_side``."""
    try:
        check_resampled_side(camera, model, max_side, roll)
        return level_depth(*resample_depth(depth, camera, model), roll)
    except CameraMismatch as e:
        field, note = e.field, ""
        if field in assumed and field in ("fx", "fy"):  # derived from the other one, which is what was sent
            field = "fy" if field == "fx" else "fx"
            note = f" ({e.field} was not given and is derived from {field})"
        raise ApiError(422, f"field {field}: {e}{note}", {"field": field}) from None
