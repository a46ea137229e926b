"""Reading crop datasets (format ``vgq-crops`` v1, see ``vgq.schema``) for training.

A crop dataset is a folder with ``manifest.json`` and one sub-folder per split
(``train``, ``val``, ``test``), each holding one ``<field>.npy`` per ``CROP_FIELDS`` field.
Arrays are memory-mapped; only the rows of a batch are read.

Manifest keys read here (written by ``vgq.schema.write_crop_manifest``, for ``datagen
crops`` and ``training.synthetic.write_crop_dataset`` alike):

* ``format`` == ``"vgq-crops"``, ``format_version`` == 1 (if present);
* ``geometry``: a ``vgq.crop.CropGeometry`` dict (``window``, ``out``, ``kappa_px``);
  a top-level ``kappa_px`` is accepted when the geometry dict lacks it;
* ``architecture`` (or ``arch``): the architecture the crops were cut for;
* optional: ``intrinsics`` (``vgq.camera.Intrinsics`` dict), ``label_threshold``,
  ``counts``, ``native_counts``, ``source`` / ``recipe`` (recorded, not interpreted here;
  export reads ``native_counts`` to calibrate for the positivity before sampling).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from vgq.camera import DEFAULT_INTRINSICS, Intrinsics
from vgq.crop import CropGeometry
from vgq.pose import FULL_POSE_COLUMNS, POSE_COLUMNS, pose_column_indices
from vgq.schema import (
    CROP_EXTRA_FIELDS,
    CROP_FIELDS,
    CROP_FORMAT,
    SPLITS,
    check_extra_fields,
    check_fields,
    read_manifest,
)

from .config import TARGETS


class DatasetError(ValueError):
    """The crop dataset is missing, malformed or unusable for the requested architecture."""


@dataclass
class CropSplit:
    """One split of a crop dataset: memory-mapped arrays, one row per grasp."""

    name: str
    arrays: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(len(self.arrays["labels"]))

    @property
    def labels(self) -> np.ndarray:
        return self.arrays["labels"]

    def poses(self, arch: str) -> np.ndarray:
        """Pose columns of ``arch`` for all rows (n, n_pose) float32 (read into memory)."""
        return np.ascontiguousarray(self.arrays["poses"][:, pose_column_indices(arch)], dtype=np.float32)

    def batch(
        self, index: np.ndarray, arch: str, target: str = "label", placement: bool = False, context: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rows ``index`` as tensors: images (b, 1, S, S) metres (``context``: (b, 2, S, S), each
        window's context view the second channel), poses (b, n_pose) (``placement``:
        (b, n_pose + 7), each row's placement row after its pose columns), and labels (b,)
        int64 (``target`` "label"), the physics label's success rates (b,) float32 in [0, 1]
        (``target`` "success_rate": the crops' ``quality``) or (b, 2) float32 of the label and the
        teacher's score, NaN where it has none (``target`` "teacher": ``arrays["teacher"]``)."""
        if target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
        index = np.asarray(index, dtype=np.int64)
        order = np.argsort(index, kind="stable")  # sorted reads from the memory map are faster
        srt = index[order]
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        img = np.asarray(self.arrays["images"][srt], dtype=np.float32)[inv][:, None]
        if context:
            if "context" not in self.arrays:
                raise DatasetError(
                    f"split {self.name!r} has no context views (context.npy): cut it with datagen crops --context-scale"
                )
            img = np.concatenate([img, np.asarray(self.arrays["context"][srt], dtype=np.float32)[inv][:, None]], 1)
        pose = np.asarray(self.arrays["poses"][srt], dtype=np.float32)[inv][:, pose_column_indices(arch)]
        if placement:
            if "placement" not in self.arrays:
                raise DatasetError(
                    f"split {self.name!r} has no placement rows (placement.npy): crop it again with this datagen"
                )
            pose = np.concatenate([pose, np.asarray(self.arrays["placement"][srt], dtype=np.float32)[inv]], axis=1)
        if target == "success_rate":
            lab = np.clip(np.asarray(self.arrays["quality"][srt], dtype=np.float32)[inv], 0.0, 1.0)
        elif target == "teacher":
            if "teacher" not in self.arrays:
                raise DatasetError(f"split {self.name!r} has no teacher scores attached (training.teacher)")
            lab = np.stack(
                [np.asarray(self.arrays["labels"][srt], dtype=np.float32), np.asarray(self.arrays["teacher"][srt])], 1
            )[inv]
        else:
            lab = np.asarray(self.arrays["labels"][srt], dtype=np.int64)[inv]
        return torch.from_numpy(img), torch.from_numpy(np.ascontiguousarray(pose)), torch.from_numpy(lab)


