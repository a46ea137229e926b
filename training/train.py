"""Training loop: single process by default, DDP (gloo) when launched by ``torchrun``.

The data order is ``DistributedSampler`` over the training split (one replica without
torchrun), reshuffled per epoch with the config's seed, so a resumed run reads exactly the
batches the killed run would have read next. The global batch is ``config.batch_size``,
split evenly over the processes; rank 0 alone writes the run folder.

Fine-tuning (``config.init``) starts a fresh run from a checkpoint's weights and input
normalisation. A mix dataset (``config.mix_data``, e.g. the planner's own candidates) supplies
``config.mix_share`` of every batch, its rows drawn by (seed, step, rank), so a resumed run
draws the same ones; its validation split is logged as ``val_mix``.

The loop state is one :class:`TrainState`; a checkpoint is one dict
(:func:`checkpoint_dict`): weights, optimizer, config, normalisation, that state, dataset facts.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DistributedSampler
from tqdm import tqdm

from vgq import atomic
from vgq.crop import CropGeometry
from vgq.normalization import Normalization
from vgq.pose import POSE_COLUMNS, mirror_poses
from vgq.schema import check_placement_rows, context_scale_of

from . import metrics as M
from .checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    POSE_STREAM_OPTIONS,
    CheckpointError,
    RunPaths,
    conv2_channels,
    freeze_encoder_layers,
    freeze_init_layers,
    load_checkpoint,
    load_init_weights,
    net_options,
    resolve_run,
    save_checkpoint,
)
from .config import TrainConfig
from .data import CropDataset, CropSplit, DatasetError, open_crop_dataset
from .networks import GraspQualityNet
from .predict import predict_split
from .teacher import load_teacher_scores

#: config keys that may change on --resume (they do not change what is learned)
RESUMABLE_CHANGES = {
    "samples",
    "val_every_samples",
    "val_max_samples",
    "checkpoint_every_samples",
    "log_every_steps",
    "eval_batch_size",
    "num_threads",
    "precision",  # the arithmetic of the steps, chosen per machine; weights and optimizer state are fp32
}


def cpu_has_native_bf16() -> bool:
    """Whether this CPU has bf16 matrix instructions (AVX-512 BF16 or AMX-BF16), from /proc/cpuinfo."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(precision: str) -> str:
    """'fp32' or 'bf16' for a TrainConfig.precision ('auto': bf16 on a CPU with native bf16)."""
    if precision == "auto":
        return "bf16" if cpu_has_native_bf16() else "fp32"
    return precision


@dataclass
class TrainResult:
    run_dir: Path
    steps: int
    samples_seen: int
    best_val_balanced_accuracy: float
    last_val: dict
    wall_time_s: float


@dataclass
class TrainState:
    """Where a run stands: the loop state saved in each checkpoint (``ckpt["state"]``).

    ``(epoch, batch_in_epoch)`` is the position in the data order, so a resumed run reads the
    very batches the killed one would have read next. ``wall_time_s`` (seconds) adds up over
    resumes; ``best_val_balanced_accuracy`` (the score ``config.select_on`` names: the validation
    balanced accuracy of ``--data`` unless a mix dataset is selected on) is NaN until a validation
    gives a finite one.
    """

    step: int = 0
    samples_seen: int = 0
    epoch: int = 0
    batch_in_epoch: int = 0
    best_val_balanced_accuracy: float = float("nan")
    best_step: int = -1
    wall_time_s: float = 0.0
    world_size: int = 1

    def advance(self, batch_size: int) -> None:
        """One optimizer step on a global batch of ``batch_size`` samples."""
        self.step += 1
        self.batch_in_epoch += 1
        self.samples_seen += batch_size

    def next_epoch(self) -> None:
        self.epoch += 1
        self.batch_in_epoch = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "checkpoint") -> TrainState:
        """The state as saved by this code or by the dict-based loop before it (same keys,
        checkpoint version 1). CheckpointError naming what is missing or malformed."""
        missing = [k for k in ("step", "samples_seen", "epoch", "batch_in_epoch") if k not in d]
        if missing:
            raise CheckpointError(f"{where}: its training state lacks {missing}; it cannot be resumed")
        kw = {}
        for f in fields(cls):
            if d.get(f.name) is not None:
                try:
                    kw[f.name] = type(f.default)(d[f.name])
                except (TypeError, ValueError) as e:
                    raise CheckpointError(
                        f"{where}: training state {f.name}={d[f.name]!r} is not a number ({e})"
                    ) from e
        return cls(**kw)


