"""vgq's records by hand: a model card written and read back field by field, normalisation
statistics of small arrays computed here, the dict forms of geometry and intrinsics, atomic
.npz writes, and the GQ-CNN rotated crop against numpy's own rotation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vgq import atomic
from vgq.camera import Intrinsics
from vgq.crop import CropGeometry, crop, rotated_crop
from vgq.model_card import CARD_NAME, ModelCard
from vgq.normalization import Normalization

COLUMNS = ("u", "v", "z", "qw", "qx", "qy", "qz")


def a_card(**kw) -> ModelCard:
    norm = Normalization(0.65, 0.03, COLUMNS, [0.5, -1.0, 0.7, 0.0, 0.0, 0.0, 0.0], [4.0, 5.0, 0.1, 1.0, 1.0, 1.0, 1.0])
    return ModelCard(
        model_version="fast_vgqcnn-abc",
        architecture="fast_vgqcnn",
        geometry=CropGeometry(96, 32, 30.0),
        intrinsics=Intrinsics(fx=500.0, fy=510.0, cx=150.0, cy=140.0, width=320, height=280),
        normalization=norm,
        files={"encoder": "e.onnx", "head": "h.onnx"},
        dataset={"recipe": "r"},
        training={"seed": 3},
        metrics={"test": {"n": 5}},
        export={"opset": 17},
        label_threshold=0.003,
        **kw,
    )


def test_model_card_round_trip_keeps_every_field(tmp_path):
    card = a_card(calibration={"method": "isotonic", "x": [0.0, 1.0], "y": [0.0, 1.0]})
    card.save(tmp_path)
    raw = json.loads((tmp_path / CARD_NAME).read_text())
    assert raw["format"] == "vgq-model-card" and raw["format_version"] == 1
    assert raw["geometry"] == {"window": 96, "out": 32, "kappa_px": 30.0}
    assert raw["intrinsics"]["fy"] == 510.0 and raw["intrinsics"]["height"] == 280
    assert raw["normalization"]["pose_std"][1] == 5.0 and raw["label_threshold"] == 0.003
    back = ModelCard.load(tmp_path)
    assert back == card
    assert (back.geometry, back.intrinsics, back.normalization) == (card.geometry, card.intrinsics, card.normalization)


def test_model_card_defaults_and_refusals(tmp_path):
    d = a_card().to_dict()
    for k in ("dataset", "training", "metrics", "export", "label_threshold", "calibration"):
        del d[k]
    card = ModelCard.from_dict(d)
    assert (card.dataset, card.training, card.metrics, card.export, card.calibration) == ({}, {}, {}, {}, {})
    assert card.label_threshold == 0.002 and card.calibrator() is None
    with pytest.raises(ValueError, match="not a model card"):
        ModelCard.from_dict({**d, "format": "other"})
    with pytest.raises(FileNotFoundError, match=CARD_NAME):
        ModelCard.load(tmp_path)
    (tmp_path / CARD_NAME).write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        ModelCard.load(tmp_path)


def test_normalisation_statistics_by_hand():
    images = np.array([[[0.5, 0.7]], [[0.9, 0.7]]])  # 4 pixels: mean 0.7, std sqrt(0.02)
    poses = np.array([[1.0, 10.0, 0.6, 0.9, 0.1, 0.2, 0.3], [3.0, 10.0, 0.8, -0.5, 0.4, 0.1, 0.2]])
    n = Normalization.from_data(images, poses, COLUMNS)
    assert n.image_mean == pytest.approx(0.7) and n.image_std == pytest.approx(np.sqrt(0.02))
    assert n.pose_mean == pytest.approx([2.0, 10.0, 0.7, 0.0, 0.0, 0.0, 0.0])
    assert n.pose_std == pytest.approx([1.0, 1.0, 0.1, 1.0, 1.0, 1.0, 1.0])  # v is constant: std 1, not 0
    np.testing.assert_allclose(n.normalize_image(np.array([0.7, 0.7 + np.sqrt(0.02)])), [0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(n.normalize_pose(poses[:1]), [[-1.0, 0.0, -1.0, 0.9, 0.1, 0.2, 0.3]], atol=1e-6)
    flat = Normalization.from_data(np.full((3, 4), 0.5), poses[:, 2:3], ("z",))  # constant: std 1, not 0
    assert flat.image_std == 1.0 and flat.image_mean == 0.5
    many = Normalization.from_data(np.arange(10_000, dtype=np.float32).reshape(-1, 2), np.zeros((5000, 1)), ("z",))
    assert many.image_mean == pytest.approx(4999.5) and many.image_std == pytest.approx(np.std(np.arange(10_000)))
    assert Normalization.from_dict(n.to_dict()) == n


@pytest.mark.parametrize(
    "bad, match",
    [
        (dict(pose_mean=[0.0, 1.0]), "one entry per pose column"),
        (dict(pose_std=[1.0, 1.0]), "one entry per pose column"),
        (dict(image_mean=float("nan")), "finite"),
        (dict(pose_std=[float("inf")]), "finite"),
        (dict(image_std=0.0), "std must be > 0"),
        (dict(pose_std=[-1.0]), "std must be > 0"),
    ],
)
def test_normalisation_refuses_bad_constants(bad, match):
    good = dict(image_mean=0.6, image_std=0.1, pose_columns=("z",), pose_mean=[0.5], pose_std=[0.2])
    with pytest.raises(ValueError, match=match):
        Normalization(**{**good, **bad})


def test_geometry_and_intrinsics_dict_forms():
    g = CropGeometry(64, 32, 20.5)
    assert g.to_dict() == {"window": 64, "out": 32, "kappa_px": 20.5} and CropGeometry.from_dict(g.to_dict()) == g
    i = Intrinsics(fx=400.0, fy=410.0, cx=100.5, cy=90.5, width=200, height=180)
    assert Intrinsics.from_dict(i.to_dict()) == i


def test_atomic_npz_compressed_and_plain(tmp_path):
    a, b = np.arange(6.0).reshape(2, 3), np.array([1, 2], np.int32)
    atomic.save_npz(tmp_path / "c.npz", a=a, b=b)
    atomic.save_npz(tmp_path / "p.npz", compressed=False, a=a, b=b)
    for f in ("c.npz", "p.npz"):
        with np.load(tmp_path / f) as d:
            assert sorted(d.files) == ["a", "b"] and np.array_equal(d["a"], a) and np.array_equal(d["b"], b)
    big = np.zeros((200, 200))
    atomic.save_npz(tmp_path / "zc.npz", z=big)
    atomic.save_npz(tmp_path / "zp.npz", compressed=False, z=big)
    assert (tmp_path / "zc.npz").stat().st_size < (tmp_path / "zp.npz").stat().st_size / 10
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith(".npz")] == []


def test_rotated_crop_by_quarter_turns_is_numpys_rotation():
    g = CropGeometry(96, 32, 0.0)
    rng = np.random.default_rng(0)
    depth = (0.7 + 0.05 * rng.random((300, 300))).astype(np.float32)
    depth[100:140, 160:170] = 0.6  # something off-centre to turn
    c = (149.5, 149.5)
    straight, _ = crop(depth, c, g)
    np.testing.assert_allclose(rotated_crop(depth, c, 0.0, g), straight, atol=1e-6)
    window = depth[102:198, 102:198]
    for k in (1, 2, 3):
        # PIL turns by +angle counter-clockwise as displayed: np.rot90 with the same k
        turned, _ = crop(np.pad(np.rot90(window, k), 102, mode="edge"), c, g)
        np.testing.assert_allclose(rotated_crop(depth, c, k * np.pi / 2, g), turned, atol=1e-5)


def test_constant_images_normalise_with_unit_std():
    """A constant image set has no spread: std 1 (no scaling), not rounding noise (~1e-8) that
    would blow inputs up by 1e8."""
    from vgq.normalization import Normalization

    cols = ["u", "v", "z", "qw", "qx", "qy", "qz"]
    n = Normalization.from_data(np.full((10, 32, 32), 0.7, np.float32), np.zeros((10, 7)), cols)
    assert n.image_std == 1.0 and abs(n.image_mean - 0.7) < 1e-6