@dataclass
class CropDataset:
    """An opened crop dataset: manifest facts and its splits."""

    path: Path
    manifest: dict
    geometry: CropGeometry
    arch: str
    intrinsics: Intrinsics
    intrinsics_from_manifest: bool
    label_threshold: float
    splits: dict[str, CropSplit] = field(default_factory=dict)

    def split(self, name: str) -> CropSplit:
        if name not in self.splits:
            raise DatasetError(f"crop dataset {self.path} has no {name!r} split (has {sorted(self.splits)})")
        if len(self.splits[name]) == 0:
            raise DatasetError(f"crop dataset {self.path}: split {name!r} is empty")
        return self.splits[name]

    def counts(self) -> dict[str, dict[str, int]]:
        out = {}
        for name, s in self.splits.items():
            lab = np.asarray(s.labels)
            out[name] = {"n": int(len(lab)), "positive": int(lab.sum())}
        return out

    def info(self) -> dict:
        """Plain-dict facts about the dataset for run metadata and model cards."""
        return {
            "path": str(self.path.resolve()),
            "format": CROP_FORMAT,
            "architecture": self.arch,
            "geometry": self.geometry.to_dict(),
            "label_threshold": self.label_threshold,
            "intrinsics_from_manifest": self.intrinsics_from_manifest,
            "counts": self.counts(),
            "source": self.manifest.get("source"),
            "recipe": self.manifest.get("recipe"),
            "label": self.label_info(),
            "sensor": self.manifest.get("sensor", {"name": "clean"}),
            "z_range": self.z_range(),
        }

    def label_info(self) -> dict:
        """Which label the crops carry: the grasp dataset's ``label`` setting (datagen.labels),
        or the paper's (robust Ferrari-Canny > threshold, nominal collision) for datasets made
        before that setting existed."""
        cfg = (self.manifest.get("source") or {}).get("config") or {}
        label = dict(cfg.get("label") or {"kind": "paper"})
        label["threshold"] = self.label_threshold
        return label

    def object_families(self) -> dict[int, str]:
        """Object id -> family name, from the manifest's source objects ({} when the dataset
        records no family, as crop datasets made before families do)."""
        objs = (self.manifest.get("source") or {}).get("objects") or []
        fams = {int(o["object_id"]): o["family"] for o in objs if o.get("family")}
        return fams

    def z_range(self) -> list[float] | None:
        """[min, max] TCP depth z (metres) of the train split: the range the model was trained on."""
        tr = self.split("train")
        if len(tr) == 0:
            return None
        z = np.asarray(tr.arrays["poses"][:, FULL_POSE_COLUMNS.index("z")], dtype=np.float64)
        return [float(z.min()), float(z.max())]

    def check_arch(self, arch: str) -> None:
        """Raise DatasetError unless crops of this dataset suit ``arch``.

        Same architecture always fits. Centred crops (kappa 0) serve both VGQ-CNN and
        Fast-VGQ-CNN (the paper's kappa = 0 ablation); off-centre crops only Fast-VGQ-CNN;
        GQ-CNN's rotated crops only GQ-CNN, VGQ-CNN's turned ones (``align_jaw``) only VGQ-CNN,
        Fast-VGQ-CNN's windows turned in steps (``jaw_turns``) only Fast-VGQ-CNN.
        """
        if arch not in POSE_COLUMNS:
            raise DatasetError(f"unknown architecture {arch!r}; expected one of {sorted(POSE_COLUMNS)}")
        if arch == self.arch:
            return
        g = self.geometry
        centred = g.kappa_px == 0 and not g.align_jaw and not g.jaw_turns  # turned crops: their own arch only
        if {arch, self.arch} == {"vgqcnn", "fast_vgqcnn"} and centred:
            return
        raise DatasetError(
            f"crop dataset {self.path} was cut for architecture {self.arch!r} "
            f"(kappa_px={g.kappa_px}, {g.turning()}); "
            f"it cannot train {arch!r}"
        )


