"""vgq-grasps / vgq-crops storage: round trip, atomicity, clear errors on bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from datagen_fakes import fake_dataset, fake_object

from datagen import storage
from vgq.schema import CROP_FIELDS, WRITTEN_CROP_FIELDS


def test_shard_round_trip_keeps_every_array(tmp_path):
    images, grasps = fake_object(np.random.default_rng(1), 3)
    entry = storage.write_shard(tmp_path, 3, images, grasps, 0.002)
    assert entry["file"] == "shards/obj_00003.npz"
    assert entry["num_positive"] == int((grasps["quality"] > 0.002).sum())
    img2, gr2 = storage.read_shard(tmp_path / entry["file"], entry["sha256"])
    for k in images:
        np.testing.assert_array_equal(img2[k], images[k])
        assert img2[k].dtype == images[k].dtype
    for k in grasps:
        np.testing.assert_array_equal(gr2[k], grasps[k])


def test_a_shard_read_can_leave_its_depth_images_compressed(tmp_path):
    images, grasps = fake_object(np.random.default_rng(1), 3)
    entry = storage.write_shard(tmp_path, 3, images, grasps, 0.002)
    img2, gr2 = storage.read_shard(tmp_path / entry["file"], entry["sha256"], skip=("depth",))
    assert "depth" not in img2 and set(img2) == set(images) - {"depth"}
    np.testing.assert_array_equal(img2["camera_phi"], images["camera_phi"])
    assert set(gr2) == set(grasps)


def test_shards_load_with_numpy_as_written_by_savez(tmp_path):
    images, grasps = fake_object(np.random.default_rng(2), 1)
    data = storage.encode_shard(images, grasps)
    (tmp_path / "s.npz").write_bytes(data)
    with np.load(tmp_path / "s.npz") as z:
        np.testing.assert_array_equal(z["depth"], images["depth"])
    np.savez_compressed(tmp_path / "ref.npz", **images, **grasps)  # level 1 against numpy's 6: bounded growth
    assert len(data) < 2 * (tmp_path / "ref.npz").stat().st_size


def test_write_shard_rejects_wrong_dtype(tmp_path):
    images, grasps = fake_object(np.random.default_rng(1), 0)
    grasps["u"] = grasps["u"].astype(np.float64)
    with pytest.raises(ValueError, match="'u'"):
        storage.write_shard(tmp_path, 0, images, grasps, 0.002)


def test_open_dataset_iterates_listed_shards_and_ignores_partial_files(tmp_path):
    fake_dataset(tmp_path, n_objects=2)
    # leftovers of a killed writer: a temp file and a shard the manifest does not list
    (tmp_path / "shards" / ".obj_00002.npz.tmp-abc").write_bytes(b"half a zip")
    (tmp_path / "shards" / "obj_00007.npz").write_bytes(b"garbage")
    ds = storage.open_dataset(tmp_path)
    shards = list(ds)
    assert [s.object_id for s in shards] == [0, 1]
    assert [s.name for s in shards] == ["fake000", "fake001"]
    assert ds.manifest["counts"]["grasps"] == sum(len(s.grasps["u"]) for s in shards)


def test_corrupt_shard_is_named(tmp_path):
    fake_dataset(tmp_path, n_objects=1)
    p = tmp_path / "shards" / "obj_00000.npz"
    data = bytearray(p.read_bytes())
    data[100] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(storage.DatasetError, match="obj_00000.npz"):
        list(storage.open_dataset(tmp_path))
    with pytest.raises(storage.DatasetError, match="obj_00000.npz"):
        list(storage.open_dataset(tmp_path, verify=False))


def test_foreign_shard_is_named(tmp_path):
    m = fake_dataset(tmp_path, n_objects=1)
    p = tmp_path / "shards" / "obj_00000.npz"
    np.savez(p, something=np.zeros(3))
    m["shards"][0].pop("sha256")
    storage.write_manifest(tmp_path, m)
    with pytest.raises(storage.DatasetError, match=r"obj_00000.npz.*missing field"):
        list(storage.open_dataset(tmp_path))


def test_foreign_or_missing_manifest(tmp_path):
    with pytest.raises(storage.DatasetError, match="does not exist"):
        storage.open_dataset(tmp_path / "nope")
    with pytest.raises(storage.DatasetError, match="no manifest.json"):
        storage.open_dataset(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(storage.DatasetError, match="something-else"):
        storage.open_dataset(tmp_path)


def test_npy_writer_is_atomic(tmp_path):
    w = storage.NpyWriter(tmp_path / "x.npy", "float32", (5, 2))
    w.array[:] = 1.5
    assert not (tmp_path / "x.npy").exists()  # not visible until closed
    w.close()
    np.testing.assert_array_equal(np.load(tmp_path / "x.npy"), np.full((5, 2), 1.5, np.float32))
    a = storage.NpyWriter(tmp_path / "y.npy", "float32", (5, 2))
    a.abort()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npy"]


def test_crop_writers_cover_every_crop_field(tmp_path):
    ws = storage.crop_writers(tmp_path, "train", 0)
    assert set(ws) == set(WRITTEN_CROP_FIELDS) > set(CROP_FIELDS)
    for w in ws.values():
        w.close()
    assert all((tmp_path / "train" / f"{k}.npy").is_file() for k in WRITTEN_CROP_FIELDS)


def test_staged_file_replaces_the_old_one_only_when_its_block_succeeds(tmp_path):
    from vgq import atomic

    target = tmp_path / "graph.onnx"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic.staged(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("check refused")
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["graph.onnx"]
    with atomic.staged(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.endswith(".tmp")
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and sorted(p.name for p in tmp_path.iterdir()) == ["graph.onnx"]
