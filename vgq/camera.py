"""Pinhole camera model (OpenCV convention: x right, y down, z along the principal ray).

Units: metres for points and depth, pixels for (u, v). Pixel centres sit on integer
coordinates, so the centre of a 300 px wide image is u = 149.5.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from math import atan2, degrees, hypot, pi, radians

import cv2
import numpy as np
from PIL import Image


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth sensor (pixels)."""

    fx: float = 525.0
    fy: float = 525.0
    cx: float = 149.5
    cy: float = 149.5
    width: int = 300
    height: int = 300

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f"intrinsics must be finite, got {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be > 0, got {self.width}x{self.height}")

    @property
    def matrix(self) -> np.ndarray:
        """3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(**{k: d[k] for k in ("fx", "fy", "cx", "cy", "width", "height")})


DEFAULT_INTRINSICS = Intrinsics()


def project(points_cam: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS) -> np.ndarray:
    """Project camera-frame points (n, 3) in metres to (n, 3) rows of (u, v, z)."""
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[:, 0] / z + intr.cx
        v = intr.fy * p[:, 1] / z + intr.cy
    return np.stack([u, v, z], axis=1)


def deproject(uvz: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS) -> np.ndarray:
    """Inverse of :func:`project`: (n, 3) rows of (u, v, z) to camera-frame points (n, 3)."""
    a = np.asarray(uvz, dtype=np.float64).reshape(-1, 3)
    x = (a[:, 0] - intr.cx) * a[:, 2] / intr.fx
    y = (a[:, 1] - intr.cy) * a[:, 2] / intr.fy
    return np.stack([x, y, a[:, 2]], axis=1)


# ----------------------------------------------------------------------------- valid depth

#: Depth beyond this (metres) is no reading: far past any grasp (grasp z is refused above
#: 10 m), and what 16-bit sensors write for "invalid" (65535 mm). A finite but absurd value
#: (1e30 m) would otherwise overflow the encoder.
MAX_DEPTH_M: float = 10.0


def valid_depth(depth: np.ndarray) -> np.ndarray:
    """Boolean mask (same shape) of pixels with a depth reading: finite, > 0 and <= MAX_DEPTH_M
    metres. Everything else is *missing* (0 is how uploads say "no reading")."""
    d = np.asarray(depth)
    with np.errstate(invalid="ignore"):  # NaN and +-inf fail one of the two comparisons: no isfinite needed
        return (d > 0) & (d <= MAX_DEPTH_M)


# ----------------------------------------------------------------------------- resampling

#: Focal lengths a client camera may have, as a ratio of the model's (fx_model / fx_camera):
#: images are resampled by this ratio, so 0.5-2 keeps the resampled image between half and
#: twice the upload's size and the object's scale within what a resize reproduces faithfully.
FOCAL_RATIO_RANGE: tuple[float, float] = (0.5, 2.0)
#: A focal length within this relative tolerance of the model's is used as is (no resampling).
FOCAL_TOLERANCE: float = 0.005
#: A resampled pixel is valid when at least this share of its bilinear weight fell on valid
#: (finite, > 0) source pixels; otherwise it is 0, "no reading".
MIN_VALID_WEIGHT: float = 0.5


class CameraMismatch(ValueError):
    """Camera intrinsics the model cannot be applied to; ``field`` names the offending value."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


def focal_lengths(fx: float | None, fy: float | None, model: Intrinsics) -> tuple[float, float]:
    """A camera's (fx, fy) px from what a client sent: a missing one follows the other at the
    model's pixel aspect; with neither, the model's. (The service's upload, its plan route and
    ``vgq-plan`` all complete a camera so.)"""
    if fx is None:
        fx = model.fx if fy is None else fy * model.fx / model.fy
    if fy is None:
        fy = fx * model.fy / model.fx
    return fx, fy


