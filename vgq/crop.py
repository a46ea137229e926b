"""Crop geometry: how a depth image becomes the network's 32 x 32 input.

One definition, used by datagen's crop stage (training data) and by the service
(uploaded images), so training and serving cannot disagree.

Conventions (image pixels, pixel centres on integer coordinates, u = column, v = row):

* A crop window is ``window`` x ``window`` source pixels whose top-left pixel is the
  integer ``origin`` (ou, ov). Its centre is ``origin + window / 2 - 0.5``.
* The window is resized to ``out`` x ``out`` with Pillow's bilinear filter; ``scale =
  window / out`` must be an integer (96 / 32 = 3).
* A grasp at image pixel (u, v) enters the network as the offset from the window centre
  in *crop* pixels: ``((u, v) - centre) / scale``.
* Parts of the window outside the image are filled by edge replication.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache

import cv2
import numpy as np
from PIL import Image

from .turns import check_turns


@dataclass(frozen=True)
class CropGeometry:
    """Window size (source px), network input size (px) and the training offset range.

    ``kappa_px`` is the largest |offset| of a grasp from the window centre, in *source*
    pixels, that the network was trained on (Fast-VGQ-CNN); 0 means centred crops.
    ``align_jaw``: centred crops turned about the grasp so its in-image jaw axis is horizontal
    (:func:`rotated_crop`, GQ-CNN's input), the pose's orientation expressed in the turned
    camera's frame (:func:`vgq.pose.roll_quaternions` by the jaw angle); a VGQ-CNN probe (the
    paper's VGQ-CNN is centred, not turned), not something the service serves.
    ``jaw_turns`` (Fast-VGQ-CNN): 0, windows of the image as it is; K >= 2, each grasp's window
    is cut from the image turned by the multiple of pi / K nearest its jaw angle
    (:mod:`vgq.turns`), so windows stay shared by the grasps of one turn.
    """

    window: int = 96
    out: int = 32
    kappa_px: float = 36.0
    align_jaw: bool = False
    jaw_turns: int = 0

    def __post_init__(self) -> None:
        if self.window <= 0 or self.out <= 0:
            raise ValueError(f"window and out must be > 0, got {self.window}, {self.out}")
        if self.window % self.out != 0:
            raise ValueError(f"window ({self.window}) must be a multiple of out ({self.out})")
        if not (0 <= self.kappa_px <= self.window / 2):
            raise ValueError(f"kappa_px must be in [0, window/2], got {self.kappa_px}")
        if self.align_jaw and self.kappa_px != 0:
            raise ValueError(f"align_jaw crops are centred on their grasp (kappa_px 0), got kappa_px {self.kappa_px}")
        check_turns(self.jaw_turns)
        if self.jaw_turns and self.align_jaw:
            raise ValueError(
                "jaw_turns and align_jaw exclude each other (windows turned by steps, or crops turned exactly)"
            )

    @property
    def scale(self) -> int:
        return self.window // self.out

    def to_dict(self) -> dict:
        """``window``, ``out``, ``kappa_px`` and, only when set, ``align_jaw`` and ``jaw_turns``
        (so the geometry of every unturned dataset, checkpoint and card reads as it always has)."""
        d = asdict(self)
        for k in ("align_jaw", "jaw_turns"):
            if not d[k]:
                del d[k]
        return d

    def turning(self) -> str:
        """How crops are turned, in words (for messages): "not turned", "turned to the jaw axis"
        or "turned in K steps"."""
        if self.align_jaw:
            return "turned to the jaw axis"
        return f"turned in {self.jaw_turns} steps" if self.jaw_turns else "not turned"

    @classmethod
    def from_dict(cls, d: dict) -> CropGeometry:
        return cls(
            window=int(d["window"]),
            out=int(d["out"]),
            kappa_px=float(d["kappa_px"]),
            align_jaw=bool(d.get("align_jaw", False)),
            jaw_turns=int(d.get("jaw_turns", 0)),
        )


def window_origin(center_uv, geom: CropGeometry) -> np.ndarray:
    """Integer top-left pixel (n, 2) of windows whose centres are nearest to ``center_uv`` (n, 2)."""
    c = np.asarray(center_uv, dtype=np.float64)
    return np.floor(c - geom.window / 2 + 0.5 + 0.5).astype(np.int64)


def origin_range(grasp_uv, geom: CropGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest integer window origins (n, 2) (float arrays) whose windows' centres lie
    within +/- ``geom.kappa_px`` (per axis) of grasps at ``grasp_uv`` (n, 2): the windows that
    hold each grasp as training placed it (empty where lo > hi)."""
    g = np.asarray(grasp_uv, dtype=np.float64).reshape(-1, 2)
    half = geom.window / 2 - 0.5  # centre = origin + half
    return np.ceil(g - half - geom.kappa_px - 1e-9), np.floor(g - half + geom.kappa_px + 1e-9)


def window_center(origin_uv, geom: CropGeometry) -> np.ndarray:
    """Centre (image px) of windows with top-left pixel ``origin_uv``."""
    return np.asarray(origin_uv, dtype=np.float64) + geom.window / 2 - 0.5


def crop_window(depth: np.ndarray, origin_uv, geom: CropGeometry) -> np.ndarray:
    """The ``window`` x ``window`` block of ``depth`` (H, W) at integer ``origin_uv`` (u, v),
    edge-replicated where it leaves the image."""
    h, w = depth.shape
    ou, ov = int(origin_uv[0]), int(origin_uv[1])
    rows = np.clip(np.arange(ov, ov + geom.window), 0, h - 1)
    cols = np.clip(np.arange(ou, ou + geom.window), 0, w - 1)
    if rows[0] == ov and rows[-1] == ov + geom.window - 1 and cols[0] == ou and cols[-1] == ou + geom.window - 1:
        return np.ascontiguousarray(depth[ov : ov + geom.window, ou : ou + geom.window], dtype=np.float32)
    return np.ascontiguousarray(depth[np.ix_(rows, cols)], dtype=np.float32)


def resize(window_img: np.ndarray, out: int) -> np.ndarray:
    """Bilinear resize (Pillow, mode F) of a square float image to ``out`` x ``out``."""
    img = Image.fromarray(np.ascontiguousarray(window_img, dtype=np.float32))
    return np.asarray(img.resize((out, out), Image.Resampling.BILINEAR), dtype=np.float32)


def crop(depth: np.ndarray, center_uv, geom: CropGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Crop the window nearest to ``center_uv`` and resize it.

    Returns ``(image (out, out) float32, actual window centre (2,) in image px)``.
    """
    origin = window_origin(center_uv, geom)
    return resize(crop_window(depth, origin, geom), geom.out), window_center(origin, geom)


CONTEXT_SCALES = (0, 2, 3, 4)  # a context view's window in windows (0: none)


def context_geometry(geom: CropGeometry, scale: int) -> CropGeometry:
    """The context view of ``geom``'s windows: ``scale`` times as wide (source px), resized to the
    same ``out`` px, centred on the same point (so a grasp's offset in it is the pose's (u, v) /
    ``scale`` crop px)."""
    if scale not in CONTEXT_SCALES[1:]:
        raise ValueError(f"context scale must be one of {CONTEXT_SCALES[1:]}, got {scale}")
    return CropGeometry(window=geom.window * scale, out=geom.out, kappa_px=0)


def context_crops(filled: np.ndarray, origins_uv, geom: CropGeometry, ctx: CropGeometry) -> np.ndarray:
    """The context views (k, out, out) float32 metres of ``geom``'s windows at integer top-left
    ``origins_uv`` (k, 2) in one image: for each, the ``ctx`` window (:func:`context_geometry`) with
    the same centre, cut from the whole image with its missing pixels already filled (``filled``
    (H, W), :func:`vgq.inpaint.fill_nearest`), edge-replicated outside it, each output pixel the mean
    of a ``ctx.scale`` x ``ctx.scale`` block (OpenCV's area resize)."""
    o = np.asarray(origins_uv, dtype=np.int64).reshape(-1, 2) - (ctx.window - geom.window) // 2
    h, w = filled.shape
    out = np.empty((len(o), ctx.out, ctx.out), dtype=np.float32)
    if not len(o):
        return out
    pad = int(max(0, -o.min(), (o[:, 0] + ctx.window - w).max(), (o[:, 1] + ctx.window - h).max()))
    src = np.ascontiguousarray(filled, dtype=np.float32)
    if pad:
        src = cv2.copyMakeBorder(src, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    for i, (ou, ov) in enumerate(o + pad):
        out[i] = cv2.resize(
            src[ov : ov + ctx.window, ou : ou + ctx.window], (ctx.out, ctx.out), interpolation=cv2.INTER_AREA
        )
    return out


def pose_uv(grasp_uv, window_centre_uv, geom: CropGeometry) -> np.ndarray:
    """Network (u, v) inputs: grasp offsets (n, 2) from the window centre in crop pixels."""
    return (np.asarray(grasp_uv, dtype=np.float64) - np.asarray(window_centre_uv, dtype=np.float64)) / geom.scale


def in_training_range(grasp_uv, window_centre_uv, geom: CropGeometry) -> np.ndarray:
    """Boolean (n,): grasps within +/- kappa_px (source px, per axis) of the window centre."""
    off = np.abs(np.asarray(grasp_uv, dtype=np.float64) - np.asarray(window_centre_uv, dtype=np.float64))
    return np.all(off <= geom.kappa_px + 1e-9, axis=-1)


def grid_window_centers(grasp_uv, image_shape, geom: CropGeometry) -> np.ndarray:
    """Window centres (n, 2) for grasps anywhere in an image: each grasp goes to the nearest
    centre of a fixed grid with spacing ``2 * floor(kappa_px)`` anchored on the image's
    central window, so its offset is within +/- kappa (per axis), as in the training crops,
    and grasps near each other share a window (encoded once). ``image_shape`` is (H, W)."""
    step = 2 * int(geom.kappa_px)  # floor: kappa_px >= 0
    if step < 1:
        raise ValueError(f"a window grid needs kappa_px >= 1 px, got {geom.kappa_px}")
    anchor = np.array(_grid_anchor(int(image_shape[0]), int(image_shape[1]), geom))
    g = np.asarray(grasp_uv, dtype=np.float64).reshape(-1, 2)
    return anchor + np.rint((g - anchor) / step) * step  # rint: np.round to 0 decimals, half to even


@lru_cache(maxsize=256)
def _grid_anchor(h: int, w: int, geom: CropGeometry) -> tuple[float, float]:
    """Centre (u, v) of the central window of an h x w image (image px): the grid's anchor."""
    c = window_center(window_origin([[(w - 1) / 2, (h - 1) / 2]], geom), geom)[0]
    return float(c[0]), float(c[1])


def rotated_crop(depth: np.ndarray, center_uv, angle_rad: float, geom: CropGeometry) -> np.ndarray:
    """GQ-CNN crop: the window centred on ``center_uv`` after rotating the image by
    ``angle_rad`` about that point, so that an in-image grasp axis at ``angle_rad``
    (from the +u axis towards +v) becomes horizontal. Returns (out, out) float32."""
    big = int(np.ceil(geom.window * np.sqrt(2))) + 2
    big += (big - geom.window) % 2  # keep the inner window centred
    c = np.asarray(center_uv, dtype=np.float64)
    origin = np.floor(c - big / 2 + 0.5 + 0.5).astype(np.int64)
    patch = crop_window(depth, origin, CropGeometry(window=big, out=big, kappa_px=0))
    local = c - origin  # centre within the patch
    img = Image.fromarray(patch)
    # PIL rotates counter-clockwise (as displayed) for positive angles; in image coordinates
    # (v down) a grasp axis at +angle (towards +v) is clockwise, so rotate by +angle.
    rot = img.rotate(np.degrees(angle_rad), resample=Image.Resampling.BILINEAR, center=(local[0] + 0.5, local[1] + 0.5))
    rot = np.asarray(rot, dtype=np.float32)
    o = window_origin(local, geom)
    inner = crop_window(rot, o, geom)
    return resize(inner, geom.out)
