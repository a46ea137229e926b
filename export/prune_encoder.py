"""Drop the encoder's dead channels and units (see export.prune_head for the head's).

Fast-VGQ-CNN's encoder is conv1_1 -> conv1_2 -> LRN -> pool -> conv2_1 -> conv2_2 -> LRN -> pool ->
fc3 -> fc4_image, each conv and fc3 followed by a ReLU. A ReLU channel that is zero for every
input contributes nothing downstream: in the bundled v2 model's int8 encoder 42 of conv1_2's 64
channels, 6 of conv2_2's and 643 of fc3's 1,024 units never fire on calibration crops. Removing
them (the channel's filter and bias, per-channel quantisation scales included; the next layer's
input slice; the LRN's band rows and columns, which only sum the squares of channels that are
zero anyway; fc3's input columns of a removed conv2_2 channel) leaves the image term unchanged
wherever they stay dead, and cuts conv1_2, the encoder's biggest layer, to a third.

Which channels are dead is measured on the graph being pruned (the maximum of each ReLU output
over calibration crops, every pixel), and the pruned graph is only kept when it scores like the
unpruned one through the fp32 head (PRUNE_* bounds). ``export.int8_encoder`` quantises the whole
encoder and then prunes the int8 graph, so the calibrated ranges are those of the whole network;
``python -m export.prune_encoder`` prunes a folder's int8 encoder in place. ``encoder.onnx``
(fp32) keeps every channel.
"""

from __future__ import annotations

import hashlib
import logging
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import helper, numpy_helper

from vgq import atomic
from vgq.model_card import ENCODER_INPUT, ModelCard

from .prune_head import PruningError

#: the pruned fp32 encoder against the exact one (through the fp32 head): far tighter than int8's bounds
PRUNE_MAX_BACC_DROP = 0.001
PRUNE_MAX_MEAN_ABS_DIFF = 0.001
PRUNE_MAX_FLIP_FRACTION = 0.001

#: ops a channel passes through unchanged in index (a pruned channel is simply absent after them);
#: Quantize / DequantizeLinear only with one scale for the whole tensor (an int8 graph's activations)
CHANNEL_WISE = {"Relu", "Mul", "Div", "Sqrt", "MaxPool", "Add", "Sub", "QuantizeLinear", "DequantizeLinear"}


def relu_maxima(encoder_path: str | Path, crops: np.ndarray, batch: int = 512) -> dict[str, np.ndarray]:
    """Each ReLU output's maximum per channel (axis 1) over (n, S, S) or (n, 1, S, S) crops."""
    g = onnx.load(str(encoder_path))
    relus = [n.output[0] for n in g.graph.node if n.op_type == "Relu"]
    for r in relus:
        g.graph.output.append(helper.make_tensor_value_info(r, onnx.TensorProto.FLOAT, None))
    s = ort.InferenceSession(g.SerializeToString(), providers=["CPUExecutionProvider"])
    x = np.ascontiguousarray(crops, np.float32).reshape(len(crops), 1, *np.shape(crops)[-2:])
    out: dict[str, np.ndarray] = {}
    for i in range(0, len(x), batch):
        for name, a in zip(relus, s.run(relus, {ENCODER_INPUT: x[i : i + batch]})):
            m = a.max(axis=tuple(ax for ax in range(a.ndim) if ax != 1))
            out[name] = m if name not in out else np.maximum(out[name], m)
    return out


