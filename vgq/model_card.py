"""Model card: the JSON that travels with exported ONNX graphs (``model_card.json``).

It states everything a consumer needs to feed the graphs correctly: architecture, crop
geometry and intrinsics it was trained for, normalisation (already inside the graphs;
recorded for reference), graph file names and I/O names, dataset and metrics, and the
calibration of its probabilities (``vgq.calibration``; empty when exported without one).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from . import atomic
from .calibration import Calibration
from .camera import DEFAULT_TILT_RANGE, Intrinsics
from .crop import CropGeometry
from .normalization import Normalization

CARD_NAME = "model_card.json"
CARD_FORMAT = "vgq-model-card"
CARD_VERSION = 1

#: ONNX graph I/O names (export writes them, the service reads them).
ENCODER_INPUT = "depth_crop"  # (n, 1, out, out) float32 metres
ENCODER_OUTPUT = "image_term"  # (n, D) float32: the image term (1024), then a jaw-grid head's feature map
HEAD_INPUTS = ("image_term", "poses")  # (1, D), (k, 7) raw pose rows (+ the placement row: card.placement_columns)
HEAD_OUTPUT = "p_success"  # (k,) float32
VGQ_INPUTS = ("depth_crops", "poses")  # (k, 1, out, out), (k, n_pose)
VGQ_OUTPUT = "p_success"


#: z range derived from a card's normalisation when the card records none: mean +/- this many std
Z_RANGE_STDS = 2.0


@dataclass
class ModelCard:
    model_version: str
    architecture: str  # fast_vgqcnn | vgqcnn | gqcnn
    geometry: CropGeometry
    intrinsics: Intrinsics
    normalization: Normalization
    files: dict[str, str]  # role -> file name in the model folder: encoder/head or model
    dataset: dict = field(default_factory=dict)
    training: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    export: dict = field(default_factory=dict)
    label_threshold: float = 0.002
    #: Calibration.to_dict() + how it was fitted and measured (export.calibrate); {} if none
    calibration: dict = field(default_factory=dict)
    #: ``vgq.placement.PLACEMENT_COLUMNS`` when the head reads each grasp's placement row after its
    #: pose columns (computed from the uploaded image by ``planning.placement``); () when it does not
    placement_columns: tuple[str, ...] = ()

    @property
    def head_pose_width(self) -> int:
        """Columns of the head's ``poses`` input: the pose columns, then any placement row."""
        return len(self.normalization.pose_columns) + len(self.placement_columns)

    def z_range(self) -> tuple[tuple[float, float], str]:
        """((z_min, z_max) metres of the grasps the model was trained on, where it comes from):
        the card's ``dataset.z_range`` when recorded, else its pose normalisation (z mean +/-
        :data:`Z_RANGE_STDS` std). The one range the service's and the planner's
        ``z_outside_training_range`` flag use."""
        rec = self.dataset.get("z_range") if isinstance(self.dataset, dict) else None
        if rec is not None and len(rec) == 2:
            return (float(rec[0]), float(rec[1])), "model card dataset.z_range"
        norm = self.normalization
        i = list(norm.pose_columns).index("z")
        m, s = float(norm.pose_mean[i]), float(norm.pose_std[i])
        return (
            m - Z_RANGE_STDS * s,
            m + Z_RANGE_STDS * s,
        ), f"model card normalization: z mean +/- {Z_RANGE_STDS:g} std"

    def tilt_range(self) -> tuple[float, float]:
        """Camera tilts from straight down (radians) the model's training cameras had: its
        dataset's ``camera.phi_range``, else datagen's default (``vgq.camera.DEFAULT_TILT_RANGE``)."""
        try:
            lo, hi = self.dataset["source"]["config"]["camera"]["phi_range"]
            return float(lo), float(hi)
        except (KeyError, TypeError, ValueError):
            return DEFAULT_TILT_RANGE

    def calibrator(self) -> Calibration | None:
        """The map raw P(success) -> calibrated P(success) (None: the card has no calibration)."""
        return Calibration.from_dict(self.calibration) if self.calibration else None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["geometry"] = self.geometry.to_dict()
        d["intrinsics"] = self.intrinsics.to_dict()
        d["normalization"] = self.normalization.to_dict()
        if not self.placement_columns:  # cards of heads without placement read as they always have
            del d["placement_columns"]
        else:
            d["placement_columns"] = list(self.placement_columns)
        d["format"] = CARD_FORMAT
        d["format_version"] = CARD_VERSION
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ModelCard:
        if d.get("format") != CARD_FORMAT:
            raise ValueError(f"not a model card (format {d.get('format')!r}, expected {CARD_FORMAT!r})")
        return cls(
            model_version=str(d["model_version"]),
            architecture=str(d["architecture"]),
            geometry=CropGeometry.from_dict(d["geometry"]),
            intrinsics=Intrinsics.from_dict(d["intrinsics"]),
            normalization=Normalization.from_dict(d["normalization"]),
            files=dict(d["files"]),
            dataset=dict(d.get("dataset", {})),
            training=dict(d.get("training", {})),
            metrics=dict(d.get("metrics", {})),
            export=dict(d.get("export", {})),
            label_threshold=float(d.get("label_threshold", 0.002)),
            calibration=dict(d.get("calibration") or {}),
            placement_columns=tuple(str(c) for c in d.get("placement_columns") or ()),
        )

    def save(self, model_dir: str | Path) -> None:
        atomic.write_json(Path(model_dir) / CARD_NAME, self.to_dict())

    @classmethod
    def load(cls, model_dir: str | Path) -> ModelCard:
        p = Path(model_dir) / CARD_NAME
        if not p.is_file():
            raise FileNotFoundError(f"no {CARD_NAME} in model folder {model_dir}")
        try:
            d = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{p}: not valid JSON ({e})") from e
        return cls.from_dict(d)
