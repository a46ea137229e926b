"""Run folders, checkpoints and ``load_trained``.

A run folder (``train --out RUN_DIR``)::

    run.json                 arch, config, dataset facts, geometry, intrinsics, training info
    metrics.jsonl            one JSON object per line: {"kind": "train" | "val", ...}
    checkpoints/last.pt      latest state (model, optimizer, position in the data)
    checkpoints/best.pt      the state with the best validation balanced accuracy
    eval/metrics_<split>.json, eval/*.png   written by ``evaluate``

Checkpoints hold only tensors and plain Python containers (config and normalisation as
dicts) so they load with ``torch.load(..., weights_only=True)``; they are written
atomically (``vgq.atomic``), so a kill never leaves a truncated checkpoint.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from vgq import atomic
from vgq.normalization import Normalization

from .networks import ENCODER_LAYERS, GraspQualityNet

CHECKPOINT_FORMAT = "vgq-training-checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(ValueError):
    """A run folder or checkpoint is missing or not one of ours."""


@dataclass(frozen=True)
class RunPaths:
    root: Path

    @property
    def run_json(self) -> Path:
        return self.root / "run.json"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.jsonl"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def last(self) -> Path:
        return self.checkpoints / "last.pt"

    @property
    def best(self) -> Path:
        return self.checkpoints / "best.pt"

    @property
    def eval_dir(self) -> Path:
        return self.root / "eval"

    def eval_metrics(self, split: str) -> Path:
        return self.eval_dir / f"metrics_{split}.json"


def save_checkpoint(path: str | Path, ckpt: dict) -> None:
    """Atomically write ``ckpt`` (tensors and plain containers only)."""
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    atomic.write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | Path) -> dict:
    """Load a checkpoint with ``weights_only=True``; CheckpointError if it is not ours."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for foreign / corrupt files
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} file")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {ckpt.get('version')} unsupported")
    return ckpt


def conv2_channels(ckpt: dict) -> int:
    """The second conv stage's width of a checkpoint's network (64, the paper's, for checkpoints
    written before the option existed)."""
    return int(ckpt.get("config", {}).get("conv2_channels", 64))


def net_options(ckpt: dict) -> dict:
    """The GraspQualityNet options a checkpoint's config records beyond arch and conv2 width
    (the paper's values for checkpoints written before the options existed)."""
    cfg = ckpt.get("config", {})
    return {
        "depth_reference": str(cfg.get("depth_reference", "none")),
        "pose_features": str(cfg.get("pose_features", "raw")),
        "pose_units": int(cfg.get("pose_units", 16)),
        "roi_head": str(cfg.get("roi_head", "none")),
        "roi_units": int(cfg.get("roi_units", 128)),
        "placement": str(cfg.get("placement", "none")) == "image",
        "placement_units": int(cfg.get("placement_units", 0)),
        "context_scale": int(cfg.get("context_scale", 0)),
    }


# a fine-tune may change these: its pose stream, or the jaw-grid head it adds, starts fresh
POSE_STREAM_OPTIONS = (
    "pose_features",
    "pose_units",
    "roi_head",
    "roi_units",
    "placement",
    "placement_units",
    "context_scale",
)
POSE_STREAM_WEIGHTS = ("pc1.weight", "pc1.bias", "fc4_pose.weight")
ROI_WEIGHTS = ("roi_fc1.weight", "roi_fc1.bias", "roi_fc2.weight", "roi_focal_px")
PLACEMENT_WEIGHTS = ("place_fc1.weight", "place_fc1.bias", "place_fc2.weight")
CONTEXT_WEIGHTS = tuple(f"ctx_{n}.{w}" for n in ("conv1", "conv2", "fc1") for w in ("weight", "bias")) + (
    "ctx_fc2.weight",
)


