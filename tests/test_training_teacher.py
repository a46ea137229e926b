"""Distillation: a teacher run's scores of the training rows (resumable, checked to be the same
rows) and a student that fits them (``--target teacher``)."""

import math

import numpy as np
import pytest
import torch

from training.checkpoint import load_trained
from training.config import TrainConfig
from training.data import DatasetError, open_crop_dataset
from training.synthetic import make_synthetic_crop_dataset
from training.teacher import load_teacher_scores, score_teacher
from training.train import distillation_loss, train

FAST = dict(batch_size=16, base_lr=0.1, seed=0, log_every_steps=2)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("teacher") / "data"  # centred crops: a VGQ-CNN teacher, a Fast student
    make_synthetic_crop_dataset(path, 48, 16, 16, arch="vgqcnn", kappa_px=0.0, signal="image", seed=1)
    return path


@pytest.fixture(scope="module")
def teacher(data, tmp_path_factory):
    run = tmp_path_factory.mktemp("teacher") / "run"
    cfg = TrainConfig(arch="vgqcnn", samples=64, val_every_samples=64, class_balance="loss_weights", **FAST)
    train(cfg, data, run, progress=False)
    return run


def test_scoring_resumes_and_leaves_unscored_rows_nan(data, teacher, tmp_path):
    out = tmp_path / "scores"
    m = score_teacher(teacher, data, out, max_rows=10, chunk_rows=4, progress=False)
    part = np.load(out / "train.npy")
    assert m["splits"]["train"]["scored"] == 10 and np.isfinite(part).sum() == 10
    m = score_teacher(teacher, data, out, chunk_rows=4, progress=False)
    full = np.load(out / "train.npy")
    assert m["splits"]["train"]["scored"] == 48 and np.isfinite(full).all() and ((full >= 0) & (full <= 1)).all()
    assert np.array_equal(full[np.isfinite(part)], part[np.isfinite(part)])  # scored rows kept, not redone


def test_scores_of_other_rows_are_refused(data, teacher, tmp_path):
    score_teacher(teacher, data, tmp_path / "scores", progress=False)
    other = tmp_path / "other"
    make_synthetic_crop_dataset(other, 48, 16, 16, arch="vgqcnn", kappa_px=0.0, signal="image", seed=2)
    with pytest.raises(DatasetError, match="other rows"):
        load_teacher_scores(tmp_path / "scores", open_crop_dataset(other).split("train"))


def test_student_trains_on_the_teachers_scores(data, teacher, tmp_path):
    score_teacher(teacher, data, tmp_path / "scores", max_rows=20, progress=False)  # part-scored: still serves
    cfg = TrainConfig(samples=64, val_every_samples=64, target="teacher", teacher=str(tmp_path / "scores"), **FAST)
    train(cfg, data, tmp_path / "student", progress=False)
    net, meta = load_trained(tmp_path / "student")
    assert net.arch == "fast_vgqcnn" and meta["training"]["config"]["target"] == "teacher"


def test_a_balanced_teachers_scores_become_posteriors(data, teacher, tmp_path):
    score_teacher(teacher, data, tmp_path / "scores", progress=False)  # the teacher trained with loss weights
    split = open_crop_dataset(data).split("train")
    raw = np.load(tmp_path / "scores" / "train.npy")
    with pytest.raises(ValueError, match="class weights"):
        load_teacher_scores(tmp_path / "scores", split)
    assert np.allclose(load_teacher_scores(tmp_path / "scores", split, [1.0, 1.0]), raw)
    post = load_teacher_scores(tmp_path / "scores", split, [0.6, 3.0])  # positives rare: P below the score
    assert np.allclose(3.0 * post / (3.0 * post + 0.6 * (1 - post)), raw, atol=1e-6) and (post <= raw + 1e-7).all()


def test_distillation_loss_mixes_label_and_teacher():
    logits = torch.tensor([[0.3, -0.2], [1.0, 2.0], [-0.5, 0.5]], requires_grad=True)
    w = torch.tensor([0.6, 3.0])
    label = torch.tensor([0.0, 1.0, 1.0])
    none = torch.stack([label, torch.full((3,), math.nan)], 1)
    hard = torch.nn.functional.cross_entropy(logits, label.long(), weight=w)
    assert torch.allclose(distillation_loss(logits, none, w, 0.25), 0.75 * hard)  # unscored rows: the label
    q = torch.softmax(logits, 1)[:, 1].detach()
    for weights, post in ((None, q), (w, 0.6 * q / (0.6 * q + 3.0 * (1 - q)))):
        (g,) = torch.autograd.grad(distillation_loss(logits, torch.stack([label, post], 1), weights, 1.0), logits)
        assert torch.allclose(g, torch.zeros_like(g), atol=1e-6)  # minimum: the posterior's balanced score


def test_teacher_target_needs_its_folder():
    with pytest.raises(ValueError, match="go together"):
        TrainConfig(target="teacher")
    with pytest.raises(ValueError, match="teacher_weight"):
        TrainConfig(target="teacher", teacher="x", teacher_weight=0.0)
