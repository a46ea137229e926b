"""Scale-out: the same training under torchrun (2 processes, gloo) equals one process."""

import os
import subprocess
import sys

import pytest
import torch

from training.checkpoint import load_checkpoint
from training.config import TrainConfig
from training.synthetic import make_synthetic_crop_dataset
from training.train import train


@pytest.mark.slow  # three Python processes importing torch: ~10 s
def test_torchrun_two_processes_match_single_process(tmp_path):
    data = tmp_path / "data"
    make_synthetic_crop_dataset(data, 16, 8, 8, positive_rate=0.5, seed=2)
    cfg = dict(samples=16, batch_size=8, base_lr=0.05, seed=5, val_every_samples=10**6)
    train(TrainConfig(**cfg), data, tmp_path / "single", progress=False)
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
        "-m",
        "training",
        "train",
        "--data",
        str(data),
        "--out",
        str(tmp_path / "ddp"),
        "--no-progress",
        "--samples",
        "16",
        "--batch-size",
        "8",
        "--base-lr",
        "0.05",
        "--seed",
        "5",
        "--val-every-samples",
        "1000000",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    a = load_checkpoint(tmp_path / "single" / "checkpoints" / "last.pt")
    b = load_checkpoint(tmp_path / "ddp" / "checkpoints" / "last.pt")
    assert b["state"]["world_size"] == 2 and b["state"]["samples_seen"] == 16 and b["state"]["step"] == 2
    # each global batch of 8 is split 4 + 4 over the ranks; DDP averages the gradients
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=1e-4, atol=1e-5)
    assert b["val"]["n"] == 8  # validation counts gathered from both ranks
