"""Crop-dataset reading: validation errors name the problem; architecture compatibility."""

import json

import numpy as np
import pytest

from training.data import DatasetError, open_crop_dataset
from training.synthetic import make_synthetic_crop_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("crops") / "data"
    make_synthetic_crop_dataset(path, 40, 16, 16, kappa_px=36.0, seed=0)
    return path


def test_round_trip_memory_mapped(data):
    ds = open_crop_dataset(data)
    assert ds.arch == "fast_vgqcnn" and ds.geometry.kappa_px == 36.0
    assert {k: v["n"] for k, v in ds.counts().items()} == {"train": 40, "val": 16, "test": 16}
    assert isinstance(ds.split("train").arrays["images"], np.memmap)


def test_batch_selects_architecture_pose_columns(data):
    sp = open_crop_dataset(data).split("train")
    img, pose, lab = sp.batch(np.array([5, 1, 3]), "vgqcnn")
    assert img.shape == (3, 1, 32, 32) and pose.shape == (3, 5) and lab.tolist() == sp.labels[[5, 1, 3]].tolist()
    np.testing.assert_array_equal(pose.numpy(), sp.arrays["poses"][[5, 1, 3]][:, 2:])  # z, qw..qz


def test_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        open_crop_dataset(tmp_path / "nope")


def test_wrong_format(tmp_path, data):
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "vgq-grasps", "format_version": 1}))
    with pytest.raises(DatasetError, match="format 'vgq-grasps', expected 'vgq-crops'"):
        open_crop_dataset(tmp_path)


def test_wrong_dtype_names_field(tmp_path, data):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(data, bad)
    np.save(bad / "train" / "labels.npy", np.zeros(40, dtype=np.int64))
    with pytest.raises(DatasetError, match="'labels'"):
        open_crop_dataset(bad)


def test_architecture_compatibility(tmp_path, data):
    ds = open_crop_dataset(data)
    ds.check_arch("fast_vgqcnn")
    with pytest.raises(DatasetError, match="cannot train 'vgqcnn'"):
        ds.check_arch("vgqcnn")  # off-centre crops
    centred = tmp_path / "centred"
    make_synthetic_crop_dataset(centred, 4, 4, 4, arch="vgqcnn", kappa_px=0.0)
    c = open_crop_dataset(centred)
    c.check_arch("fast_vgqcnn")  # kappa = 0 ablation point
    with pytest.raises(DatasetError, match="cannot train 'gqcnn'"):
        c.check_arch("gqcnn")


def test_both_crop_writers_write_one_manifest_layout(tmp_path):
    """datagen crops and training.synthetic both go through vgq.schema.write_crop_manifest."""
    from datagen_fakes import fake_dataset

    from datagen.crops import make_crops

    fake_dataset(tmp_path / "g", n_objects=10, n_images=1, n_grasps=5)
    real = make_crops(tmp_path / "g", tmp_path / "c", "vgqcnn", log=lambda s: None)
    synth = make_synthetic_crop_dataset(tmp_path / "s", 8, 4, 4, arch="vgqcnn", kappa_px=0.0)
    # extra keys: intrinsics when the source has them; sensor and inpaint describe rendered crops only
    optional = {"recipe", "seed", "versions", "intrinsics", "sensor", "inpaint"}
    assert set(synth) - optional == set(real) - optional
    for m, root in ((real, tmp_path / "c"), (synth, tmp_path / "s")):
        ds = open_crop_dataset(root)
        assert ds.manifest == json.loads((root / "manifest.json").read_text())
        for s, c in ds.counts().items():
            assert {k: m["counts"][s][k] for k in ("n", "positive")} == c
            assert m["counts"][s]["positivity"] == pytest.approx(c["positive"] / c["n"])
        # not resampled: the native positivity is that of all the crops
        total = sum(c["n"] for c in m["counts"].values())
        assert m["native_counts"]["n"] == total


def test_crops_of_a_sampled_dataset_record_the_positivity_before_sampling(tmp_path):
    from datagen_fakes import fake_dataset

    from datagen.crops import make_crops
    from datagen.sampling import SamplingParams, sample_dataset

    fake_dataset(tmp_path / "g", n_objects=10, n_images=2, n_grasps=40, seed=4)
    stats = sample_dataset(
        tmp_path / "g", tmp_path / "s", SamplingParams(target_positivity=50.0), log=lambda s: None, plot=False
    )
    m = make_crops(tmp_path / "s", tmp_path / "c", "vgqcnn", log=lambda s: None)
    native = stats["steps"]["native"]
    assert (m["native_counts"]["n"], m["native_counts"]["positive"]) == (native["grasps"], native["positive"])
    assert m["native_counts"]["n"] > sum(c["n"] for c in m["counts"].values())  # sampling dropped grasps


def test_dataset_info_records_label_sensor_and_z_range(tmp_path):
    """What the model card inherits: the label the crops carry (the paper's for datasets made
    before the label setting), the sensor model and the train split's z range."""
    from datagen_fakes import fake_dataset

    from datagen.crops import make_crops

    fake_dataset(tmp_path / "g", n_objects=10, n_images=1, n_grasps=5)
    make_crops(tmp_path / "g", tmp_path / "c", "fast_vgqcnn", log=lambda s: None, sensor="clean")
    ds = open_crop_dataset(tmp_path / "c")
    info = ds.info()
    assert info["label"]["kind"] == "paper" and info["label"]["threshold"] == ds.label_threshold
    assert info["sensor"]["name"] == "clean"
    z = np.asarray(ds.split("train").arrays["poses"])[:, 2]
    assert info["z_range"] == [float(z.min()), float(z.max())]