def load_init_weights(net: GraspQualityNet, state: dict) -> list[str]:
    """Copy a fine-tune's initial weights into ``net``; return the names that start fresh.

    Every tensor whose name and shape match is copied. Only the pose stream may differ (a run
    that changes ``pose_features`` or ``pose_units``), or a jaw-grid head be added (``roi_head``;
    its last layer starts at zero, so the fine-tune starts from the initial network) or widened
    (``roi_head`` jaw_depth, ``roi_units``: :func:`_widen_roi`), or a placement stream be added
    (``placement_units``: its last layer starts at zero too), or a context view (``context_scale``: so
    does its): pc1 keeps its fresh initialisation and
    fc4's pose weights start at zero, so the first step's network is the initial one's image
    path with fc4's bias and no pose term, and the pose stream learns from there. CheckpointError
    for any other missing or mismatched tensor."""
    own = net.state_dict()
    state = _widen_pc1(net, state)
    fresh = init_fresh_names(net, state)
    other = [k for k in fresh if k not in POSE_STREAM_WEIGHTS + ROI_WEIGHTS + PLACEMENT_WEIGHTS + CONTEXT_WEIGHTS]
    if other:
        have = tuple(state[other[0]].shape) if other[0] in state else "none"
        raise CheckpointError(
            f"init weights do not fit the network: {other[0]} has {have}, needs {tuple(own[other[0]].shape)}"
        )
    net.load_state_dict({k: v for k, v in state.items() if k in own and k not in fresh}, strict=False)
    with torch.no_grad():
        if "fc4_pose.weight" in fresh:
            net.fc4_pose.weight.zero_()
        if "roi_fc2.weight" in fresh:  # a new jaw-grid head adds nothing until it learns
            net.roi_fc2.weight.zero_()
        if "place_fc2.weight" in fresh:  # so does a new placement stream
            net.place_fc2.weight.zero_()
        if "ctx_fc2.weight" in fresh:  # and a new context view
            net.ctx_fc2.weight.zero_()
        w, mine = state.get("roi_fc1.weight"), own.get("roi_fc1.weight")
        if w is not None and mine is not None and tuple(w.shape) != tuple(mine.shape):
            _widen_roi(net, state, fresh)
    return fresh


def init_fresh_names(net: GraspQualityNet, state: dict) -> list[str]:
    """The names of ``net``'s tensors that an init ``state`` does not hold (by name and shape): the
    layers a fine-tune adds, which start fresh."""
    own = net.state_dict()
    return sorted(k for k in own if k not in state or tuple(state[k].shape) != tuple(own[k].shape))


def freeze_init_layers(net: GraspQualityNet, state: dict) -> list[str]:
    """Stop the gradient of every parameter of ``net`` that the init ``state`` holds (pc1 widened as
    :func:`load_init_weights` widens it): a fine-tune that trains only the layers it adds. Returns the
    names still trained; CheckpointError when none is."""
    fresh = set(init_fresh_names(net, _widen_pc1(net, state)))
    trained = [n for n, p in net.named_parameters() if n in fresh]
    if not trained:
        raise CheckpointError("freeze_init: the network adds no layer to its init, so nothing would train")
    for n, p in net.named_parameters():
        p.requires_grad_(n in fresh)
    return trained


def freeze_encoder_layers(net: GraspQualityNet) -> list[str]:
    """Stop the gradient of the encoder's parameters (:data:`training.networks.ENCODER_LAYERS`): a
    fine-tune of the head alone. Returns the names still trained."""
    for n, p in net.named_parameters():
        if n.split(".")[0] in ENCODER_LAYERS:
            p.requires_grad_(False)
    return [n for n, p in net.named_parameters() if p.requires_grad]


def _widen_pc1(net: GraspQualityNet, state: dict) -> dict:
    """``state`` with pc1 widened by zero columns for placement inputs a fine-tune adds (``net.n_place``
    more inputs than the init's pc1, same width otherwise): the first step's network is the init's."""
    w, mine = state.get("pc1.weight"), net.pc1.weight
    if (
        w is None
        or not net.n_place
        or net.placement_units
        or tuple(w.shape) != (mine.shape[0], mine.shape[1] - net.n_place)
    ):
        return state
    return {**state, "pc1.weight": torch.cat([w, torch.zeros(w.shape[0], net.n_place, dtype=w.dtype)], dim=1)}


def _widen_roi(net: GraspQualityNet, state: dict, fresh: list[str]) -> None:
    """Load a jaw grid into a wider one, the network's function unchanged: more inputs per
    point ("jaw_depth": the init's features first, the new inputs at zero) and / or more hidden
    units (``roi_units``: the init's units first; the new ones keep their fresh inputs and start
    with zero weight into fc4, so they add nothing until they learn). Narrower is an error."""
    w, b, w2 = state["roi_fc1.weight"], state["roi_fc1.bias"], state["roi_fc2.weight"]
    (units, inputs), (my_units, my_inputs) = w.shape, net.roi_fc1.weight.shape
    if units > my_units or inputs > my_inputs:
        raise CheckpointError(
            f"init weights do not fit the network: roi_fc1.weight has {tuple(w.shape)}, needs at most "
            f"{(my_units, my_inputs)} (a jaw grid can be widened, not narrowed)"
        )
    net.roi_fc1.weight[:units] = 0.0
    net.roi_fc1.weight[:units, :inputs] = w
    net.roi_fc1.bias[:units] = b
    net.roi_fc2.weight.zero_()
    net.roi_fc2.weight[:, :units] = w2
    for name in ("roi_fc1.weight", "roi_fc1.bias", "roi_fc2.weight"):
        if name in fresh:
            fresh.remove(name)


