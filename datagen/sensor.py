"""Depth-sensor model: what a real structured-light / stereo depth camera makes of a
rendered depth image. Applied by the crop stage (``datagen crops --sensor``), seeded per
image, so one rendered dataset gives many corrupted variants.

Effects, in the order applied to a clean depth image ``z`` (H, W) metres, 0 = no surface:

1. missing pixels (read 0) computed from the clean geometry:
   * occlusion shadows: pixels a projector offset by ``baseline_m`` along the camera +x
     axis (-x if negative) cannot light: with disparity d = fx * b / z, pixel u of a row maps
     to projector column u - d; it is shadowed if some pixel further along +u maps to a
     smaller projector column (a nearer surface blocks the projector's ray);
   * depth discontinuities (jump edges): both pixels of each 4-neighbour pair whose depth
     step exceeds ``edge_jump_m`` and whose 3-D segment lies within ``edge_angle_deg`` of the
     viewing ray (|dz| > z / (f tan angle): a jump, not a steep surface; 5 deg marks ~0.3% of
     a rendered scene, its object outlines), widened to ``edge_width_px`` px, and pixels next
     to no surface; each dropped with probability ``edge_dropout``;
   * dropout blobs: Poisson(``blob_rate``) ellipses per image, semi-axes uniform in
     ``blob_radius_px``, random orientation (dark or shiny spots);
2. a multiplicative depth-scale error per image, Gamma(k, 1/k) with k = ``gamma_shape``
   (mean 1, std 1 / sqrt(k)); Dex-Net 2.0 trains with k = 1000;
3. spatially correlated noise (with probability ``gp_rate``): N(0, ``gp_sigma_m``) on a
   grid ``gp_cell_px`` times coarser than the image, upsampled bicubically, as Dex-Net 2.0
   trains with (sigma 0.005 m, factor 4, rate 0.5);
4. per-pixel Gaussian noise growing with depth: sigma(z) = ``noise_base_m`` +
   ``noise_quad_m`` * z^2 (z in metres);
5. quantisation to ``quantum_m`` (1 mm: 16-bit millimetre sensors).

Every draw comes from the ``numpy.random.Generator`` passed in; everything is vectorised
(numpy, OpenCV). :data:`PRESETS` holds ``clean`` (identity) and ``realistic`` (default).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vgq.camera import DEFAULT_INTRINSICS, Intrinsics


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the depth-sensor model (metres, pixels, probabilities). All zero =
    clean. Invalid values raise ValueError naming the field."""

    gamma_shape: float = 0.0  # per-image scale error Gamma(k, 1/k); 0 = off
    gp_sigma_m: float = 0.0  # correlated noise std, metres; 0 = off
    gp_cell_px: float = 4.0  # coarse grid cell of the correlated noise, px (>= 1)
    gp_rate: float = 0.0  # probability that an image gets correlated noise
    noise_base_m: float = 0.0  # per-pixel noise std at z = 0, metres
    noise_quad_m: float = 0.0  # per-pixel noise std growth: + noise_quad_m * z^2 (z metres)
    baseline_m: float = 0.0  # projector offset along camera +x (negative: -x), metres; 0 = no shadows
    edge_jump_m: float = 0.0  # smallest depth step of a discontinuity, metres
    edge_angle_deg: float = 5.0  # a step whose 3-D segment is within this angle of the viewing ray is a jump
    edge_width_px: int = 1  # width of the dropped band on each side of a jump, px
    edge_dropout: float = 0.0  # probability that a discontinuity pixel reads 0
    blob_rate: float = 0.0  # expected dropout blobs per image (Poisson)
    blob_radius_px: tuple[float, float] = (2.0, 6.0)  # blob semi-axis range, px
    quantum_m: float = 0.0  # depth quantisation step, metres; 0 = off

    def __post_init__(self) -> None:
        def bad(name: str, rule: str) -> None:
            raise ValueError(f"sensor.{name} must be {rule}, got {getattr(self, name)!r}")

        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            vals = v if isinstance(v, tuple) else (v,)
            if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in vals):
                bad(f.name, "a finite number" + (" pair" if isinstance(v, tuple) else ""))
        for name in (
            "gamma_shape",
            "gp_sigma_m",
            "noise_base_m",
            "noise_quad_m",
            "edge_jump_m",
            "blob_rate",
            "quantum_m",
        ):
            if getattr(self, name) < 0:
                bad(name, ">= 0")
        if 0 < self.gamma_shape < 10:
            bad("gamma_shape", "0 (off) or >= 10 (scale std <= 32%)")
        for name in ("gp_rate", "edge_dropout"):
            if not 0 <= getattr(self, name) <= 1:
                bad(name, "a probability in [0, 1]")
        if not 0 < self.edge_angle_deg <= 45:
            bad("edge_angle_deg", "in (0, 45] degrees")
        if self.gp_cell_px < 1:
            bad("gp_cell_px", ">= 1")
        if abs(self.baseline_m) > 1:
            bad("baseline_m", "in [-1, 1] metres")
        if not isinstance(self.edge_width_px, int) or not 1 <= self.edge_width_px <= 10:
            bad("edge_width_px", "an integer in [1, 10]")
        if self.blob_rate > 1000:
            bad("blob_rate", "<= 1000 blobs per image")
        r = self.blob_radius_px
        if len(r) != 2 or not 0.5 <= r[0] <= r[1] <= 100:
            bad("blob_radius_px", "a pair [lo, hi] with 0.5 <= lo <= hi <= 100 px")
        if self.quantum_m > 0.05:
            bad("quantum_m", "<= 0.05 metres")
        if self.noise_base_m > 0.1 or self.noise_quad_m > 0.1 or self.gp_sigma_m > 0.1:
            raise ValueError("sensor noise levels (noise_base_m, noise_quad_m, gp_sigma_m) must be <= 0.1 m")

    @property
    def is_clean(self) -> bool:
        return self == CLEAN

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["blob_radius_px"] = list(self.blob_radius_px)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SensorModel:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown sensor setting {unknown[0]!r}; known: {', '.join(sorted(known))}")
        kw = dict(d)
        if "blob_radius_px" in kw:
            r = kw["blob_radius_px"]
            if not isinstance(r, (list, tuple)):
                raise ValueError(f"sensor.blob_radius_px must be a pair [lo, hi], got {r!r}")
            kw["blob_radius_px"] = tuple(r)
        return cls(**kw)

    def with_overrides(self, overrides: dict) -> SensorModel:
        """A copy with fields replaced (``{"baseline_m": 0.05}``), validated."""
        return SensorModel.from_dict({**self.to_dict(), **overrides})

    # ---------------------------------------------------------------- application
    def apply(self, depth: np.ndarray, rng: np.random.Generator, intr: Intrinsics = DEFAULT_INTRINSICS) -> np.ndarray:
        """The sensor's reading (H, W) float32 metres of the clean depth image ``depth``
        (H, W) metres (0 = no surface), 0 where the sensor returns no reading. ``intr``:
        the camera's intrinsics (fx for the shadow disparity)."""
        return self.read(depth, rng, intr)[0]

    def read(
        self, depth: np.ndarray, rng: np.random.Generator, intr: Intrinsics = DEFAULT_INTRINSICS
    ) -> tuple[np.ndarray, float]:
        """:meth:`apply`'s reading (the same, for the same ``rng`` state) and the depth scale it
        multiplied the image by (1.0 without ``gamma_shape``): a point at depth z in the clean image
        reads near ``scale * z``, as the image shows it."""
        z = np.asarray(depth, dtype=np.float64)
        if z.ndim != 2:
            raise ValueError(f"depth must be 2-D (H, W), got shape {z.shape}")
        valid = np.isfinite(z) & (z > 0)
        z = np.where(valid, z, 0.0)
        scale = 1.0
        if self.is_clean:
            return z.astype(np.float32), scale
        drop = ~valid
        if self.baseline_m != 0:
            drop |= shadow_mask(z, self.baseline_m, intr.fx)
        if self.edge_dropout > 0:
            edges = discontinuity_mask(z, self.edge_jump_m, self.edge_angle_deg, intr, self.edge_width_px)
            drop |= edges & (rng.random(z.shape) < self.edge_dropout)
        if self.blob_rate > 0:
            drop |= blob_mask(z.shape, self.blob_rate, self.blob_radius_px, rng)
        out = z
        if self.gamma_shape > 0:
            scale = float(rng.gamma(self.gamma_shape, 1.0 / self.gamma_shape))
            out = out * scale
        if self.gp_sigma_m > 0 and rng.random() < self.gp_rate:
            out = out + correlated_noise(z.shape, self.gp_sigma_m, self.gp_cell_px, rng)
        if self.noise_base_m > 0 or self.noise_quad_m > 0:
            out = out + (self.noise_base_m + self.noise_quad_m * out**2) * rng.standard_normal(z.shape)
        if self.quantum_m > 0:
            out = np.round(out / self.quantum_m) * self.quantum_m
        out = np.where(drop | ~(out > 0), 0.0, out)
        return out.astype(np.float32), scale


