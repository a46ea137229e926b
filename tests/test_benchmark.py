"""export.benchmark and export.from_onnx: FLOP counts, reading graphs back into torch, the table."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import torch
from conftest import synthetic_crops

from export.benchmark import graph_flops, isa_flags, markdown, run_benchmark
from export.from_onnx import fast_net_from_model_dir, vgq_net_like

# multiply-adds of the 32 x 32 encoder: conv1_1, conv1_2, LRN band, conv2_1, conv2_2, LRN band, fc3, fc4_image
ENCODER_MACS = (
    1024 * 64 * 49
    + 1024 * 64 * 64 * 25
    + 1024 * 64 * 64
    + 2 * 256 * 64 * 64 * 9
    + 256 * 64 * 64
    + 4096 * 1024
    + 1024 * 1024
)
HEAD_MACS_PER_GRASP = 7 * 16 + 16 * 1024 + 1024 * 1024 + 1024  # pc1, fc4 pose half, fc5, out


def test_graph_flops_of_encoder_counts_every_multiply_add(model_dir):
    assert graph_flops(model_dir / "encoder.onnx", {"depth_crop": (1, 1, 32, 32)}) == 2 * ENCODER_MACS


def test_graph_flops_of_head_grow_with_k(model_dir):
    flops = graph_flops(model_dir / "head.onnx", {"image_term": (1, 1024), "poses": (10, 7)})
    assert flops == 2 * 10 * HEAD_MACS_PER_GRASP


def test_graph_flops_of_a_jaw_grid_head_count_its_grid_reads_and_layers(tmp_path):
    """The jaw grid's shapes follow from values (gathered rows): counted by running the graph once."""
    from export.onnx_export import export_model
    from training.networks import GraspQualityNet
    from vgq.camera import DEFAULT_INTRINSICS
    from vgq.crop import CropGeometry
    from vgq.normalization import Normalization

    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw").eval()
    imgs, poses, _ = synthetic_crops(16, np.random.default_rng(5))
    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns))
    export_model(net, tmp_path / "m", imgs, poses, CropGeometry(96, 32, 0.0), DEFAULT_INTRINSICS)
    flops = graph_flops(tmp_path / "m" / "head.onnx", {"image_term": (1, net.encoding_width), "poses": (10, 7)})
    grid = 8 * 3 * 64 * 128 + 128 * 1024  # roi_fc1, roi_fc2 (the corner reads: element-wise Muls, not counted)
    assert flops == 2 * 10 * (HEAD_MACS_PER_GRASP + grid)


def test_net_read_back_from_onnx_reproduces_the_graphs(model_dir):
    net, card = fast_net_from_model_dir(model_dir)
    imgs, poses, _ = synthetic_crops(16, np.random.default_rng(11))
    enc = ort.InferenceSession(str(model_dir / "encoder.onnx"), providers=["CPUExecutionProvider"])
    head = ort.InferenceSession(str(model_dir / "head.onnx"), providers=["CPUExecutionProvider"])
    p = head.run(None, {"image_term": enc.run(None, {"depth_crop": imgs[:1, None]})[0], "poses": poses})[0]
    with torch.no_grad():
        ref = net.head(net.encode(torch.from_numpy(imgs[:1, None])), torch.from_numpy(poses)).numpy()
    assert card.architecture == "fast_vgqcnn" and np.abs(p - ref).max() < 1e-5


def test_vgq_net_like_shares_the_image_stream(model_dir):
    fast, _ = fast_net_from_model_dir(model_dir)
    vgq = vgq_net_like(fast)
    imgs, _, _ = synthetic_crops(2, np.random.default_rng(12))
    x = torch.from_numpy(imgs[:, None])
    with torch.no_grad():
        assert vgq.arch == "vgqcnn" and torch.allclose(vgq.encode(x), fast.encode(x))


def test_benchmark_table_has_a_column_per_k_and_every_row(model_dir):
    report = run_benchmark(model_dir, ks=(8, 16), runs=5, threads=1, vgq_budget_s=0.01, log=lambda s: None)
    table = markdown(report)
    lines = table.splitlines()
    header = next(line for line in lines if line.startswith("| k grasps"))
    rows = [line for line in lines if line.startswith("| ") and line is not header]
    assert header.split("|")[2:4] == [" 8 ", " 16 "]
    assert len(rows) == 13 + 4 and all(len(r.split("|")) == 5 for r in rows)  # + 4 rows for the fp32 encoder
    r = report["rows"]["16"]
    assert r["fast"]["runs"] == 5 and r["vgq"]["runs"] == 5 and r["speedup_prediction"] > 0
    assert r["fast_mflop"] == (2 * ENCODER_MACS + 2 * 16 * HEAD_MACS_PER_GRASP) / 1e6


