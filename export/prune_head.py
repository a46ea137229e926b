"""Drop the head's dead ReLU units before it is quantised: the served int8 head does less work.

Fast-VGQ-CNN's head is pc1 (7 -> 16) -> fc4 (image term + pose, 1024) -> fc5 (1024 x 1024) ->
out (1). fc5 is nearly all of its work, and many of its ReLU units never fire: in the bundled
v2 model 42% of fc5's units and 5% of fc4's stay at zero on every calibration crop, trained into
that state ("dead" units get no gradient). A unit that is zero contributes nothing downstream,
so removing it (its row of fc5 and its weight in ``out``; for fc4 its image-term column, its
pose-layer row and its column of fc5) leaves every probability unchanged wherever it stays dead.

Which units are dead is measured, not proved: the maximum pre-activation of every unit over
calibration crops (a crop dataset's train split, objects the check does not see), over their
own (crop, pose) pairs and over pairs of one crop's image term with another crop's pose (the
service scores many grasps against one window). fc4's maximum over *every* such pairing is exact
(its pre-activation is image term + pose part); fc5's is sampled (``cross_pairs``). The pruned
graph is then checked against the unpruned one on other objects' crops, own and crossed pairs:
it is refused (``PruningError``) when a probability moves by more than ``max_abs_diff`` or more
than ``max_flip_fraction`` of the decisions change. The int8 head is quantised from the pruned
graph and checked against the exact fp32 head as before (export.quantize). ``head.onnx``, the
fp32 reference, is never pruned.

A head that adds other terms to fc4 (the jaw grid's reads of the window's feature map, a placement
stream) has no closed-form maximum: its fc5 units are measured by running the head graph itself on
the same own and crossed pairs (:func:`measured_dead_units`), and only fc5's dead units go
(:func:`prune_fc5_graph`; fc4 is kept whole), checked the same way.

    python -m export.prune_head --model-dir models/fast-vgqcnn-default \\
        --calibration data/calib/crops --check examples/heldout_test_crops.npz

rebuilds a model folder's ``head_int8.onnx`` this way (atomic; the card's ``export.int8_head``
records both checks and the units kept). ``python -m export --int8-head`` does the same at
export time (``--no-prune`` keeps every unit).
"""

from __future__ import annotations

import hashlib
import logging
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

from vgq import atomic
from vgq.model_card import HEAD_INPUTS, HEAD_OUTPUT, ModelCard
from vgq.pose import POSE_COLUMNS, pose_stream_features

from .quantize import QuantizationError, check_int8_head, image_terms, quantize_head, session

#: initialiser names of the head graph as export.onnx_export writes it (export.graphs.HeadGraph)
WEIGHTS = {
    "pc1_w": "head.pc1.weight",
    "pc1_b": "head.pc1.bias",
    "fc4_w": "head.fc4_pose.weight",
    "fc4_b": "head.fc4_pose.bias",
    "fc5_w": "head.fc5.weight",
    "fc5_b": "head.fc5.bias",
    "out_w": "head.out.weight",
}
MAX_ABS_DIFF = 0.02
MAX_FLIP_FRACTION = 0.001
CROSS_PAIRS = 200_000
INT8_HEAD_FILE = "head_int8.onnx"


class PruningError(QuantizationError):
    """The pruned head does not score like the unpruned one (or the graph is not a head)."""