def check_client_intrinsics(camera: Intrinsics, model: Intrinsics) -> tuple[float, float]:
    """Scale factors (sx, sy) = (model fx / camera fx, model fy / camera fy) that bring an
    image of ``camera`` to the model's focal lengths. Raises :class:`CameraMismatch` when a
    ratio is outside :data:`FOCAL_RATIO_RANGE` or the principal point lies outside the image."""
    lo, hi = FOCAL_RATIO_RANGE
    for name, size in (("cx", camera.width), ("cy", camera.height)):
        c = getattr(camera, name)
        if not (-0.5 <= c <= size - 0.5):
            raise CameraMismatch(name, f"{name} = {c} px lies outside the image (0 to {size - 1} px)")
    ratios = []
    for name in ("fx", "fy"):
        f, fm = getattr(camera, name), getattr(model, name)
        r = fm / f
        if not lo <= r <= hi:
            raise CameraMismatch(
                name,
                f"{name} = {f:g} px is outside the range this model serves: {fm / hi:g} to {fm / lo:g} px "
                f"({lo:g}x to {hi:g}x the model's focal length ratio; the model was trained at {name} = {fm:g} px)",
            )
        ratios.append(1.0 if abs(r - 1.0) <= FOCAL_TOLERANCE else r)
    return ratios[0], ratios[1]


def resampled_intrinsics(camera: Intrinsics, sx: float, sy: float) -> Intrinsics:
    """Intrinsics of ``camera``'s image resized by (sx, sy): pixel centres on integers, so
    an edge at -0.5 px stays at -0.5 px and c' = (c + 0.5) * s - 0.5."""
    w, h = max(1, int(round(camera.width * sx))), max(1, int(round(camera.height * sy)))
    sx_eff, sy_eff = w / camera.width, h / camera.height
    return Intrinsics(
        fx=camera.fx * sx_eff,
        fy=camera.fy * sy_eff,
        cx=(camera.cx + 0.5) * sx_eff - 0.5,
        cy=(camera.cy + 0.5) * sy_eff - 0.5,
        width=w,
        height=h,
    )


def map_pixels(uv: np.ndarray, src: Intrinsics, dst: Intrinsics, roll: float = 0.0) -> np.ndarray:
    """Pixel coordinates (n, 2) of ``src``'s image in ``dst``'s: the same viewing ray, seen by
    a camera of ``dst``'s intrinsics rolled by ``roll`` radians about the optical axis (its
    axes are :func:`roll_matrix` (roll) in ``src``'s frame; 0: the same pose, u' = (u - cx) * fx'
    / fx + cx'). ``map_pixels(uv', dst, src, -roll)`` maps back."""
    a = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    p = np.array([[src.cx, src.cy], [dst.fx, dst.fy], [src.fx, src.fy], [dst.cx, dst.cy]])
    if roll == 0.0:
        return (a - p[0]) * p[1] / p[2] + p[3]  # per column, the same operations in the same order
    c, s = np.cos(roll), np.sin(roll)
    x = (a - p[0]) / p[2]  # normalised image coordinates in src's frame
    xr = np.stack([c * x[:, 0] + s * x[:, 1], -s * x[:, 0] + c * x[:, 1]], axis=1)  # R_z(roll)^T
    return xr * p[1] + p[3]


