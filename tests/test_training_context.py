"""Training with context views (training.config context_scale): the encoder reads the window and
its context view, a fine-tune from a network without one starts as that network, the head learns
what only the context shows, and crops without context views are refused."""

import numpy as np
import pytest
import torch

from training.checkpoint import CONTEXT_WEIGHTS, load_init_weights, load_trained
from training.config import TrainConfig
from training.data import DatasetError, open_crop_dataset
from training.networks import GraspQualityNet
from training.predict import predict_split
from training.synthetic import make_synthetic_crop_dataset
from training.train import train

FAST = dict(batch_size=16, base_lr=0.1, seed=0, log_every_steps=2, roi_head="jaw")
POSES = torch.tensor([[2.0, -3.0, 0.6, 1, 0, 0, 0], [-5.0, 4.0, 0.9, 0.5, 0.5, 0.5, 0.5]])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("context") / "data"
    make_synthetic_crop_dataset(path, 64, 32, 32, signal="context", positive_rate=0.5, seed=1)
    return path


def test_a_context_net_encodes_the_window_and_its_context_view_once_for_all_grasps():
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw", context_scale=3).eval()
    torch.nn.init.normal_(net.ctx_fc2.weight, std=0.01)
    x = torch.randn(1, 2, 32, 32) * 0.01 + 0.7
    enc = net.encode(x)
    assert enc.shape == (1, net.encoding_width)
    with torch.no_grad():
        shared = net.head_logits(enc, POSES)
        each = net(x.expand(2, -1, -1, -1), POSES)
        torch.testing.assert_close(shared, each)
        other = x.clone()
        other[:, 1, :8, :8] -= 0.1  # only the context view changed
        assert not torch.allclose(net.head_logits(net.encode(other), POSES), shared)
    with pytest.raises(ValueError, match="2 channel"):
        net.encode(torch.zeros(1, 1, 32, 32))


def test_a_fine_tune_that_adds_a_context_view_starts_as_its_init():
    torch.manual_seed(0)
    old = GraspQualityNet("fast_vgqcnn", roi_head="jaw").eval()
    torch.nn.init.normal_(old.roi_fc2.weight, std=0.01)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw", context_scale=3).eval()
    assert load_init_weights(net, old.state_dict()) == sorted(CONTEXT_WEIGHTS)
    x = torch.randn(1, 2, 32, 32) * 0.01 + 0.7
    with torch.no_grad():
        assert torch.equal(net.head(net.encode(x), POSES), old.head(old.encode(x[:, :1]), POSES))


def test_a_context_view_needs_a_jaw_grid_and_a_known_scale():
    with pytest.raises(ValueError, match="context_scale"):
        GraspQualityNet("fast_vgqcnn", context_scale=3)
    with pytest.raises(ValueError, match="context_scale"):
        GraspQualityNet("fast_vgqcnn", roi_head="jaw", context_scale=5)
    with pytest.raises(ValueError, match="context_scale"):
        TrainConfig(context_scale=3)


def test_training_with_a_context_view_learns_a_label_only_the_context_view_carries(data, tmp_path):
    split = open_crop_dataset(data).split("test")  # other objects: what a net memorised does not carry
    lab = np.asarray(split.labels).astype(bool)
    gaps = {}
    for scale in (3, 0):  # the same run without the context view: the window alone carries nothing
        cfg = TrainConfig(samples=64 * 12, val_every_samples=256, context_scale=scale, **FAST)
        train(cfg, data, tmp_path / f"run{scale}", progress=False)
        net, _ = load_trained(tmp_path / f"run{scale}")
        assert net.context_scale == scale
        p, _ = predict_split(net, split, np.arange(len(split)), 64)
        gaps[scale] = p[lab].mean() - p[~lab].mean()
    assert gaps[3] > 0.2 and abs(gaps[0]) < 0.1, gaps


def test_context_training_refuses_crops_without_context_views(tmp_path):
    plain = tmp_path / "plain"
    make_synthetic_crop_dataset(plain, 32, 16, 16, signal="image", seed=1)
    with pytest.raises(DatasetError, match="context-scale 3"):
        train(TrainConfig(samples=32, context_scale=3, **FAST), plain, tmp_path / "run", progress=False)
    with pytest.raises(DatasetError, match="context views"):
        open_crop_dataset(plain).split("train").batch(np.arange(4), "fast_vgqcnn", context=True)


def test_freeze_init_trains_only_the_context_layers_and_resumes_so(data, tmp_path):
    init_cfg = TrainConfig(samples=64, val_every_samples=64, **FAST)
    train(init_cfg, data, tmp_path / "init", progress=False)
    init, _ = load_trained(tmp_path / "init")
    cfg = TrainConfig(
        samples=64, val_every_samples=64, context_scale=3, init=str(tmp_path / "init"), freeze_init=True, **FAST
    )
    train(cfg, data, tmp_path / "ft", progress=False)
    train(TrainConfig(**{**cfg.to_dict(), "samples": 128}), data, tmp_path / "ft", resume=True, progress=False)
    net, _ = load_trained(tmp_path / "ft")
    own, before = net.state_dict(), init.state_dict()
    for name in before:
        torch.testing.assert_close(own[name], before[name], msg=name)  # the init's layers never moved
    assert not torch.all(own["ctx_fc2.weight"] == 0)  # the context view's did, from zero
    with pytest.raises(ValueError, match="freeze_init and freeze_encoder need init"):
        TrainConfig(freeze_init=True)