class _Graph:
    """Index of an ONNX graph: producers, consumers, initialisers and Constant tensors by name."""

    def __init__(self, model: onnx.ModelProto):
        self.model, self.g = model, model.graph
        self.producer = {o: n for n in self.g.node for o in n.output}
        self.consumers: dict[str, list] = defaultdict(list)
        for n in self.g.node:
            for i in n.input:
                self.consumers[i].append(n)
        self.inits = {t.name: t for t in self.g.initializer}
        self.consts = {n.output[0]: n for n in self.g.node if n.op_type == "Constant"}

    def array(self, name: str) -> np.ndarray | None:
        if name in self.inits:
            return numpy_helper.to_array(self.inits[name])
        if name in self.consts:
            return numpy_helper.to_array(self.consts[name].attribute[0].t)
        return None

    def set(self, name: str, value: np.ndarray) -> None:
        t = numpy_helper.from_array(np.ascontiguousarray(value), name)  # its dtype kept (int8 weights)
        if name in self.inits:
            self.inits[name].CopyFrom(t)
        else:
            self.consts[name].attribute[0].t.CopyFrom(t)

    def stored(self, name: str) -> bool:
        """A layer input held in the graph: an initialiser, or one dequantised from an initialiser."""
        dq = self.producer.get(name)
        return name in self.inits or (dq is not None and dq.op_type == "DequantizeLinear" and dq.input[0] in self.inits)

    def weight(self, name: str) -> np.ndarray:
        """A stored layer input (see ``stored``) as its array (int8 when dequantised: the shape is what counts)."""
        return self.array(name) if name in self.inits else self.array(self.producer[name].input[0])

    def take(self, name: str, index: np.ndarray, axis: int) -> None:
        """Keep ``index`` along ``axis`` of a stored layer input; a dequantised one's per-channel
        scale and zero point along the same axis too."""
        if name in self.inits:
            self.set(name, np.take(self.array(name), index, axis=axis))
            return
        dq = self.producer[name]
        q = self.array(dq.input[0])
        q_axis = next((a.i for a in dq.attribute if a.name == "axis"), 1) % max(q.ndim, 1)
        self.set(dq.input[0], np.take(q, index, axis=axis))
        if q_axis == axis % q.ndim:
            for i in dq.input[1:3]:
                if i and self.array(i).size > 1:
                    self.set(i, np.take(self.array(i), index, axis=0))


def _layer_of(graph: _Graph, relu) -> object | None:
    """The Conv or Gemm whose output ``relu`` rectifies, through per-tensor Quantize / DequantizeLinear."""
    node = graph.producer.get(relu.input[0])
    while node is not None and node.op_type in ("QuantizeLinear", "DequantizeLinear") and _per_tensor(graph, node):
        node = graph.producer.get(node.input[0])
    return node if node is not None and node.op_type in ("Conv", "Gemm") else None


def _per_tensor(graph: _Graph, node) -> bool:
    return all(graph.array(i) is None or graph.array(i).size <= 1 for i in node.input[1:])


def _is_band(graph: _Graph, node) -> bool:
    """An LRN's channel sum: a 1 x 1 Conv whose (C, C, 1, 1) weight is a stored constant."""
    w = graph.array(node.input[1]) if node.op_type == "Conv" and len(node.input) > 1 else None
    return w is not None and node.input[1] in graph.consts and w.shape[2:] == (1, 1) and w.shape[0] == w.shape[1]


def prune_encoder_graph(encoder_path: str | Path, out_path: str | Path, kept: dict[str, np.ndarray]) -> dict:
    """Write ``out_path``: the encoder with only the ``kept`` channels (indices, sorted) of each
    named ReLU output. Returns {relu output: (kept, total)}. Raises PruningError on a graph whose
    layout it does not know."""
    graph = _Graph(onnx.load(str(encoder_path)))
    summary = {}
    for relu_out, keep in kept.items():
        keep = np.asarray(keep, np.int64)
        relu = graph.producer.get(relu_out)
        layer = _layer_of(graph, relu) if relu is not None and relu.op_type == "Relu" else None
        if layer is None or not graph.stored(layer.input[1]):
            raise PruningError(f"{encoder_path}: {relu_out} is not the ReLU of a Conv or Gemm with stored weights")
        total = graph.weight(layer.input[1]).shape[0]
        if layer.op_type == "Gemm" and not any(a.name == "transB" and a.i == 1 for a in layer.attribute):
            raise PruningError(f"{encoder_path}: {layer.name} is a Gemm without transB")
        if len(keep) == 0:
            raise PruningError(f"{encoder_path}: every channel of {relu_out} is dead; nothing to keep")
        summary[relu_out] = (len(keep), total)
        if len(keep) == total:
            continue
        graph.take(layer.input[1], keep, 0)
        if len(layer.input) > 2:
            graph.take(layer.input[2], keep, 0)
        _slice_consumers(graph, relu_out, keep, total, str(encoder_path))
    del graph.g.value_info[:]  # intermediate shapes recorded by the quantiser: stale after pruning
    onnx.checker.check_model(graph.model)
    onnx.save(graph.model, str(out_path))
    return summary


