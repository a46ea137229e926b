"""An int8 variant of Fast-VGQ-CNN's head graph, kept only if it scores like the fp32 one.

Nearly all of the head's work is fc5 (1024 x 1024 per grasp: 2.1 of its 2.2 MFLOP). Only that
layer is quantised (onnxruntime dynamic quantisation: int8 weights per output channel, uint8
activations scaled per call), and in a jaw-grid head the two layers that read its grid; the pose
layers stay fp32, since raw poses mix pixels (tens)
with depths that matter to the millimetre and do not survive one shared 8-bit scale.

Dynamic quantisation scales fc5's input per call, so an int8 score depends slightly on the
other grasps of the same request. The check therefore scores in batches of ``batch`` grasps,
as the service does, refuses the int8 head when its balanced accuracy falls by more than
``max_bacc_drop`` or a probability moves by more than ``max_abs_diff``, and records how far a
grasp scored alone differs from the same grasp scored in a batch. Serve with
``head_precision fp32`` where scores must not depend on their batch-mates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from service.runtime import session_options
from training.metrics import binary_metrics
from vgq.model_card import ENCODER_INPUT, ENCODER_OUTPUT, HEAD_INPUTS, HEAD_OUTPUT

MAX_BACC_DROP = 0.005
MAX_ABS_DIFF = 0.05


class QuantizationError(ValueError):
    """The int8 head does not score like the fp32 head."""


@dataclass(frozen=True)
class Int8Check:
    n: int
    n_positive: int
    balanced_accuracy_fp32: float
    balanced_accuracy_int8: float
    max_abs_diff_probability: float
    mean_abs_diff_probability: float
    decisions_changed: int  # grasps on the other side of 0.5
    max_abs_diff_alone_vs_batch: float  # int8: a grasp scored alone vs in a batch of ``batch``
    batch: int
    quantized_nodes: tuple[str, ...]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["quantized_nodes"] = list(self.quantized_nodes)
        return d


def largest_gemm(model_path: str | Path) -> str:
    """Name of the Gemm / MatMul node with the largest weight (fc5 in the head graph)."""
    m = onnx.load(str(model_path))
    sizes = {i.name: int(np.prod(i.dims)) for i in m.graph.initializer}
    nodes = [(max(sizes.get(x, 0) for x in n.input), n.name) for n in m.graph.node if n.op_type in ("Gemm", "MatMul")]
    if not nodes:
        raise QuantizationError(f"{model_path}: no Gemm or MatMul node to quantise")
    return max(nodes)[1]


def head_nodes_to_quantize(head_path: str | Path) -> tuple[str, ...]:
    """The head's layers worth int8: its largest fully connected layer (fc5) and, in a jaw-grid
    head, the two layers that read the grid (``roi_fc1``, ``roi_fc2``: 1,536 x 128 and 128 x 1,024
    per grasp, fed by image features, not raw poses)."""
    m = onnx.load(str(head_path))
    grid = [n.name for n in m.graph.node if n.op_type in ("Gemm", "MatMul") and "/roi_fc" in n.name]
    return (largest_gemm(head_path), *grid)


def quantize_head(head_path: str | Path, out_path: str | Path) -> tuple[str, ...]:
    """Write ``out_path``: ``head_path`` with ``head_nodes_to_quantize`` in int8.
    Returns the names of the quantised nodes."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    nodes = head_nodes_to_quantize(head_path)
    # dynamic quantisation rewrites a Gemm as MatMul + Add first; the MatMul keeps the name + "_MatMul"
    quantize_dynamic(
        str(head_path),
        str(out_path),
        per_channel=True,
        weight_type=QuantType.QInt8,
        nodes_to_quantize=[x for node in nodes for x in (node, node + "_MatMul")],
    )
    done = sum(n.op_type in ("MatMulInteger", "DynamicQuantizeMatMul") for n in onnx.load(str(out_path)).graph.node)
    if done < len(nodes):
        raise QuantizationError(f"onnxruntime left {len(nodes) - done} of {nodes} of {head_path} unquantised")
    return nodes


def session(path) -> ort.InferenceSession:
    """An onnxruntime session with the service's options on one thread: checked as served."""
    return ort.InferenceSession(str(path), session_options(1), providers=["CPUExecutionProvider"])


def image_terms(encoder: str | Path | ort.InferenceSession, crops: np.ndarray) -> np.ndarray:
    """(n, 1024) image terms of (n, S, S) or (n, 1, S, S) crops (metres) through the encoder graph
    (a path, or a session already open on it)."""
    enc = encoder if isinstance(encoder, ort.InferenceSession) else session(encoder)
    x = np.ascontiguousarray(crops, np.float32).reshape(len(crops), 1, *np.shape(crops)[-2:])
    return np.concatenate(
        [enc.run([ENCODER_OUTPUT], {ENCODER_INPUT: x[i : i + 256]})[0] for i in range(0, len(x), 256)]
    )


