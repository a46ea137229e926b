"""Fine-tuning (``--init``) and a second dataset mixed into every batch (``--mix-data``): the
start point is the init's weights and normalisation, the batches hold both datasets' rows,
a resumed mixed run reads the same batches, and mismatched inputs are refused by name."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from training.__main__ import main as cli
from training.checkpoint import CheckpointError, load_checkpoint, net_from_checkpoint
from training.config import TrainConfig
from training.data import DatasetError
from training.synthetic import make_synthetic_crop_dataset
from training.train import _check_resume_config, _class_weights, _mix_index, train

FAST = dict(batch_size=16, base_lr=0.05, seed=0, log_every_steps=2, val_every_samples=64)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("finetune")
    make_synthetic_crop_dataset(root / "main", 64, 32, 16, signal="image", positive_rate=0.5, seed=1)
    make_synthetic_crop_dataset(root / "mix", 48, 32, 16, signal="pose", positive_rate=0.25, seed=2)
    make_synthetic_crop_dataset(root / "kappa0", 32, 16, 16, kappa_px=0.0, seed=3)
    return root


@pytest.fixture(scope="module")
def base_run(datasets, tmp_path_factory):
    run = tmp_path_factory.mktemp("finetune") / "base"
    train(TrainConfig(samples=16 * 4, **FAST), datasets / "main", run, progress=False)
    return run


def test_init_starts_from_the_checkpoints_weights_and_normalisation(datasets, base_run, tmp_path):
    init = load_checkpoint(base_run / "checkpoints" / "best.pt")
    # lr ~0: the run's weights stay the init's, and its normalisation is the init's, not the mix's train split
    cfg = TrainConfig(samples=16, **{**FAST, "base_lr": 1e-12}, init=str(base_run))
    train(cfg, datasets / "mix", tmp_path / "ft", progress=False)
    ft = load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt")
    assert ft["normalization"] == init["normalization"]
    for k, v in init["model"].items():
        assert torch.allclose(ft["model"][k].float(), v.float(), atol=1e-6), k
    assert ft["state"]["samples_seen"] == 16 and ft["config"]["init"] == str(base_run)


def test_init_may_add_a_jaw_grid_head_that_starts_at_zero(datasets, base_run, tmp_path):
    init = load_checkpoint(base_run / "checkpoints" / "best.pt")
    cfg = TrainConfig(samples=16, **{**FAST, "base_lr": 1e-12}, init=str(base_run), roi_head="jaw")
    train(cfg, datasets / "main", tmp_path / "ft", progress=False)
    ft = load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt")
    for k, v in init["model"].items():  # the init's weights, the new head silent: the same network
        assert torch.allclose(ft["model"][k].float(), v.float(), atol=1e-6), k
    assert ft["model"]["roi_fc2.weight"].abs().max() < 1e-9 and ft["config"]["roi_head"] == "jaw"
    assert float(ft["model"]["roi_focal_px"]) > 0


def test_a_jaw_depth_head_starts_from_a_jaw_grid_runs_head(datasets, base_run, tmp_path):
    """From a jaw-grid run, "jaw_depth" keeps the grid's learnt weights; the new relative-depth
    inputs start at zero, so the first network is the init's."""
    jaw = TrainConfig(samples=16, **FAST, init=str(base_run), roi_head="jaw")
    train(jaw, datasets / "main", tmp_path / "jaw", progress=False)
    init = load_checkpoint(tmp_path / "jaw" / "checkpoints" / "last.pt")
    cfg = TrainConfig(samples=16, **{**FAST, "base_lr": 1e-12}, init=str(tmp_path / "jaw"), roi_head="jaw_depth")
    train(cfg, datasets / "main", tmp_path / "ft", progress=False)
    ft = load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt")["model"]
    w0 = init["model"]["roi_fc1.weight"]
    assert ft["roi_fc1.weight"].shape == (w0.shape[0], w0.shape[1] + 24)
    assert torch.allclose(ft["roi_fc1.weight"][:, : w0.shape[1]].float(), w0.float(), atol=1e-6)
    assert ft["roi_fc1.weight"][:, w0.shape[1] :].abs().max() < 1e-9
    assert torch.allclose(ft["roi_fc2.weight"].float(), init["model"]["roi_fc2.weight"].float(), atol=1e-6)


