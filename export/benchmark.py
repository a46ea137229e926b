"""Inference benchmark: the paper's table "Inference time" (SPEC section 7) on this machine.

    python -m export.benchmark [--model-dir models/fast-vgqcnn-default] [--runs 1000] [--json out.json]

For k grasps (default 32, 64, 96, 128, 512), all in one run, median and p99 (ms) of:

* Fast-VGQ-CNN prediction: encoder on one crop + head on k grasps, as the service runs them
  (``service.runtime.FastModel``, its onnxruntime session options); and the head alone (the
  cached-image score call);
* VGQ-CNN prediction: one graph on k crops + k poses. The VGQ-CNN is exported with
  ``export.onnx_export.export_model`` into a temp folder from the Fast model's own weights
  (image stream, fc4, fc5, fc6; pc1 on the (z, q) columns): same cost as a trained one;
* preprocessing with ``vgq.crop``: Fast one crop per image, VGQ one crop per grasp; both
  then check the grasps and build pose rows (``vgq.grasps.pose_rows``);
* every encoder precision the model card holds (``fp32``, and ``int8`` from
  ``export.int8_encoder``): the encoder alone and encoder + head, each with its ratio to the
  fp32 FLOP floor; the service's ``encoder_precision auto`` serves the fastest (its choice is
  in the config of the report);
* speed-up VGQ / Fast (how many times faster Fast-VGQ-CNN is), and the FLOP floor of Fast:
  FLOPs of encoder + head (2 per multiply-add of Conv, Gemm, MatMul) divided by the peak
  of a 1024^3 MatMul measured in the same onnxruntime with the same threads, interleaved
  with the runs of each k (best of its runs). The FLOPs are the fp32 graphs' (``head.onnx``
  whole): an int8 head with dead units removed (``export.prune_head``) does less work than
  that floor counts, and the head row says how many units it kept.

Calls of the different models are interleaved in time, so load from other processes hits
them alike. VGQ-CNN is slow: it gets fewer runs (``--vgq-budget-s`` per k), said in the output.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DEFAULT_KS = (32, 64, 96, 128, 512)
ROOT = Path(__file__).resolve().parent.parent
DEFAULT_MODEL_DIR = ROOT / "models" / "fast-vgqcnn-default"


def _head_label(config: dict) -> str:
    """The served head's precision, and its pruning when the int8 head is pruned."""
    units = config.get("head_pruning")
    label = config.get("head_precision", "fp32")
    return f"{label}, fc5 {units['fc5_units_kept']} of {units['units']} units" if units else label


# ---- FLOPs and the machine's peak ---------------------------------------------------------
def graph_flops(path: str | Path, input_shapes: dict[str, tuple[int, ...]]) -> int:
    """FLOPs (2 per multiply-add) of the Conv, Gemm and MatMul nodes of an ONNX graph for
    the given concrete input shapes. Element-wise ops, pooling and activations are left out."""
    import onnx
    from onnx import shape_inference

    m = onnx.load(str(path))
    for inp in m.graph.input:
        if inp.name in input_shapes:
            dims = inp.type.tensor_type.shape.dim
            for d, v in zip(dims, input_shapes[inp.name]):
                d.ClearField("dim_param")
                d.dim_value = int(v)
    m = shape_inference.infer_shapes(m)
    shapes = {i.name: tuple(i.dims) for i in m.graph.initializer}
    for vi in list(m.graph.value_info) + list(m.graph.input) + list(m.graph.output):
        dims = tuple(d.dim_value for d in vi.type.tensor_type.shape.dim)
        if dims and all(dims):
            shapes[vi.name] = dims
    for n in m.graph.node:  # constants (e.g. the LRN band) as nodes
        if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value":
            shapes[n.output[0]] = tuple(n.attribute[0].t.dims)
    weighted = [n for n in m.graph.node if n.op_type in ("Conv", "Gemm", "MatMul")]
    missing = sorted({t for n in weighted for t in (n.input[0], n.output[0]) if t not in shapes})
    if missing:  # shapes that follow from values (e.g. the jaw grid's gathered rows): run the graph once
        shapes.update(_run_shapes(m, input_shapes, missing))
    total = 0
    for n in m.graph.node:
        try:
            if n.op_type == "Conv":
                out, w = shapes[n.output[0]], shapes[n.input[1]]
                total += 2 * int(np.prod(out)) * int(np.prod(w[1:]))
            elif n.op_type == "Gemm":
                a = shapes[n.input[0]]
                trans_a = next((at.i for at in n.attribute if at.name == "transA"), 0)
                out = shapes[n.output[0]]
                total += 2 * out[0] * out[1] * (a[0] if trans_a else a[1])
            elif n.op_type == "MatMul":
                a, out = shapes[n.input[0]], shapes[n.output[0]]
                total += 2 * int(np.prod(out)) * a[-1]
        except KeyError as e:
            raise ValueError(f"{path}: cannot infer the shapes of node {n.name!r} ({e})") from None
    return int(total)