def _slice_consumers(graph: _Graph, start: str, keep: np.ndarray, total: int, where: str) -> None:
    """Follow ``start`` through channel-wise ops, LRN bands and Flatten to the weighted layers that
    read it, and cut their input channels (or a Flatten's blocks of columns) to ``keep``."""
    todo, seen = [(start, 1)], set()  # (tensor, 1, or -1 after a Flatten: a block of columns per channel)
    while todo:
        name, block = todo.pop()
        for node in graph.consumers.get(name, []):
            if id(node) in seen:
                continue
            seen.add(id(node))
            if _is_band(graph, node):
                graph.set(node.input[1], graph.array(node.input[1])[keep][:, keep])
                if len(node.input) > 2:
                    graph.set(node.input[2], graph.array(node.input[2])[keep])
                todo.append((node.output[0], block))
            elif node.op_type in CHANNEL_WISE:
                params = node.input[1:] if node.op_type.endswith("Linear") else node.input  # Q / DQ: scale, zero point
                if any(graph.array(i) is not None and graph.array(i).size > 1 for i in params):
                    raise PruningError(f"{where}: {node.name} mixes {start} with a stored per-channel tensor")
                todo.append((node.output[0], block))
            elif node.op_type == "Flatten":
                todo.append((node.output[0], -1))
            elif node.op_type == "Conv" and graph.stored(node.input[1]) and block == 1:
                graph.take(node.input[1], keep, 1)
            elif node.op_type in ("Gemm", "MatMul") and graph.stored(node.input[1]):
                if node.op_type == "Gemm" and not any(a.name == "transB" and a.i == 1 for a in node.attribute):
                    raise PruningError(f"{where}: {node.name} is a Gemm without transB")
                axis = 1 if node.op_type == "Gemm" else 0
                n_in = graph.weight(node.input[1]).shape[axis]
                hw = n_in // total if block == -1 else 1
                if n_in != total * hw:
                    raise PruningError(f"{where}: {node.name} reads {n_in} inputs, not a multiple of {total}")
                graph.take(node.input[1], (keep[:, None] * hw + np.arange(hw)[None, :]).ravel(), axis)
            else:
                raise PruningError(f"{where}: cannot prune {start} through {node.op_type} {node.name}")


def _leaves_graph(graph: _Graph, start: str) -> bool:
    """Whether ``start``'s channels reach a graph output without passing a weighted layer (e.g. the
    jaw-grid head's feature map, which the encoding carries as it is): the head reads every channel."""
    outputs = {o.name for o in graph.g.output}
    todo, seen = [start], set()
    while todo:
        name = todo.pop()
        if name in outputs:
            return True
        for node in graph.consumers.get(name, []):
            weighted = node.op_type in ("Conv", "Gemm", "MatMul") and graph.stored(node.input[1])
            if id(node) in seen or (weighted and not _is_band(graph, node)):
                continue
            seen.add(id(node))
            todo.extend(node.output)
    return False


def dead_channels(encoder_path: str | Path, crops: np.ndarray) -> dict[str, np.ndarray]:
    """The channels of every ReLU that fire (max > 0) on some calibration crop: {relu output: kept};
    a ReLU whose channels leave the encoder as they are (a jaw-grid model's conv2 map) keeps them all."""
    if len(crops) < 16 or not np.isfinite(crops).all():
        raise PruningError(f"need >= 16 finite calibration crops, got {len(crops)}")
    graph = _Graph(onnx.load(str(encoder_path)))
    return {
        name: np.arange(len(m)) if _leaves_graph(graph, name) else np.flatnonzero(m > 0)
        for name, m in relu_maxima(encoder_path, crops).items()
    }