def test_a_wider_jaw_grid_starts_as_the_narrower_runs_network(datasets, base_run, tmp_path):
    """``roi_units``: a fine-tune into more hidden units keeps the init's units first and its
    scores (the new units' weights into fc4 start at zero, their inputs fresh so they can learn);
    a narrower grid than the init's is refused by name."""
    jaw = TrainConfig(samples=16, **FAST, init=str(base_run), roi_head="jaw", roi_units=8)
    train(jaw, datasets / "main", tmp_path / "jaw", progress=False)
    ckpt = load_checkpoint(tmp_path / "jaw" / "checkpoints" / "last.pt")
    for name in ("roi_fc1.bias", "roi_fc2.weight"):  # a grid that has learnt something (one step has not)
        ckpt["model"][name] = 0.3 * torch.randn(ckpt["model"][name].shape, generator=torch.Generator().manual_seed(1))
    torch.save(ckpt, tmp_path / "jaw.pt")
    cfg = TrainConfig(
        samples=16, **{**FAST, "base_lr": 1e-12}, init=str(tmp_path / "jaw.pt"), roi_head="jaw", roi_units=24
    )
    train(cfg, datasets / "main", tmp_path / "ft", progress=False)
    init = net_from_checkpoint(ckpt)
    ft = net_from_checkpoint(load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt"))
    assert ft.roi_fc1.weight.shape[0] == 24 and ft.roi_fc1.weight[8:].abs().min() > 0
    g = torch.Generator().manual_seed(0)
    s = init.image_size
    crops = 0.6 + 0.05 * torch.rand(6, 1, s, s, generator=g)
    poses = torch.cat([torch.rand(6, 2, generator=g) * 8 - 4, 0.6 + 0.1 * torch.rand(6, 1, generator=g),
                       F.normalize(torch.randn(6, 4, generator=g), dim=1)], dim=1)  # fmt: skip
    with torch.no_grad():
        assert torch.allclose(ft(crops, poses), init(crops, poses), atol=1e-5)
    narrow = TrainConfig(samples=16, **FAST, init=str(tmp_path / "jaw.pt"), roi_head="jaw", roi_units=4)
    with pytest.raises(CheckpointError, match="roi_fc1"):
        train(narrow, datasets / "main", tmp_path / "narrow", progress=False)


def test_init_of_other_crop_geometry_is_refused(datasets, base_run, tmp_path):
    with pytest.raises(CheckpointError, match="crops"):
        train(TrainConfig(samples=16, **FAST, init=str(base_run)), datasets / "kappa0", tmp_path / "x", progress=False)


def test_init_may_fine_tune_into_windows_turned_towards_the_jaw(datasets, base_run, tmp_path):
    import shutil

    turned = tmp_path / "turned"
    shutil.copytree(datasets / "main", turned)
    m = json.loads((turned / "manifest.json").read_text())
    m["geometry"]["jaw_turns"] = 4
    (turned / "manifest.json").write_text(json.dumps(m))
    train(TrainConfig(samples=16, **FAST, init=str(base_run)), turned, tmp_path / "ft", progress=False)
    ft = load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt")
    assert ft["geometry"]["jaw_turns"] == 4  # the run's crops, not the init's


def test_mixed_batches_hold_rows_of_both_datasets(datasets, tmp_path, monkeypatch):
    from training import train as train_mod

    seen = []
    real = train_mod._sgd_step

    def spy(model, opt, batch, lr, weights, bf16=False, teacher_weight=0.0):
        seen.append(batch[1][:, 2].clone())  # pose column z: the two synthetic datasets differ in it
        return real(model, opt, batch, lr, weights, bf16, teacher_weight)

    monkeypatch.setattr(train_mod, "_sgd_step", spy)
    cfg = TrainConfig(samples=16 * 3, **FAST, mix_data=str(datasets / "mix"), mix_share=0.25)
    train(cfg, datasets / "main", tmp_path / "mixed", progress=False)
    assert len(seen) == 3 and all(len(b) == 16 for b in seen)
    mix_poses = np.load(datasets / "mix" / "train" / "poses.npy")
    for step, b in enumerate(seen):  # the last 4 rows of each batch are the mix rows that step draws
        idx = _mix_index(cfg, step, 0, len(mix_poses), 4)
        assert np.allclose(b[12:].numpy(), mix_poses[idx, 2])


def test_mixed_run_resumes_to_the_same_weights(datasets, tmp_path):
    cfg = dict(**FAST, mix_data=str(datasets / "mix"), mix_share=0.5, checkpoint_every_samples=16)
    train(TrainConfig(samples=16 * 6, **cfg), datasets / "main", tmp_path / "straight", progress=False)
    train(TrainConfig(samples=16 * 3, **cfg), datasets / "main", tmp_path / "cut", progress=False)
    train(TrainConfig(samples=16 * 6, **cfg), datasets / "main", tmp_path / "cut", resume=True, progress=False)
    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")["model"]
    b = load_checkpoint(tmp_path / "cut" / "checkpoints" / "last.pt")["model"]
    for k in a:
        assert torch.allclose(a[k].float(), b[k].float(), atol=1e-6), k
    kinds = [json.loads(x)["kind"] for x in (tmp_path / "cut" / "metrics.jsonl").read_text().splitlines()]
    assert "val_mix" in kinds


def test_class_weights_follow_the_mixed_batches(datasets):
    from training.data import open_crop_dataset

    main = open_crop_dataset(datasets / "main").split("train")
    mix = open_crop_dataset(datasets / "mix").split("train")
    p = 0.5 * np.mean(np.asarray(main.labels)) + 0.5 * np.mean(np.asarray(mix.labels))
    w = _class_weights(main, mix, 0.5)
    assert w.tolist() == pytest.approx([1 / (2 * (1 - p)), 1 / (2 * p)])


def test_resume_of_a_checkpoint_older_than_the_new_options(base_run):
    saved = load_checkpoint(base_run / "checkpoints" / "last.pt")["config"]
    for k in ("init", "mix_data", "mix_share", "select_on"):
        saved.pop(k)
    _check_resume_config(saved, TrainConfig(samples=16 * 4, **FAST))  # no error: the defaults they had
    with pytest.raises(CheckpointError, match="mix_share"):
        _check_resume_config(saved, TrainConfig(samples=16 * 4, **FAST, mix_data="x", mix_share=0.5))


def test_mix_of_other_geometry_is_refused(datasets, tmp_path):
    cfg = TrainConfig(samples=16, **FAST, mix_data=str(datasets / "kappa0"), mix_share=0.5)
    with pytest.raises(DatasetError, match="crop geometry"):
        train(cfg, datasets / "main", tmp_path / "x", progress=False)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--mix-share", "0.3"], "need mix_data"),
        (["--mix-data", "D", "--mix-share", "1.5"], "mix_share must be in"),
        (["--select-on", "mix"], "need mix_data"),
    ],
)
def test_cli_names_bad_mix_options(datasets, tmp_path, capsys, extra, message):
    rc = cli(["train", "--data", str(datasets / "main"), "--out", str(tmp_path / "r"), "--no-progress", *extra])
    assert rc == 2 and message in capsys.readouterr().err