@dataclass(frozen=True)
class _Dist:
    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()


def _init_distributed() -> _Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return _Dist()
    if not dist.is_initialized():
        dist.init_process_group(backend="gloo")
    return _Dist(dist.get_rank(), dist.get_world_size())


def _crossed(samples: int, step_samples: int, every: int) -> bool:
    return samples // every > (samples - step_samples) // every


def _val_index(n: int, cfg: TrainConfig) -> np.ndarray:
    if cfg.val_max_samples and cfg.val_max_samples < n:
        rng = np.random.default_rng(cfg.seed + 7919)
        return np.sort(rng.choice(n, cfg.val_max_samples, replace=False))
    return np.arange(n)


def _validate(net: GraspQualityNet, split: CropSplit, cfg: TrainConfig, d: _Dist, bf16: bool = False) -> dict:
    """Validation metrics on ``cfg.val_max_samples`` fixed rows of ``split``, the forward pass in the
    steps' precision (``bf16``; a model selected on it is evaluated and exported in fp32)."""
    idx = _val_index(len(split), cfg)[d.rank :: d.world]
    p, loss = predict_split(net, split, idx, cfg.eval_batch_size, bf16=bf16)
    c = M.confusion(np.asarray(split.labels[idx]), p > 0.5)
    vec = torch.tensor([c["tp"], c["fn"], c["tn"], c["fp"], loss * len(idx)], dtype=torch.float64)
    if d.world > 1:
        dist.all_reduce(vec)
    c = dict(zip(("tp", "fn", "tn", "fp"), (int(round(x)) for x in vec[:4].tolist())))
    out = M.from_confusion(c)
    out["loss"] = float(vec[4]) / max(out["n"], 1)
    return out


def _better(a: float, b: float) -> bool:
    return math.isfinite(a) and (not math.isfinite(b) or a > b)


def _class_weights(split: CropSplit, mix: CropSplit | None = None, mix_share: float = 0.0) -> torch.Tensor:
    """Cross-entropy weights 1 / (2 * class share) of the batches: the training split's shares, or
    with ``mix`` the expected shares of batches holding ``mix_share`` of its rows."""
    pos = float(np.mean(np.asarray(split.labels)))
    if mix is not None:
        pos = (1.0 - mix_share) * pos + mix_share * float(np.mean(np.asarray(mix.labels)))
    if pos == 0 or pos == 1:
        raise DatasetError("class_balance='loss_weights' needs both classes in the training split")
    return torch.tensor([1.0 / (2.0 * (1.0 - pos)), 1.0 / (2.0 * pos)], dtype=torch.float32)


def _family_cells(split: CropSplit, families: dict[int, str]) -> np.ndarray:
    """Draw probabilities (n,) float64 of the train rows under ``sampling`` "family": every (object
    family, label) cell of ``split`` equally likely, the rows within a cell alike. Raises
    DatasetError when the dataset records no families."""
    if not families:
        raise DatasetError("sampling 'family' needs a crop dataset whose manifest records object families")
    ids, row_object = np.unique(np.asarray(split.arrays["object_id"]), return_inverse=True)
    # each object's family name ("": an object without one, a cell of its own), as training.evaluate names them
    _, family = np.unique(np.array([families.get(int(i), "") for i in ids]), return_inverse=True)
    cell = family[row_object] * 2 + (np.asarray(split.labels) > 0)
    counts = np.bincount(cell).astype(np.float64)
    p = 1.0 / counts[cell]
    return p / p.sum()


def _family_order(cfg: TrainConfig, probs: np.ndarray, epoch: int, rank: int, n: int) -> np.ndarray:
    """An epoch's ``n`` rows for process ``rank`` drawn by ``probs`` (with replacement) from a
    stream of (seed, epoch, rank) alone, so a resumed run draws the same rows."""
    return np.random.default_rng((cfg.seed, 0x66616D, epoch, rank)).choice(len(probs), size=n, p=probs)


def _mix_index(cfg: TrainConfig, step: int, rank: int, n_rows: int, k: int) -> np.ndarray:
    """Rows of the mix dataset's train split for optimizer step ``step`` on process ``rank``:
    drawn from a stream of (seed, step, rank) alone, so a resumed run draws the same rows."""
    return np.random.default_rng((cfg.seed, 0x6D6978, step, rank)).integers(0, n_rows, k)