def _run_shapes(model, input_shapes: dict[str, tuple[int, ...]], names: list[str]) -> dict[str, tuple[int, ...]]:
    """The shapes of the tensors ``names`` when ``model`` runs on inputs of ``input_shapes`` (all
    ones: a unit-ish pose, a depth of 1 m), for what static shape inference cannot tell."""
    import onnx
    import onnxruntime as ort
    from onnx import helper

    m = onnx.ModelProto()
    m.CopyFrom(model)
    outputs = {o.name for o in m.graph.output}
    for name in names:
        if name not in outputs:
            m.graph.output.append(helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None))
    s = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
    feeds = {i.name: np.ones(input_shapes[i.name], np.float32) for i in s.get_inputs()}
    return {name: tuple(a.shape) for name, a in zip(names, s.run(names, feeds))}


PEAK_N = 1024


def matmul_call(threads: int, n: int = PEAK_N):
    """A callable running one n x n x n float32 MatMul in onnxruntime (service session options)."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    from service.runtime import session_options

    vi = [helper.make_tensor_value_info(x, TensorProto.FLOAT, [n, n]) for x in "abc"]
    g = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "peak", vi[:2], vi[2:])
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    s = ort.InferenceSession(model.SerializeToString(), session_options(threads), providers=["CPUExecutionProvider"])
    a = np.random.default_rng(0).random((n, n), dtype=np.float32)
    feed = {"a": a, "b": a}
    return lambda: s.run(None, feed)


def matmul_peak_gflops(threads: int, n: int = PEAK_N, runs: int = 10) -> float:
    """Best GFLOP/s of an n x n x n float32 MatMul in onnxruntime (service session options)."""
    call = matmul_call(threads, n)
    for _ in range(3):
        call()
    return 2 * n**3 / min(_clock(call) for _ in range(runs)) / 1e9


# ---- timing ----------------------------------------------------------------------------------
def _clock(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def interleaved(tasks: dict[str, tuple[callable, int]], warmup: int = 20) -> dict[str, np.ndarray]:
    """Run each ``name: (fn, n)`` n times (after ``min(warmup, n)`` unrecorded calls), spreading
    every task's calls evenly over the whole run. Returns seconds per call."""
    for fn, n in tasks.values():
        for _ in range(min(warmup, n)):
            fn()
    order = sorted(((j + 0.5) / n, name) for name, (_, n) in tasks.items() for j in range(n))
    out = {name: [] for name in tasks}
    for _, name in order:
        out[name].append(_clock(tasks[name][0]))
    return {k: np.asarray(v) for k, v in out.items()}


def _stats(t: np.ndarray) -> dict:
    ms = t * 1e3
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "runs": int(len(ms))}


# ---- workload and models -------------------------------------------------------------------------
def fast_preprocess(depth, grasps, geom, center):
    """Fast-VGQ-CNN: one crop of the image, then k pose rows (du, dv, z, q)."""
    from vgq.crop import crop
    from vgq.grasps import pose_rows

    img, actual = crop(depth, center, geom)
    return img[None, None], pose_rows(grasps, actual, geom, len(grasps))


def turns_needed(grasps: np.ndarray, geom, intrinsics) -> int:
    """Windows a Fast-VGQ-CNN encodes for ``grasps`` (k, 7) near one window centre: 1, or for a model
    of windows turned towards the jaw (``geom.jaw_turns``), one per turn the grasps fall in."""
    if not geom.jaw_turns:
        return 1
    from vgq.turns import pose_jaw_angles, turn_index

    angles = pose_jaw_angles(grasps[:, :2], grasps[:, 2], grasps[:, 3:7], intrinsics)
    return len(np.unique(turn_index(angles, geom.jaw_turns)))


