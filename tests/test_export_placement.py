"""Export of a placement head (vgq.placement): the graphs read the placement row after the pose
columns, the card names its columns, and the folder reads back into the same torch network."""

import numpy as np
import onnx
import pytest
import torch

from export.from_onnx import fast_net_from_model_dir
from export.onnx_export import ExportError, export_model
from service.runtime import FastModel
from training.networks import GraspQualityNet
from vgq.camera import DEFAULT_INTRINSICS
from vgq.crop import CropGeometry
from vgq.model_card import ModelCard
from vgq.placement import PLACEMENT_COLUMNS

GEOM = CropGeometry(96, 32, 36.0)


def rows(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    imgs = (0.6 + 0.01 * rng.standard_normal((n, 32, 32))).astype(np.float32)
    poses = np.c_[rng.uniform(-10, 10, (n, 2)), rng.uniform(0.5, 0.8, n), np.tile([1.0, 0, 0, 0], (n, 1))]
    place = np.c_[np.ones(n), rng.uniform(0, 0.08, (n, 3)), rng.uniform(-0.05, 0.05, n), rng.uniform(0, 0.1, (n, 2))]
    return imgs, np.c_[poses, place].astype(np.float32)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw", placement=True).eval()
    with torch.no_grad():
        net.pc1.weight[:, -7:] = 3.0 * torch.randn(net.pc1.weight.shape[0], 7)  # the row matters
        net.fc4_pose.weight.mul_(2.0)
    imgs, poses = rows(16, np.random.default_rng(0))
    out = tmp_path_factory.mktemp("place") / "m"
    export_model(net, out, imgs, poses, GEOM, DEFAULT_INTRINSICS, training={"config": {"roi_head": "jaw"}})
    return net, out


def test_the_card_names_the_placement_columns_and_the_head_reads_them(exported):
    net, out = exported
    card = ModelCard.load(out)
    assert card.placement_columns == PLACEMENT_COLUMNS and card.head_pose_width == 14
    imgs, poses = rows(8, np.random.default_rng(1))
    model = FastModel(out, threads=1, head_precision="fp32", encoder_precision="fp32")
    term = model.encode(imgs[:1])
    with torch.no_grad():
        ref = net.head(torch.from_numpy(term), torch.from_numpy(poses)).numpy()
    got = model.score(term, poses)
    np.testing.assert_allclose(got, ref, atol=1e-4)
    moved = poses.copy()
    moved[:, 8:10] += 0.05  # 5 cm further from the object's centre, along the jaw axis
    assert np.abs(model.score(term, moved) - got).max() > 1e-3


def test_the_folder_reads_back_into_the_same_network(exported):
    net, out = exported
    back, _ = fast_net_from_model_dir(out)
    imgs, poses = rows(8, np.random.default_rng(2))
    x = torch.from_numpy(imgs[:, None])
    with torch.no_grad():
        a = torch.softmax(net(x, torch.from_numpy(poses)), 1)[:, 1]
        b = torch.softmax(back(x, torch.from_numpy(poses)), 1)[:, 1]
    assert back.n_place == 7 and torch.allclose(a, b, atol=1e-5)


def test_the_jaw_grid_head_graph_has_one_product_for_the_grid_and_placement_terms(tmp_path):
    """A placement stream beside the jaw grid: the head graph reads the grid with Gathers,
    point-major (no Transpose, no batched MatMul), and place_fc2's columns ride in roi_fc2's
    product; the folder reads back into the same layers."""
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw", placement=True, placement_units=16).eval()
    imgs, poses = rows(16, np.random.default_rng(4))
    out = tmp_path / "m"
    config = {"roi_head": "jaw", "placement_units": 16}
    export_model(net, out, imgs, poses, GEOM, DEFAULT_INTRINSICS, training={"config": config})
    nodes = onnx.load(str(out / "head.onnx")).graph.node
    assert "Transpose" not in {n.op_type for n in nodes}
    assert [n.name for n in nodes if n.op_type == "MatMul"] == ["/head/roi_fc2/MatMul"]
    back, _ = fast_net_from_model_dir(out)
    for layer in ("roi_fc1", "roi_fc2", "place_fc2"):
        torch.testing.assert_close(getattr(back, layer).weight, getattr(net, layer).weight, msg=layer)


def test_export_refuses_verification_poses_without_the_placement_row(exported, tmp_path):
    net, _ = exported
    imgs, poses = rows(4, np.random.default_rng(3))
    with pytest.raises(ExportError, match=r"\(4, 14\)"):
        export_model(net, tmp_path / "bad", imgs, poses[:, :7], GEOM, DEFAULT_INTRINSICS)


def test_a_card_without_placement_reads_and_writes_as_before(model_dir):
    card = ModelCard.load(model_dir)
    assert card.placement_columns == () and "placement_columns" not in card.to_dict()


def test_evaluate_scores_a_placement_model_also_with_its_rows_blanked(exported, tmp_path):
    import json

    from export.evaluate import main
    from training.synthetic import make_synthetic_crop_dataset

    _, out = exported
    make_synthetic_crop_dataset(tmp_path / "crops", 8, 8, 64, signal="placement", seed=4)
    main(["--model-dir", str(out), "--data", str(tmp_path / "crops"), "--max-n", "64", "--blank-placement",
          "--json", str(tmp_path / "r.json")])  # fmt: skip
    r = json.loads((tmp_path / "r.json").read_text())["results"]
    blank = f"{out} (placement rows unknown)"
    assert set(r) == {str(out), blank}
    assert r[str(out)]["all"]["auc"] != r[blank]["all"]["auc"]


def test_evaluate_refuses_a_placement_model_rows_cut_at_the_true_grasp_depth(exported, tmp_path, capsys):
    import json

    from export.evaluate import main
    from training.synthetic import make_synthetic_crop_dataset

    _, out = exported
    make_synthetic_crop_dataset(tmp_path / "crops", 8, 8, 64, signal="placement", seed=4)
    m = json.loads((tmp_path / "crops" / "manifest.json").read_text())
    del m["placement_grasp_depth"]  # cut before the crop stage read grasps at the image's depth scale
    (tmp_path / "crops" / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(out), "--data", str(tmp_path / "crops"), "--max-n", "64"])
    assert e.value.code == 2 and "none made as the service makes them" in capsys.readouterr().err