@dataclass(frozen=True)
class HeadWeights:
    """The head's fc weights (torch layout: (out, in)), float64."""

    pc1_w: np.ndarray
    pc1_b: np.ndarray
    fc4_w: np.ndarray
    fc4_b: np.ndarray
    fc5_w: np.ndarray
    fc5_b: np.ndarray
    out_w: np.ndarray

    @classmethod
    def from_onnx(cls, path: str | Path) -> HeadWeights:
        inits = {t.name: t for t in onnx.load(str(path)).graph.initializer}
        missing = [n for n in WEIGHTS.values() if n not in inits]
        if missing:
            raise PruningError(f"{path}: not a Fast-VGQ-CNN head graph (no {', '.join(missing)})")
        return cls(**{k: numpy_helper.to_array(inits[n]).astype(np.float64) for k, n in WEIGHTS.items()})

    def pose_part(self, poses: np.ndarray) -> np.ndarray:
        """(k, 7) pose rows -> (k, 1024): fc4's pose contribution plus its bias. A pc1 of 3 + 9
        inputs reads the rotation-matrix features (``vgq.pose.pose_stream_features``)."""
        poses = np.asarray(poses, np.float64)
        if self.pc1_w.shape[1] == poses.shape[1] - 4 + 9:
            poses = pose_stream_features(poses, POSE_COLUMNS["fast_vgqcnn"], "rotation")
        pc1 = np.maximum(poses @ self.pc1_w.T + self.pc1_b, 0)
        return pc1 @ self.fc4_w.T + self.fc4_b

    def fc5_pre(self, terms: np.ndarray, pose_part: np.ndarray) -> np.ndarray:
        """fc5's pre-activations (n, 1024) of n (image term, pose part) pairs, row by row."""
        return np.maximum(np.asarray(terms, np.float64) + pose_part, 0) @ self.fc5_w.T + self.fc5_b


@dataclass(frozen=True)
class DeadUnits:
    """Units kept (indices into 1024) and the calibration they were measured on."""

    fc4_kept: np.ndarray
    fc5_kept: np.ndarray
    n_units: int  # of fc4 and of fc5 before pruning
    n_calibration: int
    n_cross_pairs: int

    def summary(self) -> dict:
        return {
            "units": self.n_units,
            "fc4_units_kept": int(len(self.fc4_kept)),
            "fc5_units_kept": int(len(self.fc5_kept)),
            "n_calibration": self.n_calibration,
            "n_cross_pairs": self.n_cross_pairs,
        }


def dead_units(
    w: HeadWeights, terms: np.ndarray, poses: np.ndarray, cross_pairs: int = CROSS_PAIRS, seed: int = 0
) -> DeadUnits:
    """The units of fc4 and fc5 that fire (pre-activation > 0) for some calibration pair: the
    (n, 1024) image terms with their own (n, 7) pose rows, and for fc5 also ``cross_pairs``
    random (term i, pose j) pairs. fc4's maximum over all n x n pairs is exact: max(term) + max(pose
    part). A unit that fires nowhere is dead; the kept units are returned (sorted)."""
    terms = np.asarray(terms, np.float64)
    if terms.ndim != 2 or len(terms) != len(poses) or len(terms) == 0:
        raise PruningError(f"calibration needs n image terms and n pose rows, got {terms.shape} and {np.shape(poses)}")
    part = w.pose_part(poses)
    fc4_max = terms.max(0) + part.max(0)
    fc5_max = np.full(len(w.fc5_b), -np.inf)
    rng = np.random.default_rng(seed)
    n, chunk = len(terms), 4096
    for start in range(0, n + cross_pairs, chunk):
        if start < n:  # own pairs first
            i = np.arange(start, min(start + chunk, n))
            j = i
        else:
            m = min(chunk, n + cross_pairs - start)
            i, j = rng.integers(0, n, m), rng.integers(0, n, m)
        fc5_max = np.maximum(fc5_max, w.fc5_pre(terms[i], part[j]).max(0))
    return DeadUnits(np.flatnonzero(fc4_max > 0), np.flatnonzero(fc5_max > 0), len(fc5_max), n, int(cross_pairs))


