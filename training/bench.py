"""Training throughput on this machine: samples/second of full SGD steps (forward, backward,
update) on random inputs of the network's shape, for each training precision side by side
(steps interleaved, so a shared machine's load hits them alike), and optionally the forward-only
rows/second of validation and evaluation at several batch sizes. Data loading is not included."""

from __future__ import annotations

import os
import platform
import time

import torch

from .config import TrainConfig
from .networks import GraspQualityNet
from .train import _optimizer, _sgd_step


def _setup(precisions: tuple[str, ...], threads: int) -> None:
    """Check the precisions asked for and set torch's thread count (0: torch's default)."""
    bad = [p for p in precisions if p not in ("fp32", "bf16")]
    if bad or not precisions:
        raise ValueError(f"precisions must be fp32 and/or bf16, got {list(precisions)}")
    if threads:
        torch.set_num_threads(threads)


def measure_train_throughput(
    arch: str = "fast_vgqcnn",
    batch_size: int = 64,
    steps: int = 20,
    warmup: int = 3,
    threads: int = 0,
    precisions: tuple[str, ...] = ("fp32",),
    optimizer: str = "adamw",
) -> dict:
    """``steps`` timed optimizer steps (the v2 recipe's AdamW by default, built as the training
    loop builds it) per precision ('fp32', 'bf16': CPU autocast) after ``warmup`` untimed ones,
    interleaved; the top-level numbers are the first precision's, ``precisions`` holds each one's
    and ``speedup`` its samples/s over the first's."""
    if steps <= 0 or warmup < 0 or batch_size <= 0:
        raise ValueError("steps and batch_size must be > 0, warmup >= 0")
    _setup(precisions, threads)
    cfg = TrainConfig(arch=arch, batch_size=batch_size, optimizer=optimizer)
    torch.manual_seed(0)
    net = GraspQualityNet(arch).to(memory_format=torch.channels_last)  # as training.train builds it
    opt = _optimizer(cfg, net)
    x = 0.7 + 0.01 * torch.randn(batch_size, 1, 32, 32)
    p = torch.randn(batch_size, len(net.pose_columns))
    y = torch.randint(0, 2, (batch_size,))
    times: dict[str, list[float]] = {pr: [] for pr in precisions}
    for i in range(warmup + steps):
        for pr in precisions:
            t = time.perf_counter()
            _sgd_step(net, opt, (x, p, y), cfg.base_lr, None, bf16=pr == "bf16")  # the training loop's step
            if i >= warmup:
                times[pr].append(time.perf_counter() - t)
    per = {
        pr: {"samples_per_s": batch_size * len(ts) / sum(ts), "median_step_s": sorted(ts)[len(ts) // 2]}
        for pr, ts in times.items()
    }
    first = precisions[0]
    for v in per.values():
        v["speedup"] = v["samples_per_s"] / per[first]["samples_per_s"]
    ts = times[first]
    return {
        "arch": arch,
        "optimizer": optimizer,
        "batch_size": batch_size,
        "steps": steps,
        "samples_per_s": per[first]["samples_per_s"],
        "mean_step_s": sum(ts) / steps,
        "min_step_s": min(ts),
        "best_samples_per_s": batch_size / min(ts),
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "processor": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "precisions": per,
    }


def measure_predict_throughput(
    arch: str = "fast_vgqcnn",
    rows: int = 1024,
    batch_sizes: tuple[int, ...] = (64, 1024),
    precisions: tuple[str, ...] = ("fp32",),
    threads: int = 0,
) -> dict:
    """Rows/second of the no-grad forward pass (``training.predict.predict_split``'s: validation
    and evaluation) over ``rows`` random inputs, for each precision x batch size, interleaved after
    one untimed pass each: ``{precision: {batch_size: rows_per_s}}``."""
    if rows <= 0 or not batch_sizes or min(batch_sizes) <= 0:
        raise ValueError("rows and every batch size must be > 0")
    _setup(precisions, threads)
    torch.manual_seed(0)
    net = GraspQualityNet(arch).eval()
    x = 0.7 + 0.01 * torch.randn(rows, 1, 32, 32)
    p = torch.randn(rows, len(net.pose_columns))

    def one_pass(pr: str, bs: int) -> float:
        t = time.perf_counter()
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=pr == "bf16"):
            for i in range(0, rows, bs):
                net(x[i : i + bs], p[i : i + bs])
        return time.perf_counter() - t

    times = {(pr, bs): 0.0 for pr in precisions for bs in batch_sizes}
    for timed in (False, True):
        for key in times:
            dt = one_pass(*key)
            if timed:
                times[key] = dt
    return {pr: {str(bs): rows / times[pr, bs] for bs in batch_sizes} for pr in precisions}