def vgq_preprocess(depth, grasps, geom_vgq, geom_fast, center):
    """VGQ-CNN: one centred crop per grasp, then k pose rows (z, q)."""
    from vgq.crop import crop, window_center, window_origin
    from vgq.grasps import pose_rows

    crops = np.stack([crop(depth, g[:2], geom_vgq)[0] for g in grasps])[:, None]
    c = window_center(window_origin(center, geom_fast), geom_fast)
    return crops, np.ascontiguousarray(pose_rows(grasps, c, geom_fast, len(grasps))[:, 2:])


def export_vgq_like(model_dir: Path, out_dir: Path, depth: np.ndarray, grasps: np.ndarray):
    """Export a VGQ-CNN with the Fast model's weights (export_model verifies it against torch)."""
    from export.from_onnx import fast_net_from_model_dir, vgq_net_like
    from export.onnx_export import export_model
    from vgq.crop import CropGeometry

    fast, card = fast_net_from_model_dir(model_dir)
    geom = CropGeometry(card.geometry.window, card.geometry.out, 0.0)
    center = np.array([(depth.shape[1] - 1) / 2, (depth.shape[0] - 1) / 2])
    crops, poses = vgq_preprocess(depth, grasps[:8].astype(np.float64), geom, card.geometry, center)
    vcard = export_model(
        vgq_net_like(fast),
        out_dir,
        crops[:, 0],
        poses,
        geom,
        card.intrinsics,
        dataset={"recipe": f"benchmark: weights of {card.model_version}"},
    )
    return out_dir / vcard.files["model"], geom