def prune_head_graph(head_path: str | Path, out_path: str | Path, units: DeadUnits) -> None:
    """Write ``out_path``: the head graph with only ``units`` kept. Same inputs and output; the
    image term's kept columns are gathered before fc4's bias is added."""
    g = onnx.load(str(head_path))
    w = {t.name: numpy_helper.to_array(t) for t in g.graph.initializer}
    k4, k5 = units.fc4_kept, units.fc5_kept
    new = {
        WEIGHTS["fc4_w"]: w[WEIGHTS["fc4_w"]][k4],
        WEIGHTS["fc4_b"]: w[WEIGHTS["fc4_b"]][k4],
        WEIGHTS["fc5_w"]: w[WEIGHTS["fc5_w"]][k5][:, k4],
        WEIGHTS["fc5_b"]: w[WEIGHTS["fc5_b"]][k5],
        WEIGHTS["out_w"]: w[WEIGHTS["out_w"]][:, k5],
    }
    for t in g.graph.initializer:
        if t.name in new:
            t.CopyFrom(numpy_helper.from_array(np.ascontiguousarray(new[t.name], np.float32), t.name))
    users = [n for n in g.graph.node if HEAD_INPUTS[0] in n.input]
    if len(users) != 1 or users[0].op_type != "Add":
        raise PruningError(f"{head_path}: expected one Add on {HEAD_INPUTS[0]}, found {[n.op_type for n in users]}")
    kept_name, term_kept = "head.prune.fc4_kept", "/head/prune/term_kept"
    g.graph.initializer.append(numpy_helper.from_array(k4.astype(np.int64), kept_name))
    add = users[0]
    add.input[list(add.input).index(HEAD_INPUTS[0])] = term_kept
    gather = helper.make_node("Gather", [HEAD_INPUTS[0], kept_name], [term_kept], axis=1, name="/head/prune/Gather")
    g.graph.node.insert(list(g.graph.node).index(add), gather)
    del g.graph.value_info[:]  # intermediate shapes, if any were recorded: stale after pruning
    onnx.checker.check_model(g)
    onnx.save(g, str(out_path))


def is_plain_head(head_path: str | Path) -> bool:
    """True for the paper's head graph (what :func:`dead_units` and :func:`prune_head_graph` work
    on): its only reader of the image term is fc4's Add and its only matrix products are pc1, fc4,
    fc5 and out. False for a head that adds other terms to fc4 (a jaw grid, a placement stream: each
    brings products of its own), pruned by :func:`measured_dead_units` instead, which holds for any
    head."""
    nodes = onnx.load(str(head_path)).graph.node
    users = [n for n in nodes if HEAD_INPUTS[0] in n.input]
    products = [n for n in nodes if n.op_type in ("Gemm", "MatMul")]
    return len(users) == 1 and users[0].op_type == "Add" and len(products) == 4


def _fc5_wiring(g: onnx.GraphProto) -> tuple[onnx.NodeProto, str, str]:
    """(fc5's Gemm, the tensor it reads: fc4's ReLU output, fc5's own ReLU output) of a head graph;
    PruningError when the graph has no fc4 ReLU -> fc5 Gemm -> ReLU -> out Gemm chain."""
    fc5 = [n for n in g.node if n.op_type == "Gemm" and len(n.input) > 1 and n.input[1] == WEIGHTS["fc5_w"]]
    relu5 = [n for n in g.node if fc5 and n.op_type == "Relu" and n.input[0] == fc5[0].output[0]]
    out = [n for n in g.node if n.op_type == "Gemm" and len(n.input) > 1 and n.input[1] == WEIGHTS["out_w"]]
    producer = {o: n for n in g.node for o in n.output}
    trans_b = {a.name: a.i for a in fc5[0].attribute} if fc5 else {}
    if (
        len(fc5) != 1
        or len(relu5) != 1
        or len(out) != 1
        or out[0].input[0] != relu5[0].output[0]
        or getattr(producer.get(fc5[0].input[0]), "op_type", None) != "Relu"
        or trans_b.get("transB") != 1
    ):
        raise PruningError("not a Fast-VGQ-CNN head graph: no fc4 ReLU -> fc5 Gemm -> ReLU -> out Gemm chain")
    return fc5[0], fc5[0].input[0], relu5[0].output[0]


