"""Training loop: single process by default, DDP (gloo) when launched by ``torchrun``.

The data order is ``DistributedSampler`` over the training split (one replica without
torchrun), reshuffled per epoch with the config's seed, so a resumed run reads exactly the
batches the killed run would have read next. The global batch is ``config.batch_size``,
split evenly over the processes; rank 0 alone writes the run folder.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DistributedSampler
from tqdm import tqdm

from vgq import atomic
from vgq.normalization import Normalization

from . import metrics as M
from .checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, CheckpointError, RunPaths, load_checkpoint, save_checkpoint
from .config import TrainConfig
from .data import CropDataset, CropSplit, DatasetError, open_crop_dataset
from .networks import GraspQualityNet
from .predict import predict_split

#: config keys that may change on --resume (they do not change what is learned)
RESUMABLE_CHANGES = {"samples", "val_every_samples", "val_max_samples", "checkpoint_every_samples",
                     "log_every_steps", "eval_batch_size", "num_threads"}


@dataclass
class TrainResult:
    run_dir: Path
    steps: int
    samples_seen: int
    best_val_balanced_accuracy: float
    last_val: dict
    wall_time_s: float


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


def _validate(net: GraspQualityNet, split: CropSplit, cfg: TrainConfig, d: _Dist) -> dict:
    idx = _val_index(len(split), cfg)[d.rank :: d.world]
    p, loss = predict_split(net, split, idx, cfg.eval_batch_size)
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


def _class_weights(split: CropSplit) -> torch.Tensor:
    lab = np.asarray(split.labels)
    n, pos = len(lab), int(lab.sum())
    neg = n - pos
    if pos == 0 or neg == 0:
        raise DatasetError("class_balance='loss_weights' needs both classes in the training split")
    return torch.tensor([n / (2.0 * neg), n / (2.0 * pos)], dtype=torch.float32)


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


def _check_resume_config(saved: dict, cfg: TrainConfig) -> TrainConfig:
    diff = sorted(k for k, v in cfg.to_dict().items() if k not in RESUMABLE_CHANGES and saved.get(k) != v)
    if diff:
        raise CheckpointError(
            "cannot resume with a different configuration: "
            + ", ".join(f"{k}={cfg.to_dict()[k]!r} (checkpoint: {saved.get(k)!r})" for k in diff)
        )
    return cfg


def _check_resume_dataset(saved: dict, data: CropDataset) -> None:
    now = data.info()
    for k in ("geometry", "counts", "architecture"):
        if saved.get(k) != now.get(k):
            raise CheckpointError(
                f"cannot resume on a different dataset: {k} is {now.get(k)!r} in {data.path}, "
                f"{saved.get(k)!r} in the checkpoint's dataset {saved.get('path')}"
            )


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
    data = open_crop_dataset(data_dir)
    data.check_arch(cfg.arch)
    train_split, val_split = data.split("train"), data.split("val")
    paths = RunPaths(Path(run_dir))
    if cfg.batch_size % d.world:
        raise ValueError(f"batch_size {cfg.batch_size} is not divisible by the {d.world} processes")
    local_batch = cfg.batch_size // d.world
    if len(train_split) < cfg.batch_size:
        raise DatasetError(f"training split has {len(train_split)} rows, fewer than one batch ({cfg.batch_size})")
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    n_pos = int(np.asarray(train_split.labels).sum())
    if d.main and n_pos in (0, len(train_split)):
        print(f"warning: the training split of {data.path} has only one class "
              f"({n_pos} positive of {len(train_split)}); nothing to learn", file=sys.stderr)

    ckpt = None
    if paths.last.is_file():
        if not resume:
            raise CheckpointError(f"run folder {paths.root} already holds a checkpoint; pass --resume or another --out")
        ckpt = load_checkpoint(paths.last)
        cfg = _check_resume_config(ckpt["config"], cfg)
        _check_resume_dataset(ckpt["dataset"], data)

    torch.manual_seed(cfg.seed)
    net = GraspQualityNet(cfg.arch, image_size=data.geometry.out)
    if cfg.optimizer == "adamw":
        opt = torch.optim.AdamW(net.parameters(), lr=cfg.base_lr, weight_decay=cfg.weight_decay)
    else:
        opt = torch.optim.SGD(net.parameters(), lr=cfg.base_lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    if ckpt is not None:
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        norm = Normalization.from_dict(ckpt["normalization"])
        st = dict(ckpt["state"])
        last_val = dict(ckpt.get("val") or {})
    else:
        norm = Normalization.from_data(train_split.arrays["images"], train_split.poses(cfg.arch), net.pose_columns)
        st = {"step": 0, "samples_seen": 0, "epoch": 0, "batch_in_epoch": 0,
              "best_val_balanced_accuracy": float("nan"), "best_step": -1, "wall_time_s": 0.0}
        last_val = {}
    net.set_normalization(norm)
    best = float(st["best_val_balanced_accuracy"])
    best_val = {}
    if ckpt is not None and paths.best.is_file():
        best_val = dict(load_checkpoint(paths.best).get("val") or {})
    model = DistributedDataParallel(net) if d.world > 1 else net
    weights = _class_weights(train_split) if cfg.class_balance == "loss_weights" else None
    dinfo = data.info()  # counts read once

    if d.main:
        paths.root.mkdir(parents=True, exist_ok=True)
        # drop log lines written after the checkpoint (all of them on a fresh start)
        _trim_log(paths.metrics, int(st["samples_seen"]) if ckpt is not None else -1)
        atomic.write_json(paths.run_json, _run_info(cfg, data, norm, st, d, finished=False))
    d.barrier()

    t0 = time.time()
    wall0 = float(st["wall_time_s"])

    def state_now() -> dict:
        return {**st, "best_val_balanced_accuracy": best, "wall_time_s": wall0 + time.time() - t0, "world_size": d.world}

    def checkpoint(kind: str, val: dict) -> None:
        if not d.main:
            return
        # best.pt is for evaluation and export, never resumed from: no optimizer state
        ck = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "arch": cfg.arch,
              "model": net.state_dict(), "optimizer": opt.state_dict() if kind == "last" else None,
              "config": cfg.to_dict(),
              "normalization": norm.to_dict(), "state": state_now(), "dataset": dinfo,
              "geometry": data.geometry.to_dict(), "intrinsics": data.intrinsics.to_dict(),
              "val": M.nan_to_none(val)}
        save_checkpoint(paths.last if kind == "last" else paths.best, ck)

    log_f = open(paths.metrics, "a") if d.main else None

    def log(rec: dict) -> None:
        if log_f is not None:
            log_f.write(json.dumps(M.nan_to_none(rec)) + "\n")
            log_f.flush()

    total_steps = math.ceil(cfg.samples / cfg.batch_size)
    sampler = DistributedSampler(range(len(train_split)), num_replicas=d.world, rank=d.rank,
                                 shuffle=True, seed=cfg.seed, drop_last=True)
    bar = tqdm(total=total_steps * cfg.batch_size, initial=min(st["samples_seen"], total_steps * cfg.batch_size),
               unit="sample", unit_scale=True, desc=f"train {cfg.arch}", disable=not (progress and d.main),
               dynamic_ncols=True)
    loss_acc, loss_n, ema = 0.0, 0, None
    net.train()
    try:
        while st["step"] < total_steps:
            sampler.set_epoch(int(st["epoch"]))
            order = np.fromiter(iter(sampler), dtype=np.int64, count=len(sampler))
            n_batches = len(order) // local_batch  # BatchSampler(sampler, local_batch, drop_last=True)
            for bi in range(int(st["batch_in_epoch"]), n_batches):
                b = order[bi * local_batch : (bi + 1) * local_batch]
                lr = cfg.lr_at(st["samples_seen"])
                for g in opt.param_groups:
                    g["lr"] = lr
                img, pose, lab = train_split.batch(b, cfg.arch)
                loss = F.cross_entropy(model(img, pose), lab, weight=weights)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                st["step"] += 1
                st["batch_in_epoch"] += 1
                st["samples_seen"] += cfg.batch_size
                lv = loss.item()
                loss_acc, loss_n = loss_acc + lv, loss_n + 1
                ema = lv if ema is None else 0.95 * ema + 0.05 * lv
                bar.update(cfg.batch_size)
                post = {"loss": f"{ema:.4f}", "lr": f"{lr:.2e}"}
                if last_val:
                    post["val_bacc"] = f"{last_val.get('balanced_accuracy', float('nan')):.3f}"
                bar.set_postfix(post, refresh=False)
                done = st["step"] >= total_steps
                if st["step"] % cfg.log_every_steps == 0 or done:
                    log({"kind": "train", "step": st["step"], "samples": st["samples_seen"], "epoch": st["epoch"],
                         "loss": loss_acc / loss_n, "lr": lr, "wall_time_s": wall0 + time.time() - t0})
                    loss_acc, loss_n = 0.0, 0
                if _crossed(st["samples_seen"], cfg.batch_size, cfg.val_every_samples) or done:
                    last_val = _validate(net, val_split, cfg, d)
                    log({"kind": "val", "step": st["step"], "samples": st["samples_seen"], **last_val})
                    if _better(last_val["balanced_accuracy"], best):
                        best = last_val["balanced_accuracy"]
                        st["best_step"] = st["step"]
                        best_val = dict(last_val)
                        checkpoint("best", last_val)
                    checkpoint("last", last_val)
                    d.barrier()
                elif _crossed(st["samples_seen"], cfg.batch_size, cfg.checkpoint_every_samples):
                    checkpoint("last", last_val)
                if done:
                    break
            if st["batch_in_epoch"] >= n_batches:
                st["epoch"] += 1
                st["batch_in_epoch"] = 0
    finally:
        bar.close()
        if log_f is not None:
            log_f.close()
    if d.main:
        if not paths.best.is_file():  # no finite balanced accuracy (e.g. one class in val): keep last
            checkpoint("best", last_val)
        atomic.write_json(paths.run_json, _run_info(cfg, data, norm, state_now(), d, finished=True, best_val=best_val))
    d.barrier()
    return TrainResult(paths.root, int(st["step"]), int(st["samples_seen"]), best, last_val, wall0 + time.time() - t0)


def _run_info(cfg: TrainConfig, data: CropDataset, norm: Normalization, st: dict, d: _Dist,
              finished: bool, best_val: dict | None = None) -> dict:
    return {
        "arch": cfg.arch,
        "config": cfg.to_dict(),
        "dataset": data.info(),
        "geometry": data.geometry.to_dict(),
        "intrinsics": data.intrinsics.to_dict(),
        "intrinsics_from_manifest": data.intrinsics_from_manifest,
        "normalization": norm.to_dict(),
        "training": {**{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in st.items()},
                     "world_size": d.world, "finished": finished, "torch": torch.__version__},
        "best_validation": M.nan_to_none(best_val or {}),
    }