def _mirror_rows(cfg: TrainConfig, batch, step: int, rank: int):
    """``batch`` (images (b, 1, S, S), poses, labels) with a ``cfg.mirror`` share of its rows
    replaced by their left-right mirror images (``vgq.pose.mirror_poses``), the rows drawn from a
    stream of (seed, step, rank) alone, so a resumed run mirrors the same rows."""
    img, pose, lab = batch
    pick = np.random.default_rng((cfg.seed, 0x6D6972, step, rank)).random(len(lab)) < cfg.mirror
    if not pick.any():
        return batch
    idx = torch.from_numpy(np.flatnonzero(pick))
    img, pose = img.clone(), pose.clone()
    img[idx] = torch.flip(img[idx], dims=(-1,))
    n = len(POSE_COLUMNS[cfg.arch])  # a placement row after them is the same in the mirror image
    pose[idx, :n] = torch.from_numpy(mirror_poses(pose[idx, :n].numpy(), POSE_COLUMNS[cfg.arch]).astype(np.float32))
    return img, pose, lab


def _drop_placement(cfg: TrainConfig, batch, step: int, rank: int):
    """``batch`` with a ``cfg.placement_dropout`` share of its rows' placement rows made unknown
    (``vgq.placement.unknown_rows``: what an image without a table gives), drawn from a stream of
    (seed, step, rank) alone, so a resumed run drops the same rows."""
    img, pose, lab = batch
    pick = np.random.default_rng((cfg.seed, 0x706C6163, step, rank)).random(len(lab)) < cfg.placement_dropout
    if not pick.any():
        return batch
    pose = pose.clone()
    pose[torch.from_numpy(np.flatnonzero(pick)), len(POSE_COLUMNS[cfg.arch]) :] = 0.0
    return img, pose, lab


def _selection_score(cfg: TrainConfig, val: dict, val_mix: dict | None) -> float:
    """The balanced accuracy that picks the best checkpoint (``cfg.select_on``)."""
    if cfg.select_on == "data" or val_mix is None:
        return val["balanced_accuracy"]
    if cfg.select_on == "mix":
        return val_mix["balanced_accuracy"]
    return 0.5 * (val["balanced_accuracy"] + val_mix["balanced_accuracy"])


def _trim_log(path: Path, samples: int) -> None:
    """Drop log lines written after the checkpoint we resume from."""
    if not path.is_file():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line).get("samples", 0) <= samples:
                keep.append(line)
        except json.JSONDecodeError:
            pass  # a line cut by the kill
    atomic.write_bytes(path, ("\n".join(keep) + "\n" if keep else "").encode())


def _check_resume_config(saved: dict, cfg: TrainConfig) -> None:
    saved = {**TrainConfig.defaults(), **saved}  # a field newer than the checkpoint had its default
    diff = sorted(k for k, v in cfg.to_dict().items() if k not in RESUMABLE_CHANGES and saved.get(k) != v)
    if diff:
        raise CheckpointError(
            "cannot resume with a different configuration: "
            + ", ".join(f"{k}={cfg.to_dict()[k]!r} (checkpoint: {saved.get(k)!r})" for k in diff)
        )


def _check_resume_dataset(saved: dict, data: CropDataset, mix: CropDataset | None = None) -> None:
    now = data.info()
    for k in ("geometry", "counts", "architecture"):
        if saved.get(k) != now.get(k):
            raise CheckpointError(
                f"cannot resume on a different dataset: {k} is {now.get(k)!r} in {data.path}, "
                f"{saved.get(k)!r} in the checkpoint's dataset {saved.get('path')}"
            )
    if mix is not None and (saved.get("mix") or {}).get("counts") != mix.counts():
        raise CheckpointError(
            f"cannot resume on a different mix dataset: counts {mix.counts()} in {mix.path}, "
            f"{(saved.get('mix') or {}).get('counts')!r} in the checkpoint's"
        )


