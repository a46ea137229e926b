"""A training process killed with a real SIGKILL at a random moment resumes with --resume and
ends with the same weights as an uninterrupted run; a partial checkpoint is never read."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

from training.checkpoint import load_checkpoint
from training.synthetic import make_synthetic_crop_dataset

ROOT = Path(__file__).resolve().parent.parent
ARGS = [
    "--samples",
    "160",
    "--batch-size",
    "16",
    "--base-lr",
    "0.05",
    "--val-every-samples",
    "80",
    "--checkpoint-every-samples",
    "32",
    "--log-every-steps",
    "2",
    "--num-threads",
    "1",
    "--no-progress",
]


def train_cmd(data: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "training", "train", "--data", str(data), "--out", str(out), *ARGS, *extra]


def run(cmd) -> None:
    r = subprocess.run(
        cmd, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]


def test_sigkill_then_resume_matches_uninterrupted(tmp_path):
    data = tmp_path / "data"
    make_synthetic_crop_dataset(data, 64, 16, 16, signal="image", positive_rate=0.5, seed=3)
    run(train_cmd(data, tmp_path / "whole"))

    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        train_cmd(data, killed),
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    last = killed / "checkpoints" / "last.pt"
    deadline = time.monotonic() + 240
    while not last.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)  # somewhere after the first checkpoint, mid-run
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    assert proc.returncode == -signal.SIGKILL, f"the run ended by itself (exit {proc.returncode}) before the kill"
    assert last.exists(), "the run was killed before its first checkpoint"
    saved = load_checkpoint(last)["state"]["samples_seen"]
    assert 0 < saved < 160, f"the kill came after the last step ({saved} samples saved): not mid-run"
    run(train_cmd(data, killed, "--resume"))

    a = load_checkpoint(tmp_path / "whole" / "checkpoints" / "last.pt")
    b = load_checkpoint(last)
    assert a["state"]["samples_seen"] == b["state"]["samples_seen"] == 160
    for k in a["model"]:
        assert torch.allclose(a["model"][k], b["model"][k], atol=1e-6), k