CLEAN = SensorModel()

#: Named settings. ``realistic``: a PrimeSense-class structured-light sensor at 0.5-1 m
#: (7.5 cm baseline, ~1.5 mm noise at 0.7 m, 1 mm steps) with Dex-Net 2.0's gamma and
#: correlated-noise augmentation.
PRESETS: dict[str, SensorModel] = {
    "clean": CLEAN,
    "realistic": SensorModel(
        gamma_shape=1000.0,
        gp_sigma_m=0.005,
        gp_cell_px=4.0,
        gp_rate=0.5,
        noise_base_m=0.0005,
        noise_quad_m=0.002,
        baseline_m=0.075,
        edge_jump_m=0.005,
        edge_angle_deg=5.0,
        edge_width_px=1,
        edge_dropout=0.5,
        blob_rate=2.0,
        blob_radius_px=(2.0, 6.0),
        quantum_m=0.001,
    ),
}
DEFAULT_PRESET = "realistic"


def resolve(spec: str | SensorModel | dict | None = None, overrides: dict | None = None) -> tuple[str, SensorModel]:
    """(name, model) of a sensor setting: a preset name, a JSON file of fields, a dict, a
    SensorModel or None (the default preset), then ``overrides``. Raises ValueError naming
    the bad setting."""
    if spec is None:
        spec = DEFAULT_PRESET
    if isinstance(spec, SensorModel):
        name, model = "custom", spec
    elif isinstance(spec, dict):
        name, model = "custom", SensorModel.from_dict(spec)
    elif spec in PRESETS:
        name, model = spec, PRESETS[spec]
    elif str(spec).endswith(".json"):
        p = Path(spec)
        if not p.is_file():
            raise ValueError(f"sensor file {p} does not exist")
        try:
            d = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"sensor file {p} is not valid JSON ({e})") from None
        if not isinstance(d, dict):
            raise ValueError(f"sensor file {p} must hold a JSON object of sensor settings")
        base = PRESETS[d.pop("preset", "clean")] if d.get("preset", "clean") in PRESETS else None
        if base is None:
            raise ValueError(f"sensor file {p}: unknown preset {d['preset']!r}; presets: {', '.join(PRESETS)}")
        name, model = p.stem, base.with_overrides(d)
    else:
        raise ValueError(f"unknown sensor preset {spec!r}; use one of {', '.join(PRESETS)} or a .json file")
    if overrides:
        model = model.with_overrides(overrides)
        name = f"{name}+overrides"
    return name, model