def measured_dead_units(
    head_path: str | Path,
    encoder_path: str | Path,
    crops: np.ndarray,
    poses: np.ndarray,
    cross_pairs: int = CROSS_PAIRS,
    seed: int = 0,
    chunk: int = 2048,
) -> DeadUnits:
    """The units of fc5 that fire for some calibration pair, measured by running the head graph
    itself with fc5's ReLU output exposed: any head, whatever terms it adds to fc4 (the jaw grid
    reads the window's feature map at each grasp, so no closed form bounds fc4 or fc5). Pairs: each
    of the (n, S, S) crops with its own pose row, and ``cross_pairs`` (term i, pose j) pairs drawn
    within chunks of ``chunk`` crops (encoded a chunk at a time: a jaw-grid encoding is 17x the
    paper's). Every fc4 unit is kept: dropping fc4's few dead units from fc5's input needs a Gather
    over its (k, 1024) output, which onnxruntime runs slower (1.0 ms for 128 grasps on a Zen 3) than
    the columns it saves."""
    crops, poses = np.asarray(crops, np.float32), np.ascontiguousarray(poses, np.float32)
    if len(crops) == 0 or len(crops) != len(poses):
        raise PruningError(f"calibration needs n crops and n pose rows, got {np.shape(crops)} and {np.shape(poses)}")
    g = onnx.load(str(head_path))
    _, _, fc5_out = _fc5_wiring(g.graph)
    g.graph.output.append(helper.make_tensor_value_info(fc5_out, onnx.TensorProto.FLOAT, None))
    with tempfile.TemporaryDirectory(prefix=".prune-") as tmp:
        onnx.save(g, str(Path(tmp) / "exposed.onnx"))
        head = session(Path(tmp) / "exposed.onnx")
    encoder, rng = session(encoder_path), np.random.default_rng(seed)
    top5 = None
    n = len(crops)
    for start in range(0, n, chunk):
        terms = image_terms(encoder, crops[start : start + chunk])
        m = len(terms)
        extra = int(round(cross_pairs * m / n))
        i = np.concatenate([np.arange(m), rng.integers(0, m, extra)])
        j = np.concatenate([np.arange(m), rng.integers(0, m, extra)])
        for b in range(0, len(i), 128):
            feed = {HEAD_INPUTS[0]: terms[i[b : b + 128]], HEAD_INPUTS[1]: poses[start + j[b : b + 128]]}
            batch_top = head.run([fc5_out], feed)[0].max(0)
            top5 = batch_top if top5 is None else np.maximum(top5, batch_top)
    return DeadUnits(np.arange(len(top5)), np.flatnonzero(top5 > 0), len(top5), n, int(cross_pairs))


def prune_fc5_graph(head_path: str | Path, out_path: str | Path, units: DeadUnits) -> None:
    """Write ``out_path``: the head graph with only fc5's kept units (its rows of fc5, their
    columns of ``out``). fc4 and the terms added to it are left whole (``units.fc4_kept`` must be
    all of them): fc5 is most of the head's work. Same inputs and output."""
    g = onnx.load(str(head_path))
    _fc5_wiring(g.graph)
    w = {t.name: numpy_helper.to_array(t) for t in g.graph.initializer}
    if len(units.fc4_kept) != w[WEIGHTS["fc5_w"]].shape[1]:
        raise PruningError("prune_fc5_graph keeps every fc4 unit; use prune_head_graph for the paper's head")
    k5 = units.fc5_kept
    new = {
        WEIGHTS["fc5_w"]: w[WEIGHTS["fc5_w"]][k5],
        WEIGHTS["fc5_b"]: w[WEIGHTS["fc5_b"]][k5],
        WEIGHTS["out_w"]: w[WEIGHTS["out_w"]][:, k5],
    }
    for t in g.graph.initializer:
        if t.name in new:
            t.CopyFrom(numpy_helper.from_array(np.ascontiguousarray(new[t.name], np.float32), t.name))
    del g.graph.value_info[:]  # intermediate shapes, if any were recorded: stale after pruning
    onnx.checker.check_model(g)
    onnx.save(g, str(out_path))