def prune_encoder(
    encoder_path: str | Path,
    out_path: str | Path,
    head_path: str | Path,
    calibration_crops: np.ndarray,
    check: tuple[np.ndarray, np.ndarray, np.ndarray],
    check_data: str = "",
) -> dict:
    """Write ``out_path``: ``encoder_path`` (fp32 or int8) without the channels that never fire on
    ``calibration_crops`` (measured on that graph itself), checked against it through the fp32
    head on labelled ``check`` crops within the PRUNE_* bounds (QuantizationError otherwise).
    Returns the card's record: channels kept per ReLU and the check."""
    from .quantize import check_encoder_variant

    summary = prune_encoder_graph(encoder_path, out_path, dead_channels(encoder_path, calibration_crops))
    result = check_encoder_variant(
        encoder_path,
        out_path,
        head_path,
        *check,
        precision="pruned",
        check_data=check_data,
        calibration=f"dead channels of {len(calibration_crops)} crops",
        max_bacc_drop=PRUNE_MAX_BACC_DROP,
        max_mean_abs_diff=PRUNE_MAX_MEAN_ABS_DIFF,
        max_flip_fraction=PRUNE_MAX_FLIP_FRACTION,
    )
    return {
        "kept": {k: list(v) for k, v in summary.items()},
        "n_calibration": int(len(calibration_crops)),
        "check": result.to_dict(),
    }


def prune_folder_encoder(
    model_dir: str | Path, calibration_crops: np.ndarray, check, check_data: str = "", calibration_data: str = ""
) -> dict:
    """Prune a folder's int8 encoder in place (its quantisation kept: the same graph without its
    dead channels) once the pruned graph scores like it; the card's ``export.int8_encoder`` keeps
    its check (of the unpruned graph) and gains ``pruning``. Atomic writes."""
    model_dir = Path(model_dir)
    card = ModelCard.load(model_dir)
    if "encoder_int8" not in card.files:
        raise PruningError(f"{model_dir}: no int8 encoder to prune (python -m export.int8_encoder adds one, pruned)")
    if "pruning" in card.export.get("int8_encoder", {}):
        raise PruningError(f"{model_dir}: its int8 encoder is pruned already")
    current = model_dir / card.files["encoder_int8"]
    with atomic.staged(current) as tmp:
        record = prune_encoder(current, tmp, model_dir / card.files["head"], calibration_crops, check, check_data)
        record["calibration_data"] = calibration_data
        digest = hashlib.sha256(tmp.read_bytes()).hexdigest()
    card.export["int8_encoder"]["pruning"] = record
    card.export["int8_encoder"]["sha256"] = digest
    card.save(model_dir)
    return record


def main(argv=None) -> dict:
    from .int8_encoder import check_crops, crop_split, parse_variant_args, variant_parser
    from .quantize import QuantizationError

    p = variant_parser(
        "python -m export.prune_encoder",
        __doc__,
        "exported Fast-VGQ-CNN folder with an int8 encoder (pruned in place)",
        "finds the dead channels",
        50000,
    )
    a = parse_variant_args(p, argv, "prune-encoder")
    try:
        crops = crop_split(a.calibration, ("train",), a.calibration_n)[0]
        check, check_data = check_crops(a.check, a.model_dir, a.check_n)
        record = prune_folder_encoder(
            a.model_dir, crops, check, check_data, calibration_data=f"{a.calibration} ({len(crops)} crops)"
        )
    except (QuantizationError, ValueError, FileNotFoundError) as e:
        print(f"prune-encoder: {e}", file=sys.stderr)
        sys.exit(2)
    c = record["check"]
    logging.info(
        "int8 encoder pruned (kept / total per ReLU: %s); against the unpruned graph on %d crops: mean |dp| %.2e, "
        "max %.2e, %d decisions changed",
        record["kept"],
        c["n"],
        c["mean_abs_diff_probability"],
        c["max_abs_diff_probability"],
        c["decisions_changed"],
    )
    return record


if __name__ == "__main__":
    main()