def resample_depth(depth: np.ndarray, camera: Intrinsics, model: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """Resize a depth image (H, W, metres; :func:`valid_depth` tells readings) taken with
    ``camera`` to ``model``'s focal lengths: returns (depth', intrinsics').

    Depth values are metric and stay as they are; only the pixel grid changes. Bilinear
    (Pillow, antialiased when shrinking) over valid pixels only: a resampled pixel is the
    weighted mean of the valid source pixels under it, and 0 where less than
    :data:`MIN_VALID_WEIGHT` of its weight was valid, so missing readings never blend into
    false depths. An image already at the model's focal lengths comes back unchanged."""
    sx, sy = check_client_intrinsics(camera, model)
    d = np.asarray(depth, dtype=np.float32)
    if d.shape != (camera.height, camera.width):
        raise CameraMismatch(
            "width", f"image is {d.shape[1]}x{d.shape[0]} px but the intrinsics say {camera.width}x{camera.height}"
        )
    if sx == 1.0 and sy == 1.0:
        return d, camera
    dst = resampled_intrinsics(camera, sx, sy)
    valid = valid_depth(d)
    size = (dst.width, dst.height)

    def _resize(a: np.ndarray) -> np.ndarray:
        return np.asarray(Image.fromarray(a).resize(size, Image.Resampling.BILINEAR), dtype=np.float32)

    return valid_weighted(d, valid, _resize), dst


def valid_weighted(depth: np.ndarray, valid: np.ndarray, resample) -> np.ndarray:
    """``resample`` (a linear map of float32 images) applied to the valid readings only: each
    output pixel is the weighted mean of the valid pixels under it, 0 (no reading) where less
    than :data:`MIN_VALID_WEIGHT` of its weight was valid."""
    w = resample(valid.astype(np.float32))
    s = resample(np.where(valid, depth, np.float32(0.0)).astype(np.float32, copy=False))
    out = np.zeros_like(s)
    np.divide(s, w, out=out, where=w >= MIN_VALID_WEIGHT)
    return out


# ----------------------------------------------------------------------------- a level camera

#: A camera rolled by less than this about its optical axis is served as it is, and one this near
#: a quarter or half turn is turned by exactly that (pixels move without resampling) (radians).
ROLL_TOLERANCE: float = radians(0.5)
#: Camera tilts (radians from looking straight down) of the training cameras when a model card
#: does not record its dataset's (``datagen.camera.CameraParams.phi_range``'s default).
DEFAULT_TILT_RANGE: tuple[float, float] = (0.0, radians(70.0))


def level_roll(up) -> float:
    """Roll (radians, -pi to pi) about the optical axis that levels a camera whose frame
    (x right, y down, z along the principal ray) sees the world's up direction (against
    gravity) as ``up`` (3,), any length: the rolled camera's x-axis is horizontal and world up
    points towards -v, as every training camera's (``datagen.camera.look_at_table_origin``).
    0 when the roll is under :data:`ROLL_TOLERANCE` or the camera looks straight down or up
    (any roll is level then); a roll within ROLL_TOLERANCE of a quarter or half turn is that
    turn exactly. ValueError for a zero or non-finite ``up``."""
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.isfinite(u).all():
        raise ValueError(f"up must be 3 finite numbers (camera frame), got {u.tolist()}")
    n = float(np.linalg.norm(u))
    if n == 0.0:
        raise ValueError("up must not be the zero vector")
    if hypot(u[0], u[1]) <= 1e-9 * n:
        return 0.0
    a = atan2(u[0], -u[1])
    turns = round(a / (pi / 2))
    if abs(a - turns * pi / 2) < ROLL_TOLERANCE:
        return turns * (pi / 2) if turns != 0 else 0.0
    return a


def camera_tilt(up) -> float:
    """Angle (radians, 0 to pi) between the principal ray and straight down, for the world's up
    direction ``up`` (3,) in the camera frame (the training cameras' phi: 0 to 70 deg)."""
    u = np.asarray(up, dtype=np.float64).reshape(3)
    return float(np.arccos(np.clip(-u[2] / np.linalg.norm(u), -1.0, 1.0)))


def tilt_outside_training(up, tilt_range: tuple[float, float] = DEFAULT_TILT_RANGE) -> bool:
    """True when the world's up direction ``up`` (3,) in the camera frame (None: unknown, False)
    puts the camera's tilt from straight down outside ``tilt_range`` (radians; a model's:
    ``ModelCard.tilt_range``)."""
    if up is None:
        return False
    lo, hi = tilt_range
    return not lo - 1e-9 <= camera_tilt(up) <= hi + 1e-9


def roll_matrix(roll: float) -> np.ndarray:
    """3 x 3 R_z(roll): the axes (columns) of the camera rolled by ``roll`` radians about its
    optical axis, in the unrolled camera's frame; p_unrolled = R @ p_rolled."""
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def leveled_intrinsics(intr: Intrinsics, roll: float) -> Intrinsics:
    """Intrinsics of the image ``intr``'s camera would take rolled by ``roll`` radians: the same
    focal lengths, on a canvas just large enough to hold the whole rolled image (its principal
    point placed so that the canvas's first row and column touch the rolled image)."""
    if roll == 0.0:
        return intr
    w, h = intr.width, intr.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    origin = Intrinsics(fx=intr.fx, fy=intr.fy, cx=0.0, cy=0.0, width=1, height=1)
    c = map_pixels(corners, intr, origin, roll)  # offsets from the rolled principal point, px
    lo, hi = c.min(axis=0), c.max(axis=0)
    size = np.maximum(1, np.ceil(hi - lo - 1e-6)).astype(int)
    return Intrinsics(
        fx=intr.fx, fy=intr.fy, cx=float(-lo[0] - 0.5), cy=float(-lo[1] - 0.5), width=int(size[0]), height=int(size[1])
    )


def level_depth(depth: np.ndarray, intr: Intrinsics, roll: float) -> tuple[np.ndarray, Intrinsics]:
    """The depth image (H, W, metres; :func:`valid_depth` tells readings) of camera ``intr``
    rolled by ``roll`` radians about its optical axis: (depth', intrinsics'), the whole image
    kept on a larger canvas (:func:`leveled_intrinsics`). Depth is a distance along the optical
    axis, which a roll keeps, so values stay as they are; only the pixel grid turns. Bilinear
    over valid pixels only (as :func:`resample_depth`); the canvas outside the image is 0, no
    reading. A roll of 0 returns the image unchanged; a quarter turn moves pixels exactly."""
    if roll == 0.0:
        return np.asarray(depth, dtype=np.float32), intr
    dst = leveled_intrinsics(intr, roll)
    c, s = np.cos(roll), np.sin(roll)
    ax, ay = intr.fx / intr.fy, intr.fy / intr.fx
    # source pixel of each destination pixel: u - cx = c (u' - cx') - s ax (v' - cy'), v - cy = s ay (u' - cx') + c (v' - cy')
    m = np.array(
        [
            [c, -s * ax, intr.cx - c * dst.cx + s * ax * dst.cy],
            [s * ay, c, intr.cy - s * ay * dst.cx - c * dst.cy],
        ]
    )
    d = np.asarray(depth, dtype=np.float32)
    valid = valid_depth(d)

    def _warp(a: np.ndarray) -> np.ndarray:
        return cv2.warpAffine(
            a,
            m,
            (dst.width, dst.height),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0.0,
        )

    return valid_weighted(d, valid, _warp), dst


def source_pixels(canvas: Intrinsics, camera: Intrinsics, roll: float) -> np.ndarray:
    """(H', W', 2): for each pixel of a level ``canvas`` (:func:`leveled_intrinsics`), the
    (u, v) its viewing ray has in the image of ``camera``, the camera it was turned from by
    ``roll`` radians (outside that image for the canvas's corners)."""
    u, v = np.meshgrid(np.arange(canvas.width, dtype=np.float64), np.arange(canvas.height, dtype=np.float64))
    src = map_pixels(np.stack([u.ravel(), v.ravel()], axis=1), canvas, camera, -roll)
    return src.reshape(canvas.height, canvas.width, 2)


def footprint(canvas: Intrinsics, camera: Intrinsics, roll: float) -> np.ndarray:
    """(H', W') bool: the pixels of a level ``canvas`` whose viewing ray falls inside the image
    of ``camera`` (:func:`source_pixels`)."""
    src = source_pixels(canvas, camera, roll)
    return (src >= -0.5).all(axis=2) & (src[..., 0] <= camera.width - 0.5) & (src[..., 1] <= camera.height - 0.5)


def describe_level(up, roll: float, source: str | None = None) -> dict:
    """What an answer reports of a camera's ``up`` (None: not given, nothing levelled) and where
    it came from (``source``: "client", "table"; default "client" when ``up`` is given)."""
    if up is None:
        return {"up": None, "roll_deg": 0.0, "tilt_deg": None, "from": None}
    return {
        "up": [float(x) for x in np.asarray(up, dtype=np.float64).reshape(3)],
        "roll_deg": degrees(roll),
        "tilt_deg": degrees(camera_tilt(up)),
        "from": source or "client",
    }