def _check_target(cfg: TrainConfig, data: CropDataset) -> None:
    """``target`` "success_rate" needs crops whose ``quality`` is the physics label's success rate."""
    info = data.label_info()
    kind = info.get("kind")
    if cfg.target == "success_rate" and kind != "physics":
        raise DatasetError(
            f"target 'success_rate' needs crops with the physics label (trial success rates); {data.path} "
            f"carries the {kind!r} label"
        )
    if cfg.target == "success_rate" and info.get("early_stop"):
        raise DatasetError(
            f"target 'success_rate' needs every grasp's full trials; {data.path} was labelled with "
            "label.early_stop (its rates are over the trials run until the label was decided)"
        )
    if cfg.context_scale:
        have = context_scale_of(data.manifest)
        if have != cfg.context_scale:
            raise DatasetError(
                f"context_scale {cfg.context_scale} needs crops cut with datagen crops --context-scale "
                f"{cfg.context_scale}; {data.path} has {'context views of scale ' + str(have) if have else 'none'}"
            )
    if cfg.placement == "image":
        lacking = [s for s, sp in data.splits.items() if sp is not None and len(sp) and "placement" not in sp.arrays]
        if lacking:
            raise DatasetError(
                f"placement 'image' needs placement rows; {data.path} split {lacking[0]!r} has none "
                "(cropped before them: run datagen crops again)"
            )
        try:
            check_placement_rows(data.manifest, str(data.path))
        except ValueError as e:
            raise DatasetError(str(e)) from None


def _open_data(cfg: TrainConfig, data_dir, d: _Dist) -> tuple[CropDataset, CropSplit, CropSplit]:
    """The crop dataset and its train / val splits, checked to suit ``cfg`` on ``d.world`` processes."""
    data = open_crop_dataset(data_dir)
    data.check_arch(cfg.arch)
    _check_target(cfg, data)
    train_split, val_split = data.split("train"), data.split("val")
    if cfg.target == "teacher":
        train_split.arrays["teacher"] = load_teacher_scores(cfg.teacher, train_split, _class_weights(train_split))
    if cfg.batch_size % d.world:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by the {d.world} processes")
    if len(train_split) < cfg.batch_size:
        raise DatasetError(f"training split has {len(train_split)} rows, fewer than one batch ({cfg.batch_size})")
    n_pos = int(np.asarray(train_split.labels).sum())
    if d.main and n_pos in (0, len(train_split)):
        print(
            f"warning: the training split of {data.path} has only one class "
            f"({n_pos} positive of {len(train_split)}); nothing to learn",
            file=sys.stderr,
        )
    return data, train_split, val_split