def parse_override(s: str) -> tuple[str, object]:
    """``"name=value"`` (value parsed as JSON) -> (name, value); ValueError naming it."""
    name, eq, raw = s.partition("=")
    if not eq or not name.strip():
        raise ValueError(f"sensor override {s!r} must look like name=value")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        raise ValueError(f"sensor.{name.strip()}: cannot parse {raw!r} as a number or JSON value") from None
    return name.strip(), value


def image_rng(seed: int, object_id: int, image_index: int) -> np.random.Generator:
    """The sensor's random stream for one image of a dataset: seeded by (dataset seed,
    object id, image row), independent of every other image and of the crop windows."""
    return np.random.default_rng([int(seed), 0x5E4502, int(object_id), int(image_index)])


# --------------------------------------------------------------------------- effects


def shadow_mask(z: np.ndarray, baseline_m: float, fx: float) -> np.ndarray:
    """Pixels (H, W) bool that a projector offset by ``baseline_m`` along the camera +x axis
    (-x if negative) cannot see, for depth ``z`` (H, W) metres (0 = no surface, never an
    occluder). Rows are the epipolar lines (rectified camera-projector pair)."""
    z = np.asarray(z, dtype=np.float64)
    if baseline_m == 0:
        return np.zeros(z.shape, dtype=bool)
    flip = baseline_m < 0
    zz = z[:, ::-1] if flip else z
    w = zz.shape[1]
    with np.errstate(divide="ignore"):
        up = np.where(zz > 0, np.arange(w, dtype=np.float64)[None, :] - fx * abs(baseline_m) / zz, np.inf)
    # smallest projector column among the pixels strictly to the right (+u) of each pixel
    after = np.full_like(up, np.inf)
    after[:, :-1] = np.minimum.accumulate(up[:, :0:-1], axis=1)[:, ::-1]
    shadow = (after < up - 1e-6) & (zz > 0)
    return shadow[:, ::-1] if flip else shadow


