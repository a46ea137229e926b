"""Training with placement rows (training.config placement "image"): the head reads them, a
fine-tune from a network without them starts as that network, crops without them are refused."""

import numpy as np
import pytest
import torch

from training.checkpoint import load_checkpoint, load_init_weights, load_trained
from training.config import TrainConfig
from training.data import DatasetError, open_crop_dataset
from training.networks import GraspQualityNet
from training.predict import predict_split
from training.synthetic import make_synthetic_crop_dataset
from training.train import _drop_placement, train

FAST = dict(batch_size=16, base_lr=0.1, seed=0, log_every_steps=2)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("place") / "data"
    make_synthetic_crop_dataset(path, 64, 32, 32, signal="placement", positive_rate=0.5, seed=1)
    return path


def test_a_placement_net_reads_pose_rows_with_the_placement_row_after_them():
    net = GraspQualityNet("fast_vgqcnn", placement=True).eval()
    enc = net.encode(torch.randn(1, 1, 32, 32))
    assert net.head(enc, torch.zeros(2, 14)).shape == (2,)
    with pytest.raises(ValueError, match="width 14"):
        net.head(enc, torch.zeros(2, 7))


def test_a_fine_tune_that_adds_placement_starts_as_its_init():
    torch.manual_seed(0)
    old = GraspQualityNet("fast_vgqcnn").eval()
    net = GraspQualityNet("fast_vgqcnn", placement=True).eval()
    assert load_init_weights(net, old.state_dict()) == []  # pc1 widened by zero columns, nothing fresh
    x, poses = torch.randn(1, 1, 32, 32), torch.tensor([[2.0, -3.0, 0.6, 1, 0, 0, 0]])
    place = torch.tensor([[1.0, 0.035, 0.03, 0.01, -0.02, 0.05, 0.1]])
    with torch.no_grad():
        assert torch.equal(net.head(net.encode(x), torch.cat([poses, place], 1)), old.head(old.encode(x), poses))


def test_a_fine_tune_that_adds_a_placement_stream_starts_as_its_init_with_pc1_kept():
    torch.manual_seed(0)
    old = GraspQualityNet("fast_vgqcnn").eval()
    net = GraspQualityNet("fast_vgqcnn", placement=True, placement_units=8).eval()
    assert load_init_weights(net, old.state_dict()) == ["place_fc1.bias", "place_fc1.weight", "place_fc2.weight"]
    assert torch.equal(net.pc1.weight, old.pc1.weight)  # pc1 reads the pose features only
    x, poses = torch.randn(1, 1, 32, 32), torch.tensor([[2.0, -3.0, 0.6, 1, 0, 0, 0]])
    place = torch.tensor([[1.0, 0.035, 0.03, 0.01, -0.02, 0.05, 0.1]])
    with torch.no_grad():
        assert torch.equal(net.head(net.encode(x), torch.cat([poses, place], 1)), old.head(old.encode(x), poses))


def test_a_placement_stream_needs_placement():
    with pytest.raises(ValueError, match="placement_units"):
        GraspQualityNet("fast_vgqcnn", placement_units=8)
    with pytest.raises(ValueError, match="placement_units"):
        TrainConfig(placement_units=8)


def test_the_placement_streams_learning_rate_is_scaled(data, tmp_path):
    cfg = TrainConfig(
        samples=64, val_every_samples=64, placement="image", placement_units=8, placement_lr_scale=10.0, **FAST
    )
    train(cfg, data, tmp_path / "run", progress=False)
    ckpt = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    groups = ckpt["optimizer"]["param_groups"]
    assert [g["lr_scale"] for g in groups] == [1.0, 10.0]
    assert groups[1]["lr"] == pytest.approx(10.0 * groups[0]["lr"])
    assert len(groups[1]["params"]) == 3  # place_fc1 weight and bias, place_fc2 weight


def test_training_with_a_placement_stream_learns_a_label_only_the_placement_row_carries(data, tmp_path):
    cfg = TrainConfig(
        samples=64 * 12, val_every_samples=256, placement="image", placement_units=16, placement_dropout=0.0, **FAST
    )
    train(cfg, data, tmp_path / "run", progress=False)
    net, _ = load_trained(tmp_path / "run" / "checkpoints" / "last.pt")
    sp = open_crop_dataset(data).split("train")
    p, _ = predict_split(net, sp)
    y = np.asarray(sp.labels).astype(bool)
    assert net.placement_units == 16 and ((p > 0.5) == y).mean() > 0.8


def test_training_with_placement_learns_a_label_only_the_placement_row_carries(data, tmp_path):
    cfg = TrainConfig(samples=64 * 12, val_every_samples=256, placement="image", placement_dropout=0.0, **FAST)
    train(cfg, data, tmp_path / "run", progress=False)
    net, _ = load_trained(tmp_path / "run" / "checkpoints" / "last.pt")
    sp = open_crop_dataset(data).split("train")
    p, _ = predict_split(net, sp)
    y = np.asarray(sp.labels).astype(bool)
    assert net.n_place == 7 and ((p > 0.5) == y).mean() > 0.8  # images and poses are noise here


def test_placement_training_refuses_crops_without_placement_rows(data, tmp_path):
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(data, bare)
    (bare / "val" / "placement.npy").unlink()
    with pytest.raises(DatasetError, match="placement rows.*'val'"):
        train(TrainConfig(samples=16, placement="image", **FAST), bare, tmp_path / "r", progress=False)


def test_placement_training_refuses_rows_that_put_the_grasp_at_its_true_depth(data, tmp_path):
    import json
    import shutil

    old = tmp_path / "old"
    shutil.copytree(data, old)
    m = json.loads((old / "manifest.json").read_text())
    del m["placement_grasp_depth"]  # cut before the crop stage read grasps at the image's depth scale
    (old / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(DatasetError, match="placement_grasp_depth"):
        train(TrainConfig(samples=16, placement="image", **FAST), old, tmp_path / "r", progress=False)


def test_placement_dropout_makes_the_drawn_rows_unknown_and_leaves_the_rest():
    cfg = TrainConfig(placement="image", placement_dropout=0.5, seed=3)
    pose = torch.ones(64, 14)
    _, out, _ = _drop_placement(cfg, (torch.zeros(64, 1, 2, 2), pose, torch.zeros(64)), step=5, rank=0)
    dropped = (out[:, 7:] == 0).all(dim=1)
    assert 10 < int(dropped.sum()) < 54 and (out[:, :7] == 1).all() and (out[~dropped, 7:] == 1).all()
    _, again, _ = _drop_placement(cfg, (torch.zeros(64, 1, 2, 2), pose, torch.zeros(64)), step=5, rank=0)
    assert torch.equal(out, again)  # the same rows on a resumed run