@dataclass(frozen=True)
class PruneCheck:
    """The pruned fp32 head against the unpruned one on check crops (own and crossed pairs)."""

    n_pairs: int
    max_abs_diff_probability: float
    mean_abs_diff_probability: float
    decisions_changed: int
    check_data: str
    units: dict

    def to_dict(self) -> dict:
        return asdict(self)


def check_pruned_head(
    head_path,
    pruned_path,
    terms: np.ndarray,
    poses: np.ndarray,
    units: DeadUnits,
    check_data: str = "",
    max_abs_diff: float | None = None,
    max_flip_fraction: float | None = None,
    seed: int = 1,
) -> PruneCheck:
    """Score the check crops' own (term, pose) pairs and as many crossed pairs (term i, pose of a
    random other crop) through both graphs, 128 grasps per call; raise PruningError when the
    pruned head is off (thresholds: MAX_ABS_DIFF, MAX_FLIP_FRACTION unless given)."""
    max_abs_diff = MAX_ABS_DIFF if max_abs_diff is None else max_abs_diff
    max_flip_fraction = MAX_FLIP_FRACTION if max_flip_fraction is None else max_flip_fraction
    full, pruned = session(head_path), session(pruned_path)
    terms, poses = np.ascontiguousarray(terms, np.float32), np.ascontiguousarray(poses, np.float32)
    cross = np.random.default_rng(seed).permutation(len(poses))
    diffs, flips = [], 0
    for p in (poses, poses[cross]):
        for i in range(0, len(p), 128):
            feed = {HEAD_INPUTS[0]: terms[i : i + 128], HEAD_INPUTS[1]: p[i : i + 128]}
            a, b = (s.run([HEAD_OUTPUT], feed)[0] for s in (full, pruned))
            diffs.append(np.abs(a - b))
            flips += int(((a > 0.5) != (b > 0.5)).sum())
    d = np.concatenate(diffs)
    check = PruneCheck(len(d), float(d.max()), float(d.mean()), flips, check_data, units.summary())
    if check.max_abs_diff_probability > max_abs_diff or flips > max_flip_fraction * len(d):
        raise PruningError(
            f"the pruned head scores unlike the unpruned one: {check.to_dict()} "
            f"(allowed: |dp| {max_abs_diff}, decisions changed {max_flip_fraction:.2%})"
        )
    return check


def build_int8_head(
    encoder_path,
    head_path,
    out_path,
    calibration: tuple[np.ndarray, np.ndarray],
    check: tuple[np.ndarray, np.ndarray, np.ndarray],
    check_data: str = "",
    cross_pairs: int = CROSS_PAIRS,
    prune: bool = True,
) -> dict:
    """Write the served int8 head to ``out_path``: ``head_path`` with its dead units removed
    (measured on ``calibration`` = (crops, poses), checked on ``check`` = labelled (crops, poses,
    labels)) and then fc5 quantised; the int8 graph is checked against the exact fp32 head on
    ``check``. Returns the card's ``export.int8_head`` record; raises QuantizationError (or
    PruningError) when a check fails."""
    record: dict = {}
    source = Path(head_path)
    with tempfile.TemporaryDirectory(prefix=".prune-", dir=Path(out_path).parent) as tmp:
        if prune:
            plain = is_plain_head(head_path)
            if plain:
                units = dead_units(
                    HeadWeights.from_onnx(head_path),
                    image_terms(encoder_path, calibration[0]),
                    calibration[1],
                    cross_pairs,
                )
            else:  # a jaw grid or a placement stream adds to fc4: measured through the graph
                units = measured_dead_units(head_path, encoder_path, *calibration, cross_pairs)
            logging.info(
                "dead units: fc4 keeps %d, fc5 keeps %d of %d (%d calibration crops)",
                len(units.fc4_kept),
                len(units.fc5_kept),
                units.n_units,
                units.n_calibration,
            )
            source = Path(tmp) / "head_pruned.onnx"
            (prune_head_graph if plain else prune_fc5_graph)(head_path, source, units)
            record["pruning"] = check_pruned_head(
                head_path, source, image_terms(encoder_path, check[0]), check[1], units, check_data
            ).to_dict()
        nodes = quantize_head(source, out_path)
        result = check_int8_head(encoder_path, head_path, out_path, *check, quantized_nodes=nodes)
    return {**result.to_dict(), **record}


