"""Pose-only baseline and the kappa ablation driver."""

import json

import numpy as np
import pytest

from training.ablation import run_ablation
from training.baseline import BaselineConfig, run_baseline
from training.config import TrainConfig
from training.data import DatasetError, open_crop_dataset
from training.metrics import binary_metrics
from training.synthetic import make_synthetic_crop_dataset
from vgq.pose_only import PoseOnlyError, PoseOnlyModel


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


@pytest.mark.parametrize("model", ["logreg", "mlp"])
def test_pose_baseline_file_scores_like_the_trained_model_without_torch(pose_data, tmp_path, model):
    rec = run_baseline(pose_data, BaselineConfig(model=model, epochs=3, batch_size=128), tmp_path, progress=False)
    m = PoseOnlyModel.load(tmp_path / f"baseline_{model}.npz")
    test = open_crop_dataset(pose_data).split("test")
    p = m.predict(np.asarray(test.arrays["poses"]))
    metrics = binary_metrics(np.asarray(test.labels), p)
    assert metrics["balanced_accuracy"] == pytest.approx(rec["test"]["balanced_accuracy"], abs=1e-6)
    assert m.columns == tuple(rec["columns"])


def test_pose_only_file_with_broken_layers_is_refused(tmp_path):
    ok = PoseOnlyModel(("z",), np.zeros(1, np.float32), np.ones(1, np.float32), ((np.ones((3, 1)), np.zeros(3)),))
    ok.save(tmp_path / "b.npz")  # 3 outputs, not 2 logits
    with pytest.raises(PoseOnlyError, match="not 2 logits"):
        PoseOnlyModel.load(tmp_path / "b.npz")
    (tmp_path / "c.npz").write_bytes(b"not a zip")
    with pytest.raises(PoseOnlyError, match="not a pose-only baseline file"):
        PoseOnlyModel.load(tmp_path / "c.npz")


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
