"""Training: the loss falls on a learnable signal, checkpoints round-trip, resume continues
from the saved step, evaluation writes metrics and heat maps, load_trained meta."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from training.checkpoint import CheckpointError, load_checkpoint, load_trained
from training.config import TrainConfig
from training.data import DatasetError, open_crop_dataset
from training.evaluate import evaluate
from training.networks import GraspQualityNet
from training.predict import predict_split
from training.synthetic import make_synthetic_crop_dataset
from training.train import train

ROOT = Path(__file__).resolve().parent.parent
FAST = dict(batch_size=16, base_lr=0.1, seed=0, log_every_steps=2)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("train") / "data"
    make_synthetic_crop_dataset(path, 16, 16, 32, signal="image", positive_rate=0.5, seed=1)
    return path


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("train") / "run"
    train(TrainConfig(samples=16 * 8, val_every_samples=64, **FAST), data, run_dir, progress=False)
    return run_dir


def test_loss_falls_on_learnable_signal(data, run):
    net, _ = load_trained(run / "checkpoints" / "last.pt")
    torch.manual_seed(0)
    untrained = GraspQualityNet("fast_vgqcnn")
    untrained.set_normalization(net.normalization())
    sp = open_crop_dataset(data).split("train")
    _, loss_before = predict_split(untrained, sp)
    _, loss_after = predict_split(net, sp)
    # 8 SGD steps on the 16-row train split (batch 16): the net fits it, far below chance (ln 2)
    assert loss_after < 0.8 * loss_before and loss_after < 0.8 * math.log(2)


def test_normalisation_from_training_split_only(data, run):
    net, meta = load_trained(run)
    sp = open_crop_dataset(data).split("train")
    assert float(net.image_mean) == pytest.approx(float(np.mean(sp.arrays["images"], dtype=np.float64)), rel=1e-6)
    assert float(net.pose_mean[2]) == pytest.approx(
        float(np.mean(sp.arrays["poses"][:, 2], dtype=np.float64)), rel=1e-5
    )
    assert meta["normalization"]["pose_mean"][3:] == [0.0] * 4 and meta["normalization"]["pose_std"][3:] == [1.0] * 4


def test_metrics_log_and_best_checkpoint(run):
    recs = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    vals = [r for r in recs if r["kind"] == "val"]
    assert [r["samples"] for r in vals] == [64, 128]
    assert [r["step"] for r in recs if r["kind"] == "train"] == [2, 4, 6, 8]
    best = load_checkpoint(run / "checkpoints" / "best.pt")
    assert best["val"]["balanced_accuracy"] == max(r["balanced_accuracy"] for r in vals)


def test_checkpoint_round_trip_weights_only(run):
    ck = torch.load(run / "checkpoints" / "last.pt", weights_only=True)  # plain dicts and tensors only
    net, meta = load_trained(run / "checkpoints" / "last.pt")
    for k, v in ck["model"].items():
        torch.testing.assert_close(net.state_dict()[k], v, rtol=0, atol=0)
    assert ck["state"]["step"] == 8 and meta["training"]["samples_seen"] == 128
    assert meta["arch"] == "fast_vgqcnn" and meta["geometry"] == {"window": 96, "out": 32, "kappa_px": 36.0}
    assert meta["intrinsics"]["fx"] == 525.0 and meta["dataset"]["counts"]["train"]["n"] == 16


def test_resume_continues_from_saved_step(data, tmp_path):
    # batch 8 on 16 rows: 2 steps per epoch; stop mid-epoch after step 1, resume to step 3
    cfg = dict(batch_size=8, base_lr=0.01, seed=3, log_every_steps=1, val_every_samples=10**6)
    straight = tmp_path / "straight"
    train(TrainConfig(samples=8 * 3, **cfg), data, straight, progress=False)
    killed = tmp_path / "killed"
    train(TrainConfig(samples=8 * 1, **cfg), data, killed, progress=False)
    st = load_checkpoint(killed / "checkpoints" / "last.pt")["state"]
    assert (st["step"], st["epoch"], st["batch_in_epoch"]) == (1, 0, 1)
    with open(killed / "metrics.jsonl", "a") as f:  # a line logged after the checkpoint, then killed
        f.write('{"kind": "train", "step": 2, "samples": 16, "loss": 9.0}\n{"kind": "tra')
    with pytest.raises(CheckpointError, match="--resume"):
        train(TrainConfig(samples=8 * 3, **cfg), data, killed, progress=False)
    r = train(TrainConfig(samples=8 * 3, **cfg), data, killed, resume=True, progress=False)
    assert r.steps == 3
    a = load_checkpoint(straight / "checkpoints" / "last.pt")
    b = load_checkpoint(killed / "checkpoints" / "last.pt")
    for k in a["model"]:  # the resumed run read the same batches with the same optimizer state
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=1e-5, atol=1e-6)
    assert b["state"]["samples_seen"] == 24 and b["state"]["epoch"] == 1
    steps = [
        json.loads(x)["step"]
        for x in (killed / "metrics.jsonl").read_text().splitlines()
        if json.loads(x)["kind"] == "train"
    ]
    assert steps == [1, 2, 3]


def test_resume_refuses_changed_hyperparameters(data, run):
    with pytest.raises(CheckpointError, match="base_lr"):
        train(
            TrainConfig(samples=16 * 8, val_every_samples=64, **{**FAST, "base_lr": 0.5}),
            data,
            run,
            resume=True,
            progress=False,
        )


def test_evaluate_writes_metrics_heatmap_and_curves(data, run):
    rec = evaluate(run, data, "test", progress=False)
    out = run / "eval"
    saved = json.loads((out / "metrics_test.json").read_text())
    # the saved counts are the net's own decisions on the test crops, counted here without training.metrics
    net, _ = load_trained(run)
    arrays = open_crop_dataset(data).split("test").arrays
    with torch.no_grad():
        logits = net(
            torch.from_numpy(np.array(arrays["images"], np.float32)[:, None]),  # a writable copy of the mmap
            torch.from_numpy(np.array(arrays["poses"], np.float32)),
        )
    pred, y = torch.softmax(logits, 1)[:, 1].numpy() > 0.5, np.asarray(arrays["labels"]) == 1
    o = saved["overall"]
    assert o["n"] == 32 and (o["tp"], o["fn"], o["tn"], o["fp"]) == (
        int((pred & y).sum()),
        int((~pred & y).sum()),
        int((~pred & ~y).sum()),
        int((pred & ~y).sum()),
    )
    assert o["balanced_accuracy"] == pytest.approx(((pred & y).sum() / y.sum() + (~pred & ~y).sum() / (~y).sum()) / 2)
    assert np.nansum(np.array(saved["grid"]["n_positive"], dtype=float)) == saved["overall"]["n_positive"]
    margins = (
        "by_camera_distance_m",
        "by_camera_elevation_deg",
        "by_approach_psi_deg",
        "by_approach_beta_deg",
        "by_window_offset_px",
    )
    for margin in margins:  # every row in one bin of each
        assert sum(m["n"] for m in saved[margin].values()) == 32
    for png in ("heatmap_test.png", "curves.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    _, meta = load_trained(run)
    assert meta["metrics"]["test"]["balanced_accuracy"] == rec["overall"]["balanced_accuracy"]


def test_evaluate_max_n_scores_the_same_random_rows_each_time(data, run, tmp_path):
    full = evaluate(run, data, "test", progress=False, out_dir=tmp_path / "full")
    a = evaluate(run, data, "test", progress=False, out_dir=tmp_path / "a", max_n=20)
    b = evaluate(run, data, "test", progress=False, out_dir=tmp_path / "b", max_n=20)
    assert a["overall"]["n"] == 20 and a["rows"] == {"evaluated": 20, "of": 32, "seed": 0}
    assert a["overall"] == b["overall"] and full["rows"]["evaluated"] == 32
    assert evaluate(run, data, "test", progress=False, out_dir=tmp_path / "c", max_n=99)["overall"] == full["overall"]


def test_lr_schedule_staircase():
    cfg = TrainConfig(decay_every_samples=1000)
    assert cfg.lr_at(999) == pytest.approx(0.001) and cfg.lr_at(2500) == pytest.approx(0.001 * 0.95**2)


def test_resume_refuses_another_dataset(run, tmp_path):
    other = tmp_path / "other"
    make_synthetic_crop_dataset(other, 24, 16, 32, positive_rate=0.5, seed=9)
    with pytest.raises(CheckpointError, match="different dataset: counts"):
        train(TrainConfig(samples=16 * 8, val_every_samples=64, **FAST), other, run, resume=True, progress=False)


def test_class_balance_weights_from_train_split(data):
    from training.train import _class_weights

    sp = open_crop_dataset(data).split("train")
    n, pos = len(sp), int(np.asarray(sp.labels).sum())
    w = _class_weights(sp)
    torch.testing.assert_close(w, torch.tensor([n / (2 * (n - pos)), n / (2 * pos)]))
    assert float(w[0] * (n - pos)) == pytest.approx(float(w[1] * pos))  # both classes weigh the same in total


def test_evaluate_reports_each_family_under_its_own_name(data, run, tmp_path):
    import shutil

    fam_data = tmp_path / "families"
    shutil.copytree(data, fam_data)
    m = json.loads((fam_data / "manifest.json").read_text())
    m["source"] = {"objects": [{"object_id": i, "family": "mug" if i % 2 else "box"} for i in range(30)]}
    (fam_data / "manifest.json").write_text(json.dumps(m))
    evaluate(run, data, "test", progress=False)  # the plain test split, no families
    rec = evaluate(run, fam_data, "test", progress=False, name="test_families")
    ids = np.asarray(open_crop_dataset(fam_data).split("test").arrays["object_id"])
    fams = rec["by_family"]
    assert sorted(fams) == ["box", "mug"]
    assert fams["mug"]["n"] == int((ids % 2 == 1).sum()) and fams["box"]["n"] == int((ids % 2 == 0).sum())
    assert sum(f["tp"] for f in fams.values()) == rec["overall"]["tp"]
    y = np.asarray(open_crop_dataset(fam_data).split("test").arrays["labels"])
    assert fams["mug"]["objects"] == np.unique(ids[ids % 2 == 1]).size
    assert fams["mug"]["objects_with_positive"] == np.unique(ids[(ids % 2 == 1) & (y == 1)]).size
    for m in (*fams.values(), rec["overall"]):  # over the objects: a family's few test objects are few draws
        lo, hi = m["balanced_accuracy_ci95"]
        assert lo is None or 0 <= lo <= hi <= 1
    assert (run / "eval" / "metrics_test_families.json").is_file()
    _, meta = load_trained(run)  # the card's metrics carry it under its name, beside the plain test split
    assert meta["metrics"]["test_families"]["by_family"]["mug"]["n"] == fams["mug"]["n"]
    assert "by_family" not in meta["metrics"]["test"]
    with pytest.raises(ValueError, match="evaluation name"):
        evaluate(run, fam_data, "test", progress=False, name="../x")


def test_bf16_training_learns_and_resumes_in_fp32(data, tmp_path):
    run_dir = tmp_path / "bf16"
    cfg = TrainConfig(samples=16 * 8, val_every_samples=64, precision="bf16", **FAST)
    train(cfg, data, run_dir, progress=False)
    assert json.loads((run_dir / "run.json").read_text())["training"]["precision"] == "bf16"
    net, _ = load_trained(run_dir / "checkpoints" / "last.pt")
    assert all(p.dtype == torch.float32 for p in net.parameters())  # autocast: the weights stay fp32
    _, loss = predict_split(net, open_crop_dataset(data).split("train"))
    assert loss < 0.8 * math.log(2)
    # another machine without bf16 continues the same run in fp32
    train(
        TrainConfig(samples=16 * 10, val_every_samples=64, precision="fp32", **FAST),
        data,
        run_dir,
        resume=True,
        progress=False,
    )
    info = json.loads((run_dir / "run.json").read_text())["training"]
    assert info["precision"] == "fp32" and info["samples_seen"] == 160
    with pytest.raises(ValueError, match="precision"):
        TrainConfig(precision="fp16")


def test_bf16_validation_pass_agrees_with_fp32(data, run):
    """A bf16 run validates under bf16 autocast: the same probabilities up to bf16 rounding, in fp32."""
    net, _ = load_trained(run / "checkpoints" / "last.pt")
    sp = open_crop_dataset(data).split("val")
    p32, loss32 = predict_split(net, sp, batch_size=5)
    p16, loss16 = predict_split(net, sp, batch_size=5, bf16=True)
    assert p16.dtype == np.float32 and p16.shape == p32.shape
    assert np.abs(p16 - p32).max() < 0.05 and not np.array_equal(p16, p32)  # bf16 arithmetic did run
    assert loss16 == pytest.approx(loss32, abs=0.05)


def test_wider_second_stage_round_trips_and_guards_fine_tuning(data, tmp_path):
    train(
        TrainConfig(samples=32, val_every_samples=32, conv2_channels=24, **FAST), data, tmp_path / "w", progress=False
    )
    net, meta = load_trained(tmp_path / "w" / "checkpoints" / "best.pt")
    assert net.conv2_channels == 24 and meta["training"]["config"]["conv2_channels"] == 24
    with pytest.raises(CheckpointError, match="24 conv2 channels; this run trains 64"):
        train(TrainConfig(samples=16, **FAST, init=str(tmp_path / "w")), data, tmp_path / "x", progress=False)


def test_success_rate_target_fits_the_trials_that_held(tmp_path):
    from training.synthetic import synthetic_split, write_crop_dataset
    from vgq.crop import CropGeometry

    rng, geom = np.random.default_rng(3), CropGeometry(96, 32, 36.0)
    splits = {
        s: synthetic_split(32, rng, geom, "image", 0.5, first_object=10 * i)
        for i, s in enumerate(("train", "val", "test"))
    }
    for arrays in splits.values():  # the physics label: quality = fraction of 8 trials held, label = quality > 0.5
        arrays["quality"] = np.where(arrays["labels"] == 1, 0.875, 0.125).astype(np.float32)
    physics = {"kind": "synthetic", "config": {"label": {"kind": "physics", "trials": 8, "success_threshold": 0.5}}}
    write_crop_dataset(tmp_path / "d", splits, geom, "fast_vgqcnn", label_threshold=0.5, source=physics)
    _, _, rate = open_crop_dataset(tmp_path / "d").split("train").batch(np.arange(8), "fast_vgqcnn", "success_rate")
    labels = np.asarray(splits["train"]["labels"][:8])
    assert rate.dtype == torch.float32 and np.array_equal(rate.numpy(), np.where(labels == 1, 0.875, 0.125))
    train(
        TrainConfig(samples=32, val_every_samples=32, target="success_rate", **FAST),
        tmp_path / "d",
        tmp_path / "r",
        progress=False,
    )
    _, meta = load_trained(tmp_path / "r" / "checkpoints" / "last.pt")
    assert meta["training"]["config"]["target"] == "success_rate"


def test_success_rate_target_refuses_crops_without_trials(data, tmp_path):
    with pytest.raises(DatasetError, match="needs crops with the physics label"):
        train(TrainConfig(samples=16, target="success_rate", **FAST), data, tmp_path / "r", progress=False)


def test_success_rate_target_refuses_crops_labelled_with_early_stop(tmp_path):
    from training.synthetic import synthetic_split, write_crop_dataset
    from vgq.crop import CropGeometry

    rng, geom = np.random.default_rng(3), CropGeometry(96, 32, 36.0)
    splits = {
        s: synthetic_split(32, rng, geom, "image", 0.5, first_object=10 * i) for i, s in enumerate(("train", "val"))
    }
    label = {"kind": "physics", "trials": 8, "success_threshold": 0.5, "early_stop": True}
    source = {"kind": "synthetic", "config": {"label": label}}
    write_crop_dataset(tmp_path / "d", splits, geom, "fast_vgqcnn", label_threshold=0.5, source=source)
    with pytest.raises(DatasetError, match="early_stop"):
        train(TrainConfig(samples=16, target="success_rate", **FAST), tmp_path / "d", tmp_path / "r", progress=False)


def test_relative_depth_and_rotation_features_round_trip(data, tmp_path):
    opts = dict(depth_reference="centre", pose_features="rotation", pose_units=32)
    train(TrainConfig(samples=32, val_every_samples=32, **opts, **FAST), data, tmp_path / "r", progress=False)
    net, _ = load_trained(tmp_path / "r" / "checkpoints" / "best.pt")
    assert (net.depth_reference, net.pose_features, net.pose_units) == ("centre", "rotation", 32)
    assert net.normalization().image_reference == "centre"
    with pytest.raises(CheckpointError, match="depth_reference 'centre'; this run trains 'none'"):
        train(TrainConfig(samples=16, **FAST, init=str(tmp_path / "r")), data, tmp_path / "x", progress=False)


def test_fine_tune_into_a_new_pose_stream_keeps_the_image_path(run):
    from training.checkpoint import load_init_weights

    init = load_checkpoint(run / "checkpoints" / "best.pt")
    net = GraspQualityNet("fast_vgqcnn", pose_features="rotation", pose_units=32).eval()
    assert load_init_weights(net, init["model"]) == ["fc4_pose.weight", "pc1.bias", "pc1.weight"]
    old, _ = load_trained(run / "checkpoints" / "best.pt")
    net.set_normalization(old.normalization())
    x = torch.randn(1, 1, 32, 32)
    poses = torch.tensor([[0.0, 0.0, 0.6, 1, 0, 0, 0], [9.0, -4.0, 0.9, 0, 0, 1, 0]])
    with torch.no_grad():
        assert torch.equal(net.encode(x), old.encode(x))  # the image term is the init's
        p = net.head(net.encode(x), poses)
    assert p[0] == p[1]  # fc4's pose weights start at zero: no pose term until it learns one
    with pytest.raises(CheckpointError, match="conv1_1.weight"):
        load_init_weights(net, {**init["model"], "conv1_1.weight": torch.zeros(3)})


def test_fine_tune_from_the_bundled_model_folder(data, tmp_path):
    model = ROOT / "models" / "fast-vgqcnn-default"
    opts = dict(pose_features="rotation", pose_units=32)
    train(TrainConfig(samples=16, **FAST, **opts, init=str(model)), data, tmp_path / "f", progress=False)
    net, meta = load_trained(tmp_path / "f" / "checkpoints" / "last.pt")
    from export.from_onnx import fast_net_from_model_dir

    bundled, card = fast_net_from_model_dir(model)
    assert (net.pose_features, net.pose_units) == ("rotation", 32) and meta["training"]["config"]["init"] == str(model)
    assert net.normalization().to_dict() == card.normalization.to_dict()  # the bundle's input normalisation


def test_mirror_augmentation_flips_the_drawn_rows_the_same_way_on_resume(data):
    from training.train import _mirror_rows
    from vgq.pose import POSE_COLUMNS, mirror_poses

    batch = open_crop_dataset(data).split("train").batch(np.arange(16), "fast_vgqcnn")
    cfg = TrainConfig(mirror=0.5, **FAST)
    img, pose, lab = _mirror_rows(cfg, batch, step=7, rank=0)
    again = _mirror_rows(cfg, batch, step=7, rank=0)
    torch.testing.assert_close(img, again[0])  # rows drawn by (seed, step, rank): a resume redraws them
    flipped = ~torch.isclose(img, batch[0]).flatten(1).all(1)
    assert 0 < int(flipped.sum()) < 16
    torch.testing.assert_close(img[flipped], torch.flip(batch[0][flipped], dims=(-1,)))
    expect = mirror_poses(batch[1][flipped].numpy(), POSE_COLUMNS["fast_vgqcnn"])
    np.testing.assert_allclose(pose[flipped].numpy(), expect, atol=1e-6)
    torch.testing.assert_close(pose[~flipped], batch[1][~flipped])
    torch.testing.assert_close(lab, batch[2])  # a mirrored grasp keeps its label
    img0, _, _ = _mirror_rows(TrainConfig(mirror=0.0, **FAST), batch, step=7, rank=0)
    torch.testing.assert_close(img0, batch[0])
    with pytest.raises(ValueError, match="mirror"):
        TrainConfig(mirror=1.5)


def _turned_copy(src: Path, dst: Path, **turning) -> Path:
    """A copy of a crop dataset whose manifest says its crops are turned (default: to the jaw axis)."""
    import shutil

    shutil.copytree(src, dst)
    m = json.loads((dst / "manifest.json").read_text())
    m["geometry"].update(turning or {"align_jaw": True})
    (dst / "manifest.json").write_text(json.dumps(m))
    return dst


def test_crops_turned_to_the_jaw_train_vgqcnn_only_and_evaluate_only_a_net_trained_on_them(tmp_path):
    centred = tmp_path / "centred"
    make_synthetic_crop_dataset(centred, 16, 16, 32, arch="vgqcnn", kappa_px=0.0, seed=1)
    turned = _turned_copy(centred, tmp_path / "turned")
    ds = open_crop_dataset(turned)
    assert ds.geometry.align_jaw
    ds.check_arch("vgqcnn")
    with pytest.raises(DatasetError, match="turned to the jaw axis.*cannot train 'fast_vgqcnn'"):
        ds.check_arch("fast_vgqcnn")  # a Fast model on turned windows could never be served
    run = tmp_path / "run"
    train(TrainConfig(arch="vgqcnn", samples=32, val_every_samples=32, **FAST), turned, run, progress=False)
    assert load_trained(run / "checkpoints" / "last.pt")[1]["geometry"]["align_jaw"] is True
    evaluate(run, turned, "test", progress=False, out_dir=tmp_path / "ok")
    with pytest.raises(DatasetError, match="not turned"):
        evaluate(run, centred, "test", progress=False, out_dir=tmp_path / "bad")


def test_windows_turned_in_steps_train_fast_vgqcnn_only_and_evaluate_only_a_net_trained_on_them(tmp_path):
    plain = tmp_path / "plain"
    make_synthetic_crop_dataset(plain, 16, 16, 32, seed=1)
    turned = _turned_copy(plain, tmp_path / "turned", jaw_turns=4)
    ds = open_crop_dataset(turned)
    assert ds.geometry.jaw_turns == 4
    ds.check_arch("fast_vgqcnn")
    run = tmp_path / "run"
    train(TrainConfig(samples=32, val_every_samples=32, **FAST), turned, run, progress=False)
    assert load_trained(run / "checkpoints" / "last.pt")[1]["geometry"]["jaw_turns"] == 4
    evaluate(run, turned, "test", progress=False, out_dir=tmp_path / "ok")
    with pytest.raises(DatasetError, match="not turned; the net was trained on crops turned in 4 steps"):
        evaluate(run, plain, "test", progress=False, out_dir=tmp_path / "bad")
    centred = _turned_copy(plain, tmp_path / "centred", jaw_turns=4, kappa_px=0.0)
    with pytest.raises(DatasetError, match="turned in 4 steps.*cannot train 'vgqcnn'"):
        open_crop_dataset(centred).check_arch("vgqcnn")


def test_freeze_encoder_trains_only_the_head_and_resumes_so(data, run, tmp_path):
    from training.networks import ENCODER_LAYERS

    cfg = TrainConfig(samples=64, val_every_samples=64, init=str(run), freeze_encoder=True, **FAST)
    train(cfg, data, tmp_path / "ft", progress=False)
    train(TrainConfig(**{**cfg.to_dict(), "samples": 128}), data, tmp_path / "ft", resume=True, progress=False)
    init, _ = load_trained(run)
    net, _ = load_trained(tmp_path / "ft")
    own, before = net.state_dict(), init.state_dict()
    encoder = [k for k in before if k.split(".")[0] in ENCODER_LAYERS]
    assert {k.split(".")[0] for k in encoder} >= {"conv1_1", "conv2_2", "fc3", "fc4_image"}
    for name in encoder:
        torch.testing.assert_close(own[name], before[name], msg=name)  # the encoder never moved
    assert not torch.equal(own["fc5.weight"], before["fc5.weight"])  # the head did
    with pytest.raises(ValueError, match="freeze_encoder need init"):
        TrainConfig(freeze_encoder=True)


def _with_families(data: Path, dest: Path, family) -> Path:
    """A copy of crop dataset ``data`` whose manifest gives object i the family ``family(i)``."""
    import shutil

    shutil.copytree(data, dest)
    m = json.loads((dest / "manifest.json").read_text())
    m["source"] = {"objects": [{"object_id": i, "family": family(i)} for i in range(30)]}
    (dest / "manifest.json").write_text(json.dumps(m))
    return dest


def test_family_sampling_draws_every_family_and_label_alike(data, tmp_path):
    from training.train import _family_cells, _family_order

    fam_data = _with_families(data, tmp_path / "families", lambda i: "mug" if i == 3 else "box")  # mugs: 1 object
    ds = open_crop_dataset(fam_data)
    sp = ds.split("train")
    ids, y = np.asarray(sp.arrays["object_id"]), np.asarray(sp.labels)
    mug = ids == 3
    assert 0 < mug.sum() < len(ids) / 4  # a minority family
    order = _family_order(TrainConfig(seed=3), _family_cells(sp, ds.object_families()), 0, 0, 40_000)
    for fam in (mug, ~mug):
        for label in (0, 1):
            if ((fam) & (y == label)).any():  # each (family, label) cell present: a quarter of the draws
                share = np.isin(order, np.flatnonzero(fam & (y == label))).mean()
                assert share == pytest.approx(1 / 4, abs=0.02)
    again = _family_order(TrainConfig(seed=3), _family_cells(sp, ds.object_families()), 0, 0, 40_000)
    assert np.array_equal(order, again)  # a resumed run draws the same epoch


def test_family_sampling_needs_a_dataset_that_records_families(data, tmp_path):
    with pytest.raises(DatasetError, match="families"):
        train(TrainConfig(samples=32, sampling="family", **FAST), data, tmp_path / "run", progress=False)