def net_from_checkpoint(ckpt: dict) -> GraspQualityNet:
    """A GraspQualityNet in eval mode with the checkpoint's weights and normalisation."""
    net = GraspQualityNet(
        ckpt["arch"],
        image_size=int(ckpt["geometry"]["out"]),
        conv2_channels=conv2_channels(ckpt),
        **net_options(ckpt),
    )
    net.load_state_dict(ckpt["model"])
    net.set_normalization(Normalization.from_dict(ckpt["normalization"]))  # same values; validates
    return net.eval()


def resolve_run(path: Path) -> tuple[Path, Path | None]:
    """(checkpoint file, run folder or None) for a run folder or a checkpoint path."""
    if path.is_dir():
        paths = RunPaths(path)
        for p in (paths.best, paths.last):
            if p.is_file():
                return p, path
        raise CheckpointError(f"run folder {path} has no checkpoints/best.pt or checkpoints/last.pt")
    if path.is_file():
        root = path.parent.parent if path.parent.name == "checkpoints" else None
        return path, root if root is not None and RunPaths(root).run_json.is_file() else None
    raise CheckpointError(f"{path} is neither a run folder nor a checkpoint file")


def _finite(x):
    return None if isinstance(x, float) and not math.isfinite(x) else x


def load_trained(path: str | Path) -> tuple[GraspQualityNet, dict]:
    """Load a trained net from a run folder (its best checkpoint, else the last) or a
    checkpoint file. Returns ``(net in eval mode, meta)``; meta is plain JSON-ready data::

        arch, checkpoint, label_threshold,
        geometry    vgq.crop.CropGeometry dict of the training crops
        intrinsics  vgq.camera.Intrinsics dict (dataset manifest, else the default sensor)
        normalization  vgq.normalization.Normalization dict (also in the net's buffers)
        dataset     path, format, architecture, counts per split, source, recipe
        training    config, samples_seen, steps, seed, wall_time_s, world_size, best validation
        metrics     {split: overall metrics} from ``evaluate`` of this very checkpoint, if any
    """
    ckpt_path, run_dir = resolve_run(Path(path))
    ckpt = load_checkpoint(ckpt_path)
    net = net_from_checkpoint(ckpt)
    st = ckpt["state"]
    meta = {
        "arch": ckpt["arch"],
        "checkpoint": str(ckpt_path.resolve()),
        "label_threshold": ckpt["dataset"].get("label_threshold", 0.002),
        "geometry": dict(ckpt["geometry"]),
        "intrinsics": dict(ckpt["intrinsics"]),
        "normalization": dict(ckpt["normalization"]),
        "dataset": dict(ckpt["dataset"]),
        "training": {
            "config": dict(ckpt["config"]),
            "samples_seen": int(st["samples_seen"]),
            "steps": int(st["step"]),
            "seed": int(ckpt["config"]["seed"]),
            "wall_time_s": float(st["wall_time_s"]),
            "world_size": int(st.get("world_size", 1)),
            "validation": {k: _finite(v) for k, v in dict(ckpt.get("val") or {}).items()},
            "best_val_balanced_accuracy": _finite(st.get("best_val_balanced_accuracy")),
            "torch": torch.__version__,
        },
        "metrics": {},
    }
    if run_dir is not None:
        ev = RunPaths(run_dir).eval_dir
        for f in sorted(ev.glob("metrics_*.json")) if ev.is_dir() else []:
            try:
                m = json.loads(f.read_text())
            except json.JSONDecodeError:
                continue
            same = Path(m.get("checkpoint", "")).resolve() == ckpt_path.resolve()
            if same and m.get("samples_seen") == int(st["samples_seen"]):  # not a stale evaluation
                key = m.get("name") or m.get("split", f.stem[len("metrics_") :])
                meta["metrics"][key] = {
                    **m.get("overall", {}),
                    **({"by_family": m["by_family"]} if m.get("by_family") else {}),
                }
    return net, meta
