"""Batched inference of a GraspQualityNet over (part of) a memory-mapped crop split."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .data import CropSplit
from .networks import GraspQualityNet


@torch.no_grad()
def predict_split(
    net: GraspQualityNet,
    split: CropSplit,
    index: np.ndarray | None = None,
    batch_size: int = 64,
    progress: bool = False,
    desc: str = "predict",
    bf16: bool = False,
) -> tuple[np.ndarray, float]:
    """P(success) (n,) for rows ``index`` (default: all) and the mean cross-entropy there.

    ``bf16``: the forward pass under CPU bf16 autocast (a training run's validation when its steps
    are bf16: ~1.7x faster on a CPU with native bf16, a few decisions in 10,000 flipped); the
    probabilities and the loss are computed in fp32 either way. Small batches are the fastest on
    2-core CPUs (Zen 4: 64 rows 2.0x faster than 1,024 in fp32; the activations stay in cache)."""
    was_training = net.training
    net.eval()
    idx = np.arange(len(split)) if index is None else np.asarray(index, dtype=np.int64)
    out = np.empty(len(idx), dtype=np.float32)
    loss_sum = 0.0
    try:
        for i in tqdm(range(0, len(idx), batch_size), desc=desc, unit="batch", disable=not progress, leave=False):
            img, pose, lab = split.batch(
                idx[i : i + batch_size], net.arch, placement=bool(net.n_place), context=bool(net.context_scale)
            )
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                logits = net(img, pose)
            logits = logits.float()
            loss_sum += float(F.cross_entropy(logits, lab, reduction="sum"))
            out[i : i + batch_size] = torch.softmax(logits, 1)[:, 1].numpy()
    finally:
        net.train(was_training)
    return out, loss_sum / max(len(idx), 1)
