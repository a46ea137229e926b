"""Pose-only baseline and the kappa ablation driver."""

import json

import pytest

from training.ablation import run_ablation
from training.baseline import BaselineConfig, run_baseline
from training.config import TrainConfig
from training.data import DatasetError
from training.synthetic import make_synthetic_crop_dataset


@pytest.fixture(scope="module")
def pose_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("baseline") / "d"
    make_synthetic_crop_dataset(path, 1000, 100, 400, signal="pose", positive_rate=0.2, seed=0)
    return path


def test_pose_baseline_learns_pose_signal(pose_data, tmp_path):
    rec = run_baseline(
        pose_data, BaselineConfig(model="logreg", epochs=10, batch_size=128, lr=0.05), tmp_path / "out", progress=False
    )
    assert rec["test"]["balanced_accuracy"] > 0.9  # the label is a threshold on qw
    assert (tmp_path / "out" / "baseline_logreg.json").is_file()
    assert (tmp_path / "out" / "heatmap_baseline_logreg.png").is_file()


def test_pose_baseline_restricted_columns_see_no_signal(pose_data):
    rec = run_baseline(
        pose_data, BaselineConfig(model="mlp", columns="gqcnn", epochs=3, batch_size=256), progress=False
    )
    assert rec["columns"] == ["z"] and rec["test"]["balanced_accuracy"] < 0.65  # z carries no signal


def test_ablation_trains_each_kappa_and_plots(tmp_path):
    dirs = []
    for k in (12.0, 0.0):
        dirs.append(tmp_path / f"k{k:g}")
        make_synthetic_crop_dataset(dirs[-1], 8, 8, 8, kappa_px=k, positive_rate=0.5, seed=int(k))
    cfg = TrainConfig(samples=8, batch_size=8, val_every_samples=10**6)
    rec = run_ablation(dirs, tmp_path / "abl", cfg, progress=False)
    assert [r["kappa_px"] for r in rec["results"]] == [0.0, 12.0]
    assert all(0 <= r["balanced_accuracy"] <= 1 for r in rec["results"] if r["balanced_accuracy"] is not None)
    assert (tmp_path / "abl" / "ablation.png").read_bytes()[:4] == b"\x89PNG"
    ck = tmp_path / "abl" / "kappa_12px" / "checkpoints" / "last.pt"
    mtime = ck.stat().st_mtime_ns
    again = run_ablation(dirs, tmp_path / "abl", cfg, progress=False)  # finished runs are not retrained
    assert ck.stat().st_mtime_ns == mtime and again["results"] == rec["results"]
    assert json.loads((tmp_path / "abl" / "ablation.json").read_text())["results"] == rec["results"]


def test_ablation_rejects_duplicate_kappa(tmp_path):
    for name in ("a", "b"):
        make_synthetic_crop_dataset(tmp_path / name, 8, 4, 4, kappa_px=6.0)
    with pytest.raises(DatasetError, match="distinct kappa"):
        run_ablation([tmp_path / "a", tmp_path / "b"], tmp_path / "abl", TrainConfig(samples=8, batch_size=8))