def check_int8_head(
    encoder_path,
    head_path,
    int8_path,
    crops: np.ndarray,
    poses: np.ndarray,
    labels: np.ndarray,
    quantized_nodes: tuple[str, ...] = (),
    max_bacc_drop: float = MAX_BACC_DROP,
    max_abs_diff: float = MAX_ABS_DIFF,
    batch: int = 128,
    n_alone: int = 256,
) -> Int8Check:
    """Score (n, S, S) or (n, 1, S, S) crops (metres) with their (n, 7) raw poses through encoder +
    each head, ``batch`` grasps per head call (the head broadcasts one image term per grasp);
    raise QuantizationError when the int8 head is off. ``n_alone`` grasps are also scored one
    per call to measure the int8 head's dependence on its batch."""
    y = np.asarray(labels).astype(bool)
    if y.all() or not y.any():
        raise QuantizationError("the int8 check needs positive and negative examples")
    h32, h8 = session(head_path), session(int8_path)
    poses = np.ascontiguousarray(poses, np.float32)
    terms = image_terms(encoder_path, crops)

    def score(sess, b: int, n: int) -> np.ndarray:
        return np.concatenate(
            [
                sess.run([HEAD_OUTPUT], {HEAD_INPUTS[0]: terms[i : i + b], HEAD_INPUTS[1]: poses[i : i + b]})[0]
                for i in range(0, n, b)
            ]
        )

    n = len(y)
    p32, p8 = score(h32, batch, n), score(h8, batch, n)
    alone = min(n_alone, n)
    d = np.abs(p32 - p8)
    check = Int8Check(
        n,
        int(y.sum()),
        binary_metrics(y, p32)["balanced_accuracy"],
        binary_metrics(y, p8)["balanced_accuracy"],
        float(d.max()),
        float(d.mean()),
        int(((p32 > 0.5) != (p8 > 0.5)).sum()),
        float(np.abs(score(h8, 1, alone) - p8[:alone]).max()),
        batch,
        tuple(quantized_nodes),
    )
    if (
        check.balanced_accuracy_fp32 - check.balanced_accuracy_int8 > max_bacc_drop
        or check.max_abs_diff_probability > max_abs_diff
    ):
        raise QuantizationError(
            f"int8 head scores unlike the fp32 head: {check.to_dict()} "
            f"(allowed: balanced accuracy drop {max_bacc_drop}, |dp| {max_abs_diff})"
        )
    return check


# ---- int8 encoder ----------------------------------------------------------------------------------
# Static QDQ quantisation: int8 weights per output channel, uint8 activations with ranges fixed by
# calibration crops. Only the layers that carry the encoder's cost are quantised: the Conv with
# the largest kernel volume (conv1_2: 210 of its 275 MFLOP) and the fully connected layers with
# stored weights (fc3, fc4: 21 of its 22 MB, memory-bound at batch 1). The first conv (raw depth
# in, millimetres matter) and the convs after LRN stay fp32: measured on the bundled model,
# conv2_1 in int8 alone moved probabilities by 0.08 on average; conv1_2 + fc3 + fc4 by 0.02.
ENCODER_MAX_BACC_DROP = 0.005
ENCODER_MAX_MEAN_ABS_DIFF = 0.025
ENCODER_MAX_FLIP_FRACTION = 0.02


@dataclass(frozen=True)
class EncoderCheck:
    """An encoder variant scored against the fp32 encoder (both through the fp32 head)."""

    precision: str
    n: int
    n_positive: int
    balanced_accuracy_fp32: float
    balanced_accuracy_variant: float
    max_abs_diff_probability: float
    mean_abs_diff_probability: float
    decisions_changed: int  # grasps on the other side of 0.5
    quantized_nodes: tuple[str, ...]
    check_data: str
    calibration: str

    def to_dict(self) -> dict:
        d = asdict(self)
        d["quantized_nodes"] = list(self.quantized_nodes)
        return d


def encoder_nodes_to_quantize(model_path: str | Path) -> tuple[str, ...]:
    """The encoder's Conv with the largest kernel volume (C_in * kh * kw) and every Gemm / MatMul
    whose weight is stored in the graph (see the section comment)."""
    m = onnx.load(str(model_path))
    inits = {i.name: tuple(i.dims) for i in m.graph.initializer}
    convs = [
        (int(np.prod(inits[n.input[1]][1:])), n.name)
        for n in m.graph.node
        if n.op_type == "Conv" and len(n.input) > 1 and n.input[1] in inits
    ]
    fcs = [n.name for n in m.graph.node if n.op_type in ("Gemm", "MatMul") and any(x in inits for x in n.input[1:2])]
    if not convs:
        raise QuantizationError(f"{model_path}: no Conv with stored weights to quantise")
    return (max(convs)[1], *fcs)