# ---- the benchmark ------------------------------------------------------------------------------
def run_benchmark(
    model_dir: str | Path = DEFAULT_MODEL_DIR,
    ks=DEFAULT_KS,
    runs: int = 1000,
    threads: int | None = None,
    vgq_budget_s: float = 4.0,
    log=print,
) -> dict:
    """Measure everything (see the module doc); returns the JSON-able report."""
    import onnxruntime as ort

    from service.runtime import FastModel, session_options
    from tools.loadtest.workload import load_workload
    from vgq.model_card import ENCODER_INPUT, HEAD_INPUTS, VGQ_INPUTS, VGQ_OUTPUT

    model_dir = Path(model_dir)
    threads = threads or max(1, os.cpu_count() or 1)
    kmax = max(ks)
    work = load_workload(kmax)
    depth, all_grasps = work.depth, work.grasps.astype(np.float64)
    fast = FastModel(model_dir, threads=threads)  # as the service runs it (head and encoder precision auto)
    variants = {p: FastModel(model_dir, threads=threads, encoder_precision=p) for p in fast.encoder_info["available"]}
    fast32 = FastModel(model_dir, threads=threads, head_precision="fp32") if fast.head_precision != "fp32" else None
    geom = fast.geometry
    center = np.array([(depth.shape[1] - 1) / 2, (depth.shape[0] - 1) / 2])
    notes = []
    with tempfile.TemporaryDirectory(prefix="vgq-bench-") as tmp:
        log(f"exporting a VGQ-CNN with the weights of {fast.version} (torch) ...")
        vgq_path, geom_vgq = export_vgq_like(model_dir, Path(tmp) / "vgqcnn", depth, all_grasps)
        vgq = ort.InferenceSession(str(vgq_path), session_options(threads), providers=["CPUExecutionProvider"])
        enc_path, head_path = model_dir / fast.card.files["encoder"], model_dir / fast.card.files["head"]
        s = geom.out
        enc_flops = graph_flops(enc_path, {ENCODER_INPUT: (1, 1, s, s)})
        peak_call = matmul_call(threads)
        peaks = []
        rows = {}
        # a placement head (card.placement_columns) reads each grasp's placement row after its pose: the
        # rows of the image as the service computes them, its analysis timed as preprocessing (once per image)
        placed = fast.n_pose != 7
        if placed:
            from service import placement

            camera, depth32 = fast.card.intrinsics, np.asarray(depth, np.float32)  # the upload as the service reads it
            analysis = placement.analyse(depth32, camera)
        for k in ks:
            grasps = np.ascontiguousarray(all_grasps[:k])
            crop1, poses = fast_preprocess(depth, grasps, geom, center)
            if placed:
                poses = np.column_stack([poses, placement.rows(analysis, grasps)]).astype(np.float32)
            term = fast.encode(crop1[0, 0])
            # a model of windows turned towards the jaw encodes one window per turn its grasps need
            windows = turns_needed(grasps, geom, fast.card.intrinsics)
            crop_n = np.ascontiguousarray(np.repeat(crop1[:, 0], windows, axis=0))
            crops, vposes = vgq_preprocess(depth, grasps, geom_vgq, geom, center)
            vfeed = {VGQ_INPUTS[0]: crops, VGQ_INPUTS[1]: vposes}
            t_vgq = min(_clock(lambda: vgq.run([VGQ_OUTPUT], vfeed)) for _ in range(2))
            t_vpre = _clock(lambda: vgq_preprocess(depth, grasps, geom_vgq, geom, center))
            n_vgq = int(min(runs, max(5, vgq_budget_s / max(t_vgq, 1e-6))))
            n_vpre = int(min(runs, max(5, vgq_budget_s / max(t_vpre, 1e-6))))
            log(f"k = {k}: {runs} Fast runs, {n_vgq} VGQ runs ...")
            t = interleaved(
                {
                    "fast": (lambda: fast.score(fast.encode(crop_n)[:1], poses), runs),
                    "head": (lambda: fast.score(term, poses), runs),
                    "encoder": (lambda: fast.encode(crop1[0, 0]), runs),
                    "vgq": (lambda: vgq.run([VGQ_OUTPUT], vfeed), n_vgq),
                    "fast_pre": (lambda: fast_preprocess(depth, grasps, geom, center), runs),
                    **(
                        {"placement": (lambda: placement.rows(placement.analyse(depth32, camera), grasps), runs)}
                        if placed
                        else {}
                    ),
                    "vgq_pre": (lambda: vgq_preprocess(depth, grasps, geom_vgq, geom, center), n_vpre),
                    "peak": (peak_call, max(5, min(50, runs // 20))),
                    **({"head_fp32": (lambda: fast32.score(term, poses), runs)} if fast32 else {}),
                    **{f"encoder_{p}": ((lambda m=m: m.encode(crop1[0, 0])), runs) for p, m in variants.items()},
                    **{
                        f"fast_{p}": ((lambda m=m: m.score(m.encode(crop_n)[:1], poses)), runs)
                        for p, m in variants.items()
                    },
                },
                warmup=min(20, max(2, runs // 10)),
            )
            # the peak of this k's time window: load from other processes lowers both alike
            peak = 2 * PEAK_N**3 / t.pop("peak").min() / 1e9
            peaks.append(peak)
            head_flops = graph_flops(head_path, {HEAD_INPUTS[0]: tuple(term.shape), HEAD_INPUTS[1]: (k, fast.n_pose)})
            st = {name: _stats(v) for name, v in t.items()}
            floor_ms = (windows * enc_flops + head_flops) / (peak * 1e9) * 1e3
            fm, vm = st["fast"]["median_ms"], st["vgq"]["median_ms"]
            rows[k] = {
                **st,
                "speedup_prediction": vm / fm,
                "speedup_total": (vm + st["vgq_pre"]["median_ms"])
                / (fm + st["fast_pre"]["median_ms"] + st.get("placement", {}).get("median_ms", 0.0)),
                "matmul_peak_gflops": peak,
                "windows": windows,
                "fast_mflop": (windows * enc_flops + head_flops) / 1e6,
                "head_mflop": head_flops / 1e6,
                "flop_floor_ms": floor_ms,
                "head_flop_floor_ms": head_flops / (peak * 1e9) * 1e3,
                "fast_over_floor": fm / floor_ms,
                "head_over_floor": st["head"]["median_ms"] / (head_flops / (peak * 1e9) * 1e3),
                "encoder_flop_floor_ms": enc_flops / (peak * 1e9) * 1e3,
                "variants": {
                    p: {
                        "fast_over_floor": st[f"fast_{p}"]["median_ms"] / floor_ms,
                        "encoder_over_floor": st[f"encoder_{p}"]["median_ms"] / (enc_flops / (peak * 1e9) * 1e3),
                        "speedup_prediction": vm / st[f"fast_{p}"]["median_ms"],
                    }
                    for p in variants
                },
            }
            fewer = [f"{what} {n} runs" for what, n in (("prediction", n_vgq), ("preprocessing", n_vpre)) if n < runs]
            if fewer:
                notes.append(
                    f"k = {k}: VGQ-CNN {', '.join(fewer)}, fewer than {runs} (too slow; "
                    "the p99 of few runs is close to their max)"
                )
    return {
        "machine": machine_info(threads),
        "config": {
            "model_dir": str(model_dir),
            "model_version": fast.version,
            "head_precision": fast.head_precision,
            # the int8 head's pruning (export.prune_head), when it has one: units kept of fc4 and fc5
            "head_pruning": fast.card.export.get("int8_head", {}).get("pruning", {}).get("units")
            if fast.head_precision == "int8"
            else None,
            "encoder_precision": fast.encoder_precision,
            "encoder_selection": fast.encoder_info,
            "runs": runs,
            "ks": list(ks),
            "threads": threads,
            "vgq_budget_s": vgq_budget_s,
            "image": work.source,
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        },
        "encoder_mflop": enc_flops / 1e6,
        "matmul_peak_gflops": max(peaks),
        "rows": {str(k): v for k, v in rows.items()},
        "notes": notes,
    }


#: CPU flags that decide which precision is fast: AVX2 / FMA (fp32), AVX-512, int8 dot products
#: (VNNI), bf16, AMX tiles.
ISA_FLAGS = (
    "avx2",
    "fma",
    "avx512f",
    "avx512bw",
    "avx512_vnni",
    "avx_vnni",
    "avx512_bf16",
    "amx_tile",
    "amx_int8",
    "amx_bf16",
)


def isa_flags(cpuinfo: str = "/proc/cpuinfo") -> list[str]:
    """The ``ISA_FLAGS`` this CPU reports (Linux /proc/cpuinfo; empty elsewhere)."""
    try:
        with open(cpuinfo) as f:
            flags = set(next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), []))
    except OSError:
        return []
    return [x for x in ISA_FLAGS if x in flags]


def machine_info(threads: int) -> dict:
    import onnxruntime as ort

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "threads": threads,
        "isa": isa_flags(),
        "onnxruntime": ort.__version__,
        "python": platform.python_version(),
        "load_average": list(os.getloadavg()),
    }


def markdown(report: dict) -> str:
    rows = report["rows"]
    ks = list(rows)

    def line(label, fn):
        return f"| {label} | " + " | ".join(fn(rows[k]) for k in ks) + " |"

    def ms(name):
        return lambda r: f"{r[name]['median_ms']:.2f} / {r[name]['p99_ms']:.2f}"

    m, c = report["machine"], report["config"]
    variants = list(rows[ks[0]].get("variants", {}))
    out = [
        f"{m['cpu']}, {m['cores']} cores, ISA {' '.join(m.get('isa', [])) or 'unknown'}; onnxruntime {m['onnxruntime']}, {m['threads']} thread(s); "
        f"model {c['model_version']}; {c['runs']} runs; load average {m['load_average'][0]:.2f}; {c['date']}",
        f"best MatMul peak {report['matmul_peak_gflops']:.1f} GFLOP/s ({PEAK_N}^3, measured between the runs of each k); "
        f"encoder {report['encoder_mflop']:.1f} MFLOP; encoder precision served by auto: {c.get('encoder_precision', 'fp32')} "
        f"(start-up timing, ms: {c.get('encoder_selection', {}).get('median_ms') or 'one encoder, not timed'})",
        "",
        "| k grasps | " + " | ".join(ks) + " |",
        "|---|" + "---:|" * len(ks),
        line("VGQ-CNN prediction, ms (median / p99)", ms("vgq")),
        *(
            [line("windows encoded per call (one per turn the grasps need: jaw_turns)", lambda r: str(r["windows"]))]
            if any(r.get("windows", 1) != 1 for r in rows.values())
            else []
        ),
        line("Fast-VGQ-CNN prediction (encoder + head), ms", ms("fast")),
        line(f"Fast-VGQ-CNN head only (cached image, {_head_label(c)}), ms", ms("head")),
        *([line("Fast-VGQ-CNN head only, fp32 graph, ms", ms("head_fp32"))] if "head_fp32" in rows[ks[0]] else []),
        line("Fast-VGQ-CNN encoder only, ms", ms("encoder")),
        line("VGQ-CNN preprocessing (k crops), ms", ms("vgq_pre")),
        line("Fast-VGQ-CNN preprocessing (1 crop), ms", ms("fast_pre")),
        *(
            [line("placement head: the image's analysis and the k placement rows, ms", ms("placement"))]
            if "placement" in rows[ks[0]]
            else []
        ),
        line("speed-up VGQ / Fast, prediction", lambda r: f"{r['speedup_prediction']:.1f}x"),
        line("speed-up VGQ / Fast, preprocessing + prediction", lambda r: f"{r['speedup_total']:.1f}x"),
        line("Fast FLOPs (encoder + head), MFLOP", lambda r: f"{r['fast_mflop']:.0f}"),
        line("MatMul peak in the same window, GFLOP/s", lambda r: f"{r['matmul_peak_gflops']:.0f}"),
        line("Fast FLOP floor, ms (head alone)", lambda r: f"{r['flop_floor_ms']:.2f} ({r['head_flop_floor_ms']:.2f})"),
        line(
            "Fast time / FLOP floor (head alone)", lambda r: f"{r['fast_over_floor']:.2f} ({r['head_over_floor']:.2f})"
        ),
        *[
            x
            for p in variants
            for x in (
                line(f"encoder {p}: encoder only, ms", ms(f"encoder_{p}")),
                line(f"encoder {p}: encoder + head, ms", ms(f"fast_{p}")),
                line(
                    f"encoder {p}: (encoder + head) / fp32 FLOP floor (encoder alone)",
                    lambda r, p=p: (
                        f"{r['variants'][p]['fast_over_floor']:.2f} ({r['variants'][p]['encoder_over_floor']:.2f})"
                    ),
                ),
                line(
                    f"encoder {p}: speed-up VGQ / Fast, prediction",
                    lambda r, p=p: f"{r['variants'][p]['speedup_prediction']:.1f}x",
                ),
            )
        ],
        line("VGQ-CNN runs", lambda r: str(r["vgq"]["runs"])),
    ]
    out += [f"- {n}" for n in report["notes"]]
    return "\n".join(out)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m export.benchmark", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--model-dir", default=str(DEFAULT_MODEL_DIR), help="Fast-VGQ-CNN model folder (default: the bundled one)"
    )
    p.add_argument("--runs", type=int, default=1000, help="timed runs per measurement after warm-up (default 1000)")
    p.add_argument("--ks", default=",".join(map(str, DEFAULT_KS)), help="grasp counts (default 32,64,96,128,512)")
    p.add_argument(
        "--threads", type=int, default=0, help="onnxruntime intra-op threads (default: all cores, as the service)"
    )
    p.add_argument(
        "--vgq-budget-s", type=float, default=4.0, help="seconds per k for the slow VGQ-CNN runs (default 4)"
    )
    p.add_argument("--json", help="also write the report as JSON to this file")
    a = p.parse_args(argv)
    try:
        ks = tuple(int(x) for x in a.ks.split(",") if x.strip())
    except ValueError:
        p.error(f"--ks must be comma-separated integers, got {a.ks!r}")
    if not ks or min(ks) < 1 or a.runs < 1 or a.threads < 0 or not a.vgq_budget_s > 0:
        p.error("--ks and --runs must be >= 1, --threads >= 0, --vgq-budget-s > 0")
    if not (Path(a.model_dir) / "model_card.json").is_file():
        p.error(f"--model-dir {a.model_dir!r} holds no model_card.json")
    try:
        report = run_benchmark(
            a.model_dir, ks, a.runs, a.threads or None, a.vgq_budget_s, log=lambda s: print(s, file=sys.stderr)
        )
    except (ValueError, RuntimeError) as e:
        print(f"benchmark: {e}", file=sys.stderr)
        sys.exit(2)
    print(markdown(report))
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")
    return report


if __name__ == "__main__":
    main()
