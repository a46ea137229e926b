"""Per-window preprocessing of an uploaded depth image: missing pixels (0 = no reading) are
filled by the shared contract (:func:`vgq.inpaint.crop_filled`, exactly what datagen's crop
stage does to training images), then the window is resized for the encoder. A window that
is mostly missing is refused (422) rather than scored."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vgq.crop import CropGeometry, crop_window
from vgq.inpaint import MARGIN_PX, NoValidDepth, crop_filled, missing_mask

from .errors import ApiError


@dataclass(frozen=True)
class WindowInput:
    image: np.ndarray  # (out, out) float32 metres, every pixel finite and > 0
    center: np.ndarray  # (2,) float64 window centre, image px (u, v)
    missing_fraction: float  # fraction of the window's pixels that had no reading


def window_missing(depth: np.ndarray, origin_uv, geom: CropGeometry, outside: np.ndarray | None = None) -> float:
    """Share of the pixels of the window at ``origin_uv`` (u, v) of ``depth`` (H, W) metres without
    a reading (0 or non-finite), not counting those ``outside`` (H, W) bool marks as outside the
    camera's image (the corners of a turned canvas: beyond the image, as the edge-replicated
    pixels of a window that leaves an unturned image are)."""
    miss = missing_mask(crop_window(depth, origin_uv, geom))
    if outside is not None:
        miss &= ~crop_window(outside.view(np.uint8), origin_uv, geom).astype(bool)
    return float(miss.mean())


def window_input(
    depth: np.ndarray, origin_uv, geom: CropGeometry, max_missing_fraction: float, outside: np.ndarray | None = None
) -> WindowInput:
    """The encoder input of the window with integer top-left pixel ``origin_uv`` (u, v) of
    ``depth`` (H, W) metres (0 = missing). Raises ApiError 422 when more than
    ``max_missing_fraction`` of the window is missing (:func:`window_missing`; ``outside``: the
    pixels beyond the camera's image, not counted) or no valid pixel is near it."""
    ou, ov = int(origin_uv[0]), int(origin_uv[1])
    where = f"the {geom.window}x{geom.window} px crop window at u {ou}..{ou + geom.window - 1}, v {ov}..{ov + geom.window - 1}"
    try:
        image, center, frac = crop_filled(depth, (ou, ov), geom)
        if outside is not None and frac > 0.0:
            frac = window_missing(depth, (ou, ov), geom, outside)
    except NoValidDepth:
        raise ApiError(
            422,
            f"{where} has no valid depth pixel (all 0 = no reading, also within {MARGIN_PX} px around it)",
            {"missing_fraction": 1.0},
        ) from None
    if frac > max_missing_fraction:
        raise ApiError(
            422,
            f"{100 * frac:.1f}% of {where} has no depth reading (0); at most "
            f"{100 * max_missing_fraction:g}% may be missing (setting max_missing_fraction)",
            {"missing_fraction": frac},
        )
    return WindowInput(image, center, frac)