def test_a_placement_head_is_timed_with_its_placement_rows_and_their_analysis():
    """The bundle's head reads placement rows (since 2026-12-07): scored with the service's rows of
    the image, the analysis timed as a preprocessing row of its own."""
    report = run_benchmark(
        "models/fast-vgqcnn-default", ks=(8,), runs=3, threads=1, vgq_budget_s=0.01, log=lambda s: None
    )
    r = report["rows"]["8"]
    assert r["placement"]["runs"] == 3 and r["fast"]["median_ms"] > 0
    assert "| placement head: the image's analysis and the k placement rows, ms |" in markdown(report)


def test_a_model_of_turned_windows_is_timed_encoding_a_window_per_turn_its_grasps_need(model_dir, tmp_path):
    import json
    import shutil

    from export.benchmark import turns_needed
    from tools.loadtest.workload import load_workload
    from vgq.camera import DEFAULT_INTRINSICS
    from vgq.crop import CropGeometry

    turned = tmp_path / "turned"
    shutil.copytree(model_dir, turned)
    card = json.loads((turned / "model_card.json").read_text())
    card["geometry"]["jaw_turns"] = 4
    (turned / "model_card.json").write_text(json.dumps(card))
    grasps = load_workload(16).grasps.astype(np.float64)
    windows = turns_needed(grasps, CropGeometry(jaw_turns=4), DEFAULT_INTRINSICS)
    assert turns_needed(grasps, CropGeometry(), DEFAULT_INTRINSICS) == 1 and windows > 1
    report = run_benchmark(turned, ks=(16,), runs=5, threads=1, vgq_budget_s=0.01, log=lambda s: None)
    r = report["rows"]["16"]
    assert r["windows"] == windows
    assert r["fast_mflop"] == (windows * 2 * ENCODER_MACS + 2 * 16 * HEAD_MACS_PER_GRASP) / 1e6
    assert "windows encoded per call" in markdown(report)


def test_benchmark_compares_every_encoder_precision_in_one_run(model_dir, tmp_path):
    import shutil

    from export.int8_encoder import add_int8_encoder

    m = tmp_path / "m"
    shutil.copytree(model_dir, m)
    add_int8_encoder(
        m, synthetic_crops(32, np.random.default_rng(5))[0], synthetic_crops(300, np.random.default_rng(6))
    )
    report = run_benchmark(m, ks=(8,), runs=5, threads=1, vgq_budget_s=0.01, log=lambda s: None)
    r = report["rows"]["8"]
    assert set(r["variants"]) == {"fp32", "int8"} and r["encoder_int8"]["runs"] == r["fast_fp32"]["runs"] == 5
    assert all(v["fast_over_floor"] > 0 and v["encoder_over_floor"] > 0 for v in r["variants"].values())
    assert report["config"]["encoder_precision"] in ("fp32", "int8")
    table = markdown(report)
    assert "encoder int8: (encoder + head) / fp32 FLOP floor" in table and "ISA " in table


def test_isa_flags_picks_the_precision_relevant_flags(tmp_path):
    f = tmp_path / "cpuinfo"
    f.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 fma avx512f avx512_vnni amx_tile amx_int8\n")
    assert isa_flags(str(f)) == ["avx2", "fma", "avx512f", "avx512_vnni", "amx_tile", "amx_int8"]
    assert isa_flags(str(tmp_path / "none")) == []


def test_wider_net_read_back_from_onnx(tmp_path):
    from export.onnx_export import export_model
    from training.networks import GraspQualityNet
    from vgq.camera import DEFAULT_INTRINSICS
    from vgq.crop import CropGeometry
    from vgq.normalization import Normalization

    imgs, poses, _ = synthetic_crops(32, np.random.default_rng(13))
    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", conv2_channels=80).eval()
    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns))
    export_model(
        net, tmp_path / "m", imgs, poses, CropGeometry(96, 32, 36.0), DEFAULT_INTRINSICS, dataset={}, training={}
    )
    import onnx

    assert "Pow" not in {n.op_type for n in onnx.load(str(tmp_path / "m" / "encoder.onnx")).graph.node}  # both LRNs
    back, _ = fast_net_from_model_dir(tmp_path / "m")
    x, p = torch.from_numpy(imgs[:1, None]), torch.from_numpy(poses[:4])
    with torch.no_grad():
        assert back.conv2_channels == 80 and torch.allclose(
            back.head(back.encode(x), p), net.head(net.encode(x), p), atol=1e-5
        )