def _open_mix(
    cfg: TrainConfig, data: CropDataset, d: _Dist
) -> tuple[CropDataset | None, CropSplit | None, CropSplit | None]:
    """The ``mix_data`` crop dataset and its train / val splits (Nones without one), checked to
    share ``data``'s crop geometry and label threshold (the network's input and label contract)."""
    if not cfg.mix_data:
        return None, None, None
    mix = open_crop_dataset(cfg.mix_data)
    mix.check_arch(cfg.arch)
    _check_target(cfg, mix)
    if mix.geometry != data.geometry:
        raise DatasetError(f"mix dataset {mix.path} has crop geometry {mix.geometry}; {data.path} has {data.geometry}")
    if mix.label_threshold != data.label_threshold:
        raise DatasetError(
            f"mix dataset {mix.path} has label threshold {mix.label_threshold}; {data.path} has {data.label_threshold}"
        )
    cfg.mix_rows(cfg.batch_size // d.world)  # a batch must hold rows of both
    return mix, mix.split("train"), mix.split("val")


def _init_checkpoint(cfg: TrainConfig, data: CropDataset) -> dict:
    """The checkpoint ``cfg.init`` names (a file, or a run folder's best.pt), checked to suit the run."""
    path = Path(cfg.init)
    if (path / "model_card.json").is_file():  # an exported model folder (e.g. the bundled model)
        from export.from_onnx import init_checkpoint_from_model_dir

        ckpt = init_checkpoint_from_model_dir(path)
    else:
        path, _ = resolve_run(path)
        ckpt = load_checkpoint(path)
    if ckpt["arch"] != cfg.arch:
        raise CheckpointError(f"init checkpoint {path} is a {ckpt['arch']} network; this run trains {cfg.arch}")
    init_channels = conv2_channels(ckpt)
    if init_channels != cfg.conv2_channels:
        raise CheckpointError(
            f"init checkpoint {path} has {init_channels} conv2 channels; this run trains {cfg.conv2_channels}"
        )
    for k, v in net_options(ckpt).items():
        if v != getattr(cfg, k) and k not in POSE_STREAM_OPTIONS:  # a new pose stream starts fresh
            raise CheckpointError(f"init checkpoint {path} has {k} {v!r}; this run trains {getattr(cfg, k)!r}")
    if not _same_input(ckpt["geometry"], data.geometry):
        raise CheckpointError(
            f"init checkpoint {path} was trained on crops {ckpt['geometry']}; {data.path} has {data.geometry.to_dict()}"
        )
    return ckpt


def _same_input(init_geometry: dict, geom: CropGeometry) -> bool:
    """Whether a net trained on crops of ``init_geometry`` can start a run on crops of ``geom``: the
    same windows, perhaps turned towards the jaw in other steps (a fine-tune into turned windows)."""
    try:
        return CropGeometry.from_dict({**init_geometry, "jaw_turns": geom.jaw_turns}) == geom
    except ValueError:  # e.g. crops turned to the jaw axis cannot also be turned in steps
        return False


def _checkpoint_to_resume(
    paths: RunPaths, resume: bool, cfg: TrainConfig, data: CropDataset, mix: CropDataset | None = None
) -> dict | None:
    """``last.pt`` when resuming (checked against ``cfg``, ``data`` and ``mix``), None on a fresh start."""
    if not paths.last.is_file():
        return None
    if not resume:
        raise CheckpointError(f"run folder {paths.root} already holds a checkpoint; pass --resume or another --out")
    ckpt = load_checkpoint(paths.last)
    _check_resume_config(ckpt["config"], cfg)
    _check_resume_dataset(ckpt["dataset"], data, mix)
    return ckpt


def _optimizer(cfg: TrainConfig, net: GraspQualityNet) -> torch.optim.Optimizer:
    """The run's optimizer; AdamW's fused CPU kernel (one pass over each parameter: the step 1.07x
    faster end to end on a Zen 4; the same update up to floating-point order). Each parameter group's
    ``lr_scale`` multiplies the schedule's rate (:func:`_sgd_step`): the placement stream's is
    ``cfg.placement_lr_scale``, the context view's ``cfg.context_lr_scale``."""
    named = [
        (n, p) for n, p in net.named_parameters() if p.requires_grad
    ]  # not the layers freeze_init / freeze_encoder hold
    scaled = {"place_": cfg.placement_lr_scale, "ctx_": cfg.context_lr_scale}
    groups = [{"params": [p for n, p in named if not n.startswith(tuple(scaled))], "lr_scale": 1.0}]
    for prefix, scale in scaled.items():
        own = [p for n, p in named if n.startswith(prefix)]
        if own:
            groups.append({"params": own, "lr_scale": scale})
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(groups, lr=cfg.base_lr, weight_decay=cfg.weight_decay, fused=True)
    return torch.optim.SGD(groups, lr=cfg.base_lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


def _start_or_resume(cfg: TrainConfig, data: CropDataset, train_split: CropSplit, ckpt: dict | None, paths: RunPaths):
    """(net with its normalisation, optimizer, Normalization, TrainState, last validation, best validation):
    fresh (normalisation from the training split) or as saved in ``ckpt``."""
    torch.manual_seed(cfg.seed)
    net = GraspQualityNet(
        cfg.arch,
        image_size=data.geometry.out,
        conv2_channels=cfg.conv2_channels,
        depth_reference=cfg.depth_reference,
        pose_features=cfg.pose_features,
        pose_units=cfg.pose_units,
        roi_head=cfg.roi_head,
        roi_units=cfg.roi_units,
        placement=cfg.placement == "image",
        placement_units=cfg.placement_units,
        context_scale=cfg.context_scale,
        roi_focal_px=data.intrinsics.fx * data.geometry.out / data.geometry.window,  # crop px per unit depth
    ).to(memory_format=torch.channels_last)  # oneDNN's convolutions ~1.1x faster (training.bench)
    init = _init_checkpoint(cfg, data) if cfg.init and (ckpt is None or cfg.freeze_init) else None
    if cfg.freeze_init:
        trained = freeze_init_layers(net, init["model"])
        print(f"freeze_init: training {len(trained)} tensors the init lacks, the rest stay", file=sys.stderr)
    if cfg.freeze_encoder:
        trained = freeze_encoder_layers(net)
        print(f"freeze_encoder: training the head's {len(trained)} tensors, the encoder's stay", file=sys.stderr)
    opt = _optimizer(cfg, net)
    best_val: dict = {}
    if ckpt is None and cfg.init:  # fine-tuning: the init's weights and its input normalisation, a fresh optimizer
        fresh = load_init_weights(net, init["model"])
        if fresh:
            print(
                f"fine-tune from {cfg.init}: {', '.join(fresh)} start fresh (layers the init lacks or holds in another shape)",
                file=sys.stderr,
            )
        norm = Normalization.from_dict(init["normalization"])
        state, last_val = TrainState(), {}
    elif ckpt is None:
        norm = Normalization.from_data(
            train_split.arrays["images"], train_split.poses(cfg.arch), net.pose_columns, cfg.depth_reference
        )
        state, last_val = TrainState(), {}
    else:
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        if cfg.optimizer == "adamw":  # a run saved before the fused kernel (its groups say fused None) gets it too
            for g in opt.param_groups:
                g["fused"] = True
        norm = Normalization.from_dict(ckpt["normalization"])
        state, last_val = TrainState.from_dict(ckpt["state"], str(paths.last)), dict(ckpt.get("val") or {})
        if paths.best.is_file():
            best_val = dict(load_checkpoint(paths.best).get("val") or {})
    net.set_normalization(norm)
    return net, opt, norm, state, last_val, best_val


def checkpoint_dict(
    cfg: TrainConfig,
    net: GraspQualityNet,
    opt: torch.optim.Optimizer | None,
    norm: Normalization,
    state: TrainState,
    data_info: dict,
    data: CropDataset,
    val: dict,
) -> dict:
    """The one checkpoint layout (version CHECKPOINT_VERSION): tensors and plain containers
    only, so it loads with ``weights_only=True``. ``opt`` None (best.pt: for evaluation and
    export, never resumed from) stores no optimizer state."""
    return {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "arch": cfg.arch,
        "model": net.state_dict(),
        "optimizer": None if opt is None else opt.state_dict(),
        "config": cfg.to_dict(),
        "normalization": norm.to_dict(),
        "state": state.to_dict(),
        "dataset": data_info,
        "geometry": data.geometry.to_dict(),
        "intrinsics": data.intrinsics.to_dict(),
        "val": M.nan_to_none(val),
    }


def distillation_loss(logits: torch.Tensor, target: torch.Tensor, weights, teacher_weight: float) -> torch.Tensor:
    """``(1 - teacher_weight)`` x the label's cross-entropy + ``teacher_weight`` x the cross-entropy to
    the teacher's soft two-class target (1 - P, P), over the rows it scored (P NaN: none); both terms
    with the class ``weights`` (None: unweighted). ``target`` (b, 2): the label and the teacher's
    posterior P (:func:`training.teacher.load_teacher_scores`). With weights, the soft term's minimum
    is the class-balanced score of the posterior the student can tell, as the label term's is: a
    student fitting balanced scores directly would under-score where it cannot tell what the teacher
    can (the balanced score is concave in the posterior)."""
    label, p = target[:, 0].long(), target[:, 1]
    hard = F.cross_entropy(logits, label, weight=weights)
    scored = torch.isfinite(p)
    p = torch.where(scored, p, torch.zeros_like(p))
    soft = F.cross_entropy(logits, torch.stack([1.0 - p, p], dim=1), weight=weights, reduction="none") * scored
    return (1.0 - teacher_weight) * hard + teacher_weight * soft.sum() / len(label)


def _sgd_step(
    model: torch.nn.Module,
    opt: torch.optim.Optimizer,
    batch,
    lr: float,
    weights,
    bf16: bool = False,
    teacher_weight: float = 0.0,
) -> float:
    """One optimizer step at learning rate ``lr`` on ``(images, poses, labels)``; the loss.
    ``bf16``: forward and backward under CPU bf16 autocast (parameters and optimizer stay fp32).
    Labels (b, 2) (target "teacher"): :func:`distillation_loss` with ``teacher_weight``."""
    for g in opt.param_groups:
        g["lr"] = lr * g.get("lr_scale", 1.0)
    img, pose, lab = batch
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        logits = model(img, pose)
    if lab.dim() == 2:
        loss = distillation_loss(logits.float(), lab, weights, teacher_weight)
    else:
        if lab.is_floating_point():  # success rates: a soft two-class target (1 - r, r)
            lab = torch.stack([1.0 - lab, lab], dim=1)
        loss = F.cross_entropy(logits.float(), lab, weight=weights)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss.item()


class _MetricsLog:
    """``metrics.jsonl`` lines (rank 0 only; other ranks write nothing)."""

    def __init__(self, path: Path, enabled: bool):
        self._f = open(path, "a") if enabled else None

    def write(self, rec: dict) -> None:
        if self._f is not None:
            self._f.write(json.dumps(M.nan_to_none(rec)) + "\n")
            self._f.flush()

    def close(self) -> None:
        if self._f is not None:
            self._f.close()


def train(
    config: TrainConfig,
    data_dir: str | Path,
    run_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
) -> TrainResult:
    """Train ``config.arch`` on the crop dataset ``data_dir`` into the run folder ``run_dir``.

    ``resume``: continue from ``run_dir/checkpoints/last.pt`` (a fresh start when there is
    none). Without it an existing checkpoint is an error. Raises DatasetError /
    CheckpointError (both ValueError) naming the problem.
    """
    d = _init_distributed()
    cfg = config
    data, train_split, val_split = _open_data(cfg, data_dir, d)
    mix, mix_train, mix_val = _open_mix(cfg, data, d)
    paths = RunPaths(Path(run_dir))
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    bf16 = resolve_precision(cfg.precision) == "bf16"
    ckpt = _checkpoint_to_resume(paths, resume, cfg, data, mix)

    net, opt, norm, state, last_val, best_val = _start_or_resume(cfg, data, train_split, ckpt, paths)
    state.world_size = d.world
    model = DistributedDataParallel(net) if d.world > 1 else net
    weights = _class_weights(train_split, mix_train, cfg.mix_share) if cfg.class_balance == "loss_weights" else None
    cells = _family_cells(train_split, data.object_families()) if cfg.sampling == "family" else None
    data_info = data.info()  # counts read once
    if mix is not None:
        data_info["mix"] = mix.info()

    if d.main:
        paths.root.mkdir(parents=True, exist_ok=True)
        _trim_log(paths.metrics, state.samples_seen if ckpt is not None else -1)  # all lines on a fresh start
        atomic.write_json(paths.run_json, _run_info(cfg, data_info, data, norm, state, finished=False, bf16=bf16))
    d.barrier()

    t0, wall0 = time.time(), state.wall_time_s

    def save(path: Path, val: dict, with_optimizer: bool) -> None:
        state.wall_time_s = wall0 + time.time() - t0
        if d.main:
            save_checkpoint(
                path, checkpoint_dict(cfg, net, opt if with_optimizer else None, norm, state, data_info, data, val)
            )

    total_steps = math.ceil(cfg.samples / cfg.batch_size)
    local_batch = cfg.batch_size // d.world
    local_mix = cfg.mix_rows(local_batch)  # of each process's batch, rows of the mix dataset
    local_main = local_batch - local_mix
    sampler = DistributedSampler(
        range(len(train_split)), num_replicas=d.world, rank=d.rank, shuffle=True, seed=cfg.seed, drop_last=True
    )
    bar = tqdm(
        total=total_steps * cfg.batch_size,
        initial=min(state.samples_seen, total_steps * cfg.batch_size),
        unit="sample",
        unit_scale=True,
        desc=f"train {cfg.arch}",
        disable=not (progress and d.main),
        dynamic_ncols=True,
    )
    log = _MetricsLog(paths.metrics, d.main)
    loss_acc, loss_n, ema = 0.0, 0, None

    def load(order: np.ndarray, bi: int, step: int):
        """Batch ``bi`` of an epoch's ``order``, read for optimizer step ``step``."""
        place, ctx = cfg.placement == "image", bool(cfg.context_scale)
        batch = train_split.batch(order[bi * local_main : (bi + 1) * local_main], cfg.arch, cfg.target, place, ctx)
        if local_mix:
            extra = mix_train.batch(
                _mix_index(cfg, step, d.rank, len(mix_train), local_mix), cfg.arch, cfg.target, place, ctx
            )
            batch = tuple(torch.cat(pair) for pair in zip(batch, extra))
        if place and cfg.placement_dropout:
            batch = _drop_placement(cfg, batch, step, d.rank)
        return _mirror_rows(cfg, batch, step, d.rank) if cfg.mirror else batch

    # the next batch is read from the memory map in a thread while this one's step runs (numpy and
    # torch release the GIL), so a cold page cache's random reads overlap the arithmetic
    pool = ThreadPoolExecutor(1, thread_name_prefix="train-batches")
    net.train()
    try:
        while state.step < total_steps:
            sampler.set_epoch(state.epoch)
            order = np.fromiter(iter(sampler), dtype=np.int64, count=len(sampler))
            if cells is not None:
                order = _family_order(cfg, cells, state.epoch, d.rank, len(order))
            n_batches = len(order) // local_main  # BatchSampler(sampler, local_main, drop_last=True)
            ahead = (
                pool.submit(load, order, state.batch_in_epoch, state.step) if state.batch_in_epoch < n_batches else None
            )
            for bi in range(state.batch_in_epoch, n_batches):
                lr = cfg.lr_at(state.samples_seen)
                batch = ahead.result()
                ahead = pool.submit(load, order, bi + 1, state.step + 1) if bi + 1 < n_batches else None
                loss = _sgd_step(model, opt, batch, lr, weights, bf16, cfg.teacher_weight)
                state.advance(cfg.batch_size)
                loss_acc, loss_n = loss_acc + loss, loss_n + 1
                ema = loss if ema is None else 0.95 * ema + 0.05 * loss
                bar.update(cfg.batch_size)
                bar.set_postfix(
                    {
                        "loss": f"{ema:.4f}",
                        "lr": f"{lr:.2e}",
                        **({"val_bacc": f"{last_val.get('balanced_accuracy', math.nan):.3f}"} if last_val else {}),
                    },
                    refresh=False,
                )
                done = state.step >= total_steps
                if state.step % cfg.log_every_steps == 0 or done:
                    log.write(
                        {
                            "kind": "train",
                            "step": state.step,
                            "samples": state.samples_seen,
                            "epoch": state.epoch,
                            "loss": loss_acc / loss_n,
                            "lr": lr,
                            "wall_time_s": wall0 + time.time() - t0,
                        }
                    )
                    loss_acc, loss_n = 0.0, 0
                if _crossed(state.samples_seen, cfg.batch_size, cfg.val_every_samples) or done:
                    last_val = _validate(net, val_split, cfg, d, bf16)
                    log.write({"kind": "val", "step": state.step, "samples": state.samples_seen, **last_val})
                    val_mix = _validate(net, mix_val, cfg, d, bf16) if mix_val is not None else None
                    if val_mix is not None:
                        log.write({"kind": "val_mix", "step": state.step, "samples": state.samples_seen, **val_mix})
                    score = _selection_score(cfg, last_val, val_mix)
                    if _better(score, state.best_val_balanced_accuracy):
                        state.best_val_balanced_accuracy, state.best_step = score, state.step
                        best_val = dict(last_val) if val_mix is None else {**last_val, "mix": val_mix}
                        save(paths.best, last_val, with_optimizer=False)
                    save(paths.last, last_val, with_optimizer=True)
                    d.barrier()
                elif _crossed(state.samples_seen, cfg.batch_size, cfg.checkpoint_every_samples):
                    save(paths.last, last_val, with_optimizer=True)
                if done:
                    break
            if state.batch_in_epoch >= n_batches:
                state.next_epoch()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        bar.close()
        log.close()
    if d.main and not paths.best.is_file():  # no finite balanced accuracy (e.g. one class in val): keep last
        save(paths.best, last_val, with_optimizer=False)
    state.wall_time_s = wall0 + time.time() - t0
    if d.main:
        atomic.write_json(
            paths.run_json, _run_info(cfg, data_info, data, norm, state, finished=True, best_val=best_val, bf16=bf16)
        )
    d.barrier()
    return TrainResult(
        paths.root, state.step, state.samples_seen, state.best_val_balanced_accuracy, last_val, state.wall_time_s
    )


def _run_info(
    cfg: TrainConfig,
    data_info: dict,
    data: CropDataset,
    norm: Normalization,
    state: TrainState,
    finished: bool,
    best_val: dict | None = None,
    bf16: bool = False,
) -> dict:
    return {
        "arch": cfg.arch,
        "config": cfg.to_dict(),
        "dataset": data_info,
        "geometry": data.geometry.to_dict(),
        "intrinsics": data.intrinsics.to_dict(),
        "intrinsics_from_manifest": data.intrinsics_from_manifest,
        "normalization": norm.to_dict(),
        "training": {
            **M.nan_to_none(state.to_dict()),
            "finished": finished,
            "torch": torch.__version__,
            "precision": "bf16" if bf16 else "fp32",
        },
        "best_validation": M.nan_to_none(best_val or {}),
    }
