"""The one configuration of dataset generation and sampling: :class:`DatagenConfig`.

It composes the parameter dataclasses of the stages (mesh, antipodal sampler, quality
metric, camera sampler, gripper geometry, sampling) with the run settings. It loads from
a plain JSON file (nested objects per section, unknown keys rejected), takes overrides
of the form ``section.field=value`` (value parsed as JSON, else as a string) and
validates values with errors that name the bad field. Loading, overrides and type
coercion go through the shared bridge ``vgq.cli_config``; the checks here are datagen's
own. Units: metres and radians.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from vgq.camera import DEFAULT_INTRINSICS, Intrinsics
from vgq.cli_config import ConfigError, build, from_dict, load_json_object
from vgq.cli_config import parse_override as parse_override  # datagen's --set KEY=VALUE
from vgq.schema import IMAGE_FIELDS

from .camera import CameraParams
from .collision import RobustCollisionParams
from .grasps import AntipodalParams
from .gripper import GripperGeometry
from .labels import LabelParams
from .mesh import MeshParams
from .physics import PhysicsParams
from .quality import QualityParams
from .sampling import SamplingParams


@dataclass(frozen=True)
class DatagenConfig:
    """Everything that determines a generated dataset (besides the meshes themselves)."""

    mesh: MeshParams = field(default_factory=MeshParams)
    antipodal: AntipodalParams = field(default_factory=AntipodalParams)
    quality: QualityParams = field(default_factory=QualityParams)
    camera: CameraParams = field(default_factory=CameraParams)
    gripper: GripperGeometry = field(default_factory=GripperGeometry)
    intrinsics: Intrinsics = DEFAULT_INTRINSICS
    sampling: SamplingParams = field(default_factory=SamplingParams)
    label: LabelParams = field(default_factory=LabelParams)  # which label becomes `quality` (issue 17)
    collision: RobustCollisionParams = field(default_factory=RobustCollisionParams)  # P(collision-free)
    physics: PhysicsParams = field(default_factory=PhysicsParams)  # physics trials (label.kind "physics")
    cameras_per_pose: int = 10  # camera poses per stable pose (VG-dset: 100, Dex-Net 2.0: 50)
    stable_pose_min_probability: float = 0.01  # keep stable poses with p >= this
    max_stable_poses: int | None = None  # keep at most this many (most probable first)
    seed: int = 0  # run seed; per-object seeds derive from (seed, object name)
    source: str | None = None  # mesh folder; None -> pybullet_data random_urdfs
    num_objects: int | None = None  # first N mesh sources (sorted); None -> all; 0 -> none (families only)
    first_object: int = 0  # skip this many mesh sources (sorted) first: num_objects counts from here
    # procedural objects per family (datagen.families), after the source's objects, e.g. {"mug": 60}
    families: dict[str, int] = field(default_factory=dict, hash=False)

    def to_dict(self) -> dict:
        return _to_jsonable(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, d: dict) -> DatagenConfig:
        cfg = from_dict(cls, d, check=_check_leaf)
        validate(cfg)
        return cfg

    def with_overrides(self, overrides: dict) -> DatagenConfig:
        """A copy with ``{"section.field": value}`` overrides applied (and validated)."""
        cfg = build(DatagenConfig, base=self, overrides=overrides, check=_check_leaf)
        validate(cfg)
        return cfg

    @property
    def label_threshold(self) -> float:
        """A grasp is positive when its ``quality`` (the label's score) exceeds this."""
        if self.label.kind == "physics":
            return float(self.label.success_threshold)
        return float(self.quality.label_threshold)


def recorded_config(d: dict) -> dict:
    """A config dict recorded in a dataset manifest, upgraded for settings added since: a
    dataset without a ``label`` section predates the label setting and has the paper's label;
    one whose ``physics`` lacks ``pad_contact_radius`` ran its trials with rigid point contacts (0)."""
    if not isinstance(d, dict):
        return d
    if "label" not in d:
        d = {**d, "label": {"kind": "paper"}}
    if isinstance(d.get("physics"), dict) and "pad_contact_radius" not in d["physics"]:
        d = {**d, "physics": {**d["physics"], "pad_contact_radius": 0.0}}
    return d


def load_config(path: str | Path) -> DatagenConfig:
    """Load a config from a JSON file; missing keys keep their defaults."""
    p = Path(path)
    d = load_json_object(p)
    try:
        return DatagenConfig.from_dict(d)
    except ConfigError as e:
        raise ConfigError(f"config file {p}: {e}") from e


# ----------------------------------------------------------------------------- building


def _to_jsonable(x):
    if isinstance(x, dict):
        return {k: _to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return x


# ----------------------------------------------------------------------------- validation

_NONNEG_WORDS = ("width", "length", "depth", "thickness", "distance", "radius", "extent", "coef", "sigma", "threshold")


def _leaves(d: dict, prefix: str = ""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", k, v


def _check_leaf(path: str, name: str, v) -> None:
    """Generic checks by field name: finite numbers; counts (num_*, max_*, *_factor) >= 1
    (num_objects >= 0);
    sizes and sigmas >= 0; ranges (*_range) as (low, high) with low <= high."""
    vals = v if isinstance(v, (list, tuple)) else [v]
    for x in vals:
        if isinstance(x, float) and not math.isfinite(x):
            raise ConfigError(f"{path} must be finite, got {x}")
    if isinstance(v, bool) or v is None:
        return
    counts_from = 0 if path == "num_objects" else 1  # num_objects 0: families only
    if isinstance(v, int) and (name.startswith(("num_", "max_")) or name.endswith("_factor")) and v < counts_from:
        raise ConfigError(f"{path} must be >= {counts_from}, got {v}")
    if isinstance(v, (int, float)) and any(w in name for w in _NONNEG_WORDS) and v < 0:
        raise ConfigError(f"{path} must be >= 0, got {v}")
    if name.endswith("_range"):
        if len(vals) != 2:
            raise ConfigError(f"{path} must be (low, high), got {v}")
        if vals[0] > vals[1]:
            raise ConfigError(f"{path} is reversed: low {vals[0]} > high {vals[1]}")


def validate(cfg: DatagenConfig) -> None:
    """Raise :class:`ConfigError` naming the first bad field."""
    for path, name, v in _leaves(dataclasses.asdict(cfg)):
        _check_leaf(path, name, v)
    if cfg.cameras_per_pose < 1:
        raise ConfigError(f"cameras_per_pose must be >= 1, got {cfg.cameras_per_pose}")
    if not 0.0 <= cfg.stable_pose_min_probability <= 1.0:
        raise ConfigError(f"stable_pose_min_probability must be in [0, 1], got {cfg.stable_pose_min_probability}")
    if cfg.max_stable_poses is not None and cfg.max_stable_poses < 1:
        raise ConfigError(f"max_stable_poses must be >= 1 or null, got {cfg.max_stable_poses}")
    if cfg.num_objects is not None and cfg.num_objects < 0:
        raise ConfigError(f"num_objects must be >= 0 or null, got {cfg.num_objects}")
    if isinstance(cfg.first_object, bool) or not isinstance(cfg.first_object, int) or cfg.first_object < 0:
        raise ConfigError(f"first_object must be an integer >= 0, got {cfg.first_object!r}")
    if cfg.families:
        from .families import FAMILIES

        for fam, n in cfg.families.items():
            if fam not in FAMILIES:
                raise ConfigError(f"unknown object family {fam!r} in families (known: {', '.join(FAMILIES)})")
            if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                raise ConfigError(f"families.{fam} must be an object count >= 0, got {n!r}")
    if cfg.num_objects == 0 and not any(cfg.families.values()):
        raise ConfigError("num_objects is 0 and no families are given: the run would have no objects")
    if cfg.seed < 0:
        raise ConfigError(f"seed must be >= 0, got {cfg.seed}")
    d_lo, _ = cfg.camera.d_range
    if d_lo <= 0:
        raise ConfigError(f"camera.d_range must be > 0 m, got {cfg.camera.d_range}")
    phi_lo, phi_hi = cfg.camera.phi_range
    if phi_lo < 0 or phi_hi >= math.pi / 2:
        raise ConfigError(f"camera.phi_range must lie in [0, pi/2) radians, got {cfg.camera.phi_range}")
    if cfg.antipodal.max_width > cfg.gripper.max_width:
        raise ConfigError(
            f"antipodal.max_width ({cfg.antipodal.max_width}) exceeds gripper.max_width ({cfg.gripper.max_width})"
        )
    if cfg.quality.max_width != cfg.antipodal.max_width:
        raise ConfigError(
            f"quality.max_width ({cfg.quality.max_width}) must equal antipodal.max_width ({cfg.antipodal.max_width}): "
            "perturbed grasps re-find their contacts within the sampler's opening"
        )
    shape = IMAGE_FIELDS["depth"][1]
    if (cfg.intrinsics.height, cfg.intrinsics.width) != tuple(shape):
        raise ConfigError(
            f"intrinsics image size {cfg.intrinsics.width}x{cfg.intrinsics.height} must match the dataset "
            f"schema's depth shape {shape[1]}x{shape[0]}"
        )