def rebuild_int8_head(
    model_dir: str | Path,
    calibration: tuple[np.ndarray, np.ndarray],
    check: tuple[np.ndarray, np.ndarray, np.ndarray],
    check_data: str = "",
    calibration_data: str = "",
    cross_pairs: int = CROSS_PAIRS,
) -> dict:
    """Replace a Fast-VGQ-CNN folder's int8 head by a pruned one (:func:`build_int8_head`); the
    file and the card are only written once both checks pass (each write atomic)."""
    model_dir = Path(model_dir)
    card = ModelCard.load(model_dir)
    if card.architecture != "fast_vgqcnn":
        raise PruningError(f"{model_dir}: a pruned head exists for fast_vgqcnn only, not {card.architecture}")
    with atomic.staged(model_dir / INT8_HEAD_FILE) as tmp:
        record = build_int8_head(
            model_dir / card.files["encoder"],
            model_dir / card.files["head"],
            tmp,
            calibration,
            check,
            check_data,
            cross_pairs,
        )
        record["pruning"]["calibration_data"] = calibration_data
        record["sha256"] = hashlib.sha256(tmp.read_bytes()).hexdigest()
    card.files["head_int8"] = INT8_HEAD_FILE
    card.export["int8_head"] = record
    card.save(model_dir)
    return record


def main(argv=None) -> dict:
    from .int8_encoder import check_crops, crop_split, parse_variant_args, variant_parser

    p = variant_parser(
        "python -m export.prune_head",
        __doc__,
        "exported Fast-VGQ-CNN model folder (its int8 head is replaced)",
        "finds the dead units",
        50000,
    )
    p.add_argument(
        "--cross-pairs", type=int, default=CROSS_PAIRS, help=f"crossed (term, pose) pairs (default {CROSS_PAIRS})"
    )
    a = parse_variant_args(p, argv, "prune-head")
    if a.cross_pairs < 0:
        p.error("--cross-pairs must be >= 0")
    try:
        place = bool(ModelCard.load(a.model_dir).placement_columns)
        crops, poses, _ = crop_split(a.calibration, ("train",), a.calibration_n, placement=place)
        check, check_data = check_crops(a.check, a.model_dir, a.check_n)
        record = rebuild_int8_head(
            a.model_dir,
            (crops, poses),
            check,
            check_data=check_data,
            calibration_data=f"{a.calibration} ({len(crops)} crops)",
            cross_pairs=a.cross_pairs,
        )
    except (QuantizationError, ValueError, FileNotFoundError) as e:
        print(f"prune-head: {e}", file=sys.stderr)
        sys.exit(2)
    pr = record["pruning"]
    logging.info(
        "int8 head rebuilt: fc4 keeps %d, fc5 keeps %d of %d units; pruned vs unpruned on %d pairs: max |dp| %.2e, "
        "%d decisions changed; int8 vs fp32: balanced accuracy %.4f (fp32 %.4f), max |dp| %.4f, %d of %d decisions changed",
        pr["units"]["fc4_units_kept"],
        pr["units"]["fc5_units_kept"],
        pr["units"]["units"],
        pr["n_pairs"],
        pr["max_abs_diff_probability"],
        pr["decisions_changed"],
        record["balanced_accuracy_int8"],
        record["balanced_accuracy_fp32"],
        record["max_abs_diff_probability"],
        record["decisions_changed"],
        record["n"],
    )
    return record


if __name__ == "__main__":
    main()