def _open_split(path: Path, name: str) -> CropSplit | None:
    d = path / name
    if not d.is_dir():
        return None
    arrays = {}
    for f in CROP_FIELDS:
        p = d / f"{f}.npy"
        if not p.is_file():
            raise DatasetError(f"crop dataset {path}: split {name!r} lacks {f}.npy")
        try:
            arrays[f] = np.load(p, mmap_mode="r", allow_pickle=False)
        except ValueError as e:
            raise DatasetError(f"{p}: not a readable .npy array ({e})") from e
    for f in CROP_EXTRA_FIELDS:  # cut since the field exists: read where present
        p = d / f"{f}.npy"
        if p.is_file():
            try:
                arrays[f] = np.load(p, mmap_mode="r", allow_pickle=False)
            except ValueError as e:
                raise DatasetError(f"{p}: not a readable .npy array ({e})") from e
    try:
        n = check_fields(CROP_FIELDS, arrays, f"crop dataset {path} split {name!r}")
        check_extra_fields(arrays, n, f"crop dataset {path} split {name!r}")
    except ValueError as e:
        raise DatasetError(str(e)) from e
    return CropSplit(name, arrays)


def open_crop_dataset(path: str | Path) -> CropDataset:
    """Open and validate a crop dataset folder; raises DatasetError naming the problem."""
    path = Path(path)
    m = read_manifest(path, CROP_FORMAT, DatasetError)
    g = m.get("geometry") or m.get("crop_geometry")
    if not isinstance(g, dict):
        raise DatasetError(f"{path}/manifest.json: no crop 'geometry' entry")
    g = dict(g)
    if "kappa_px" not in g and "kappa_px" in m:
        g["kappa_px"] = m["kappa_px"]
    try:
        geom = CropGeometry.from_dict(g)
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}/manifest.json: bad crop geometry {g} ({e})") from e
    arch = m.get("architecture", m.get("arch"))
    if arch not in POSE_COLUMNS:
        raise DatasetError(
            f"{path}/manifest.json: architecture {arch!r} unknown; expected one of {sorted(POSE_COLUMNS)}"
        )
    if "intrinsics" in m:
        try:
            intr, from_manifest = Intrinsics.from_dict(m["intrinsics"]), True
        except (KeyError, TypeError, ValueError) as e:
            raise DatasetError(f"{path}/manifest.json: bad intrinsics ({e})") from e
    else:
        intr, from_manifest = DEFAULT_INTRINSICS, False
    splits = {}
    for name in SPLITS:
        s = _open_split(path, name)
        if s is not None:
            if s.arrays["images"].shape[1:] != (geom.out, geom.out):
                raise DatasetError(
                    f"crop dataset {path}: images are {s.arrays['images'].shape[1:]}, geometry says {geom.out}"
                )
            splits[name] = s
    if not splits:
        raise DatasetError(f"crop dataset {path} has none of the split folders {SPLITS}")
    return CropDataset(
        path=path,
        manifest=m,
        geometry=geom,
        arch=str(arch),
        intrinsics=intr,
        intrinsics_from_manifest=from_manifest,
        label_threshold=float(m.get("label_threshold", 0.002)),
        splits=splits,
    )