def quantize_encoder(
    encoder_path: str | Path, out_path: str | Path, calibration_crops: np.ndarray, nodes: tuple[str, ...] | None = None
) -> tuple[str, ...]:
    """Write ``out_path``: ``encoder_path`` with ``nodes`` (default ``encoder_nodes_to_quantize``)
    in int8 (QDQ, per-channel weights), activation ranges from the (n, S, S) or (n, 1, S, S)
    calibration crops (metres; min / max per tensor). Returns the quantised node names."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    crops = np.ascontiguousarray(calibration_crops, np.float32)
    crops = crops.reshape(len(crops), 1, *crops.shape[-2:])
    if len(crops) < 16 or not np.isfinite(crops).all():
        raise QuantizationError(f"need >= 16 finite calibration crops, got {len(crops)}")
    nodes = tuple(nodes or encoder_nodes_to_quantize(encoder_path))

    class Crops(CalibrationDataReader):
        def __init__(self):
            self.it = iter(range(len(crops)))

        def get_next(self):
            i = next(self.it, None)
            return None if i is None else {ENCODER_INPUT: crops[i : i + 1]}

    quantize_static(
        str(encoder_path),
        str(out_path),
        Crops(),
        quant_format=QuantFormat.QDQ,
        per_channel=True,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        nodes_to_quantize=list(nodes),
        calibrate_method=CalibrationMethod.MinMax,
    )
    if not any(n.op_type == "QuantizeLinear" for n in onnx.load(str(out_path)).graph.node):
        raise QuantizationError(f"onnxruntime left the nodes {nodes} of {encoder_path} unquantised")
    return nodes


def check_encoder_variant(
    encoder_path,
    variant_path,
    head_path,
    crops: np.ndarray,
    poses: np.ndarray,
    labels: np.ndarray,
    precision: str = "int8",
    quantized_nodes: tuple[str, ...] = (),
    check_data: str = "",
    calibration: str = "",
    max_bacc_drop: float = ENCODER_MAX_BACC_DROP,
    max_mean_abs_diff: float = ENCODER_MAX_MEAN_ABS_DIFF,
    max_flip_fraction: float = ENCODER_MAX_FLIP_FRACTION,
) -> EncoderCheck:
    """Score labelled (n, S, S) crops (metres) with their (n, 7) raw poses through each encoder and
    the fp32 head; raise QuantizationError when the variant's balanced accuracy falls by more than
    ``max_bacc_drop``, its probabilities move by more than ``max_mean_abs_diff`` on average, or more
    than ``max_flip_fraction`` of the decisions (p > 0.5) change. A quantised encoder moves every
    grasp of an image together, so the check bounds the mean shift and the flips rather than the
    single largest shift (recorded too)."""
    y = np.asarray(labels).astype(bool)
    if y.all() or not y.any():
        raise QuantizationError("the encoder check needs positive and negative examples")
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    e32, ev, head = (
        ort.InferenceSession(str(p), so, providers=["CPUExecutionProvider"])
        for p in (encoder_path, variant_path, head_path)
    )
    crops = np.ascontiguousarray(crops, np.float32).reshape(len(crops), 1, *np.shape(crops)[-2:])
    poses = np.ascontiguousarray(poses, np.float32)

    def probabilities(enc) -> np.ndarray:
        out = []
        for i in range(0, len(crops), 256):
            terms = enc.run([ENCODER_OUTPUT], {ENCODER_INPUT: crops[i : i + 256]})[0]
            out.append(head.run([HEAD_OUTPUT], {HEAD_INPUTS[0]: terms, HEAD_INPUTS[1]: poses[i : i + 256]})[0])
        return np.concatenate(out)

    p32, pv = probabilities(e32), probabilities(ev)
    d = np.abs(p32 - pv)
    check = EncoderCheck(
        precision,
        len(y),
        int(y.sum()),
        binary_metrics(y, p32)["balanced_accuracy"],
        binary_metrics(y, pv)["balanced_accuracy"],
        float(d.max()),
        float(d.mean()),
        int(((p32 > 0.5) != (pv > 0.5)).sum()),
        tuple(quantized_nodes),
        check_data,
        calibration,
    )
    if (
        check.balanced_accuracy_fp32 - check.balanced_accuracy_variant > max_bacc_drop
        or check.mean_abs_diff_probability > max_mean_abs_diff
        or check.decisions_changed > max_flip_fraction * check.n
    ):
        raise QuantizationError(
            f"{precision} encoder scores unlike the fp32 encoder: {check.to_dict()} (allowed: balanced "
            f"accuracy drop {max_bacc_drop}, mean |dp| {max_mean_abs_diff}, flips {max_flip_fraction:.0%})"
        )
    return check