def test_a_placement_stream_serves_and_reads_back_as_trained(tmp_path):
    torch.manual_seed(1)
    net = GraspQualityNet("fast_vgqcnn", placement=True, placement_units=16).eval()
    with torch.no_grad():
        net.place_fc2.weight.normal_(0.0, 0.5)  # the stream matters
    imgs, poses = rows(16, np.random.default_rng(3))
    out = tmp_path / "m"
    export_model(net, out, imgs, poses, GEOM, DEFAULT_INTRINSICS, training={"config": {"placement_units": 16}})
    model = FastModel(out, threads=1, head_precision="fp32", encoder_precision="fp32")
    term = model.encode(imgs[:1])
    with torch.no_grad():
        ref = net.head(torch.from_numpy(term), torch.from_numpy(poses)).numpy()
    np.testing.assert_allclose(model.score(term, poses), ref, atol=1e-4)
    moved = poses.copy()
    moved[:, 8:10] += 0.05
    assert np.abs(model.score(term, moved) - model.score(term, poses)).max() > 1e-3
    back, _ = fast_net_from_model_dir(out)
    x = torch.from_numpy(imgs[:, None])
    with torch.no_grad():
        a = torch.softmax(net(x, torch.from_numpy(poses)), 1)[:, 1]
        b = torch.softmax(back(x, torch.from_numpy(poses)), 1)[:, 1]
    assert back.placement_units == 16 and torch.allclose(a, b, atol=1e-5)


def test_model_ab_compares_placement_models(exported):
    """export.model_ab on a placement model (its head reads 14 columns): the held-out grasps with
    "not known" placement rows; a folder against itself agrees exactly."""
    from export.model_ab import compare

    _, out = exported
    r = compare(out, out, k=16, rounds=1, calls=1)
    assert r["max_abs_diff"] == 0.0 and r["decisions_changed"] == 0 and r["head_a_over_b"] > 0