def discontinuity_mask(
    z: np.ndarray, jump_m: float, angle_deg: float = 5.0, intr: Intrinsics = DEFAULT_INTRINSICS, width_px: int = 1
) -> np.ndarray:
    """Jump-edge pixels (H, W) bool of depth ``z`` (H, W) metres (0 = no surface): both pixels
    of every 4-neighbour pair with |dz| > max(``jump_m``, z_near / (f tan ``angle_deg``)),
    i.e. whose 3-D segment lies within ``angle_deg`` of the viewing ray, plus surface pixels
    next to no surface; widened to ``width_px`` px on each side."""
    z = np.asarray(z, dtype=np.float64)
    valid = z > 0
    m = np.zeros(z.shape, dtype=bool)
    for axis, f in ((1, intr.fx), (0, intr.fy)):
        a, b = (z[:, 1:], z[:, :-1]) if axis == 1 else (z[1:], z[:-1])
        va, vb = (valid[:, 1:], valid[:, :-1]) if axis == 1 else (valid[1:], valid[:-1])
        thr = np.maximum(jump_m, np.minimum(a, b) / (f * np.tan(np.radians(angle_deg))))
        jump = (va & vb & (np.abs(a - b) > thr)) | (va != vb)
        if axis == 1:
            m[:, 1:] |= jump
            m[:, :-1] |= jump
        else:
            m[1:] |= jump
            m[:-1] |= jump
    if width_px > 1:
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * width_px - 1, 2 * width_px - 1))
        m = cv2.dilate(m.view(np.uint8), k).astype(bool)
    return m & valid


def blob_mask(
    shape: tuple[int, int], rate: float, radius_px: tuple[float, float], rng: np.random.Generator
) -> np.ndarray:
    """Dropout blobs (H, W) bool: Poisson(``rate``) filled ellipses, centres uniform over the
    image, semi-axes uniform in ``radius_px``, orientation uniform."""
    h, w = shape
    n = int(rng.poisson(rate))
    m = np.zeros((h, w), dtype=np.uint8)
    if n == 0:
        return m.astype(bool)
    cu, cv = rng.uniform(0, w, n), rng.uniform(0, h, n)
    axes = rng.uniform(radius_px[0], radius_px[1], (n, 2))
    angle = rng.uniform(0, 180, n)
    for i in range(n):  # a handful of blobs; each drawn by OpenCV
        cv2.ellipse(
            m, ((float(cu[i]), float(cv[i])), (float(2 * axes[i, 0]), float(2 * axes[i, 1])), float(angle[i])), 1, -1
        )
    return m.astype(bool)


def correlated_noise(shape: tuple[int, int], sigma_m: float, cell_px: float, rng: np.random.Generator) -> np.ndarray:
    """Spatially correlated noise (H, W) metres: N(0, ``sigma_m``) on a grid ``cell_px``
    times coarser, upsampled bicubically (Dex-Net 2.0's Gaussian-process noise)."""
    h, w = shape
    gh, gw = max(1, round(h / cell_px)), max(1, round(w / cell_px))
    coarse = rng.normal(0.0, sigma_m, (gh, gw)).astype(np.float32)
    return cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.float64)


def missing_fraction(depth: np.ndarray) -> float:
    """Fraction of pixels that read no depth (0 or non-finite)."""
    d = np.asarray(depth)
    return float(np.mean(~(np.isfinite(d) & (d > 0))))


__all__ = [
    "CLEAN",
    "DEFAULT_PRESET",
    "PRESETS",
    "SensorModel",
    "blob_mask",
    "correlated_noise",
    "discontinuity_mask",
    "image_rng",
    "missing_fraction",
    "parse_override",
    "resolve",
    "shadow_mask",
]
