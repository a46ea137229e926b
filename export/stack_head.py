"""Append a placement stacker (``training.stacker``) to a model folder's head graphs.

The head graph's last step is ``sigmoid(logit)``; the stacked graph reads (k, 7 + 7) pose rows
(the pose columns, then the placement row, ``vgq.placement``), hands the first 7 to the head as
before and computes ``sigmoid(logit + known * mlp(logit, placement))`` with the stacker's
standardisation folded into its first layer. Every other graph and file of the folder is copied
as it is; the card gains ``placement_columns`` (so the service analyses each upload and appends
the rows), a new ``model_version`` and, under ``export.stacker``, what the stacker was fitted and
judged on. What was measured or fitted on the unstacked scores (the card's test results, the
planner's calibration and ranker) is set aside, not passed off as the stacked model's.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

from planning import calibration as planner_calibration
from planning import ranker as planner_ranker
from training.stacker import Stacker
from vgq import atomic
from vgq.model_card import CARD_NAME, HEAD_INPUTS, HEAD_OUTPUT, ModelCard
from vgq.placement import PLACEMENT_COLUMNS

#: the card's head graphs, each stacked alike
HEAD_ROLES = ("head", "head_int8")
#: the card's metrics measured through the head graphs: once stacked they are the unstacked model's, kept
#: under ``metrics.before_stacker`` (``training.stacker.measure`` measures the stacked graphs' again)
GRAPH_METRICS = ("test", "test_clean", "test_more_objects")
#: files fitted on the unstacked scores that no longer fit: not copied (``planning.calibration`` and
#: ``planning.ranker`` fit them again on a pool of the stacked model's candidates)
UNSTACKED_FILES = (planner_calibration.FILE, planner_ranker.FILE)


def stack_graph(model: onnx.ModelProto, stacker: Stacker, n_pose: int) -> onnx.ModelProto:
    """``model`` (a head graph: inputs image_term, poses (k, n_pose); output p_success (k,) from one
    Sigmoid) with the stacker between its logit and its Sigmoid, reading poses (k, n_pose + 7)."""
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    sig = [n for n in g.node if n.op_type == "Sigmoid"]
    if len(sig) != 1:
        raise ValueError(f"a head graph has one Sigmoid (its probability); this one has {len(sig)}")
    if [i.name for i in g.input] != list(HEAD_INPUTS) or [o.name for o in g.output] != [HEAD_OUTPUT]:
        raise ValueError(f"not a head graph: inputs {[i.name for i in g.input]}, outputs {[o.name for o in g.output]}")
    pose_in = "stacker/pose_columns"
    for n in g.node:  # the head reads the pose columns, sliced from the wider input
        n.input[:] = [pose_in if x == HEAD_INPUTS[1] else x for x in n.input]
    g.input[1].type.tensor_type.shape.dim[1].dim_value = n_pose + len(PLACEMENT_COLUMNS)
    (w1, b1), *rest = stacker.layers
    w1f = (w1 / stacker.std[None, :]).astype(np.float32)  # standardisation folded into the first layer
    b1f = (b1 - w1f @ stacker.mean).astype(np.float32)
    inits = {
        "stacker/pose_lo": np.array([0], np.int64),
        "stacker/pose_hi": np.array([n_pose], np.int64),
        "stacker/place_hi": np.array([n_pose + len(PLACEMENT_COLUMNS)], np.int64),
        "stacker/known_hi": np.array([n_pose + 1], np.int64),
        "stacker/axis": np.array([1], np.int64),
        "stacker/w0": w1f,
        "stacker/b0": b1f,
    }
    for i, (w, b) in enumerate(rest, start=1):
        inits[f"stacker/w{i}"], inits[f"stacker/b{i}"] = w.astype(np.float32), b.astype(np.float32)
    g.initializer.extend(numpy_helper.from_array(v, k) for k, v in inits.items())
    ax = "stacker/axis"
    head_nodes = [
        helper.make_node("Slice", [HEAD_INPUTS[1], "stacker/pose_lo", "stacker/pose_hi", ax], [pose_in]),
    ]
    lg = sig[0].input[0]  # the head's logit (k, 1)
    tail = [
        helper.make_node("Slice", [HEAD_INPUTS[1], "stacker/pose_hi", "stacker/known_hi", ax], ["stacker/known"]),
        helper.make_node("Slice", [HEAD_INPUTS[1], "stacker/known_hi", "stacker/place_hi", ax], ["stacker/place"]),
        helper.make_node("Concat", [lg, "stacker/place"], ["stacker/x"], axis=1),
    ]
    x = "stacker/x"
    for i in range(len(stacker.layers)):
        tail.append(helper.make_node("Gemm", [x, f"stacker/w{i}", f"stacker/b{i}"], [f"stacker/h{i}"], transB=1))
        x = f"stacker/h{i}"
        if i < len(stacker.layers) - 1:
            tail.append(helper.make_node("Relu", [x], [f"stacker/r{i}"]))
            x = f"stacker/r{i}"
    tail += [
        helper.make_node("Mul", ["stacker/known", x], ["stacker/delta"]),
        helper.make_node("Add", [lg, "stacker/delta"], ["stacker/logit"]),
    ]
    nodes = list(g.node)
    at = nodes.index(sig[0])
    sig[0].input[0] = "stacker/logit"
    del g.node[:]
    g.node.extend(head_nodes + nodes[:at] + tail + nodes[at:])
    onnx.checker.check_model(m)
    return m


def write_stacked(
    model_dir: str | Path, stacker: Stacker, out: str | Path, record: dict, calibration: dict | None = None
) -> Path:
    """A copy of ``model_dir`` in ``out`` (written beside it, then moved into place) with every head
    graph stacked and the card updated; ``record`` (what the stacker was fitted and judged on) is
    kept in the card's ``export.stacker``; ``calibration`` (``export.calibrate``'s record, refitted
    on the stacked scores) replaces the card's, which would no longer fit (None: dropped); the card's
    ``GRAPH_METRICS`` move under ``metrics.before_stacker`` and the planner's ``UNSTACKED_FILES`` are
    left out. ValueError for a folder whose head already reads placement rows, or an ``out`` that exists and
    is not a model folder (it would be replaced)."""
    model_dir, out = Path(model_dir), Path(out)
    card = ModelCard.load(model_dir)
    if card.placement_columns:
        raise ValueError(f"{model_dir}: its head already reads placement rows")
    if out.exists() and not (out / CARD_NAME).is_file():  # only a model folder is replaced
        raise ValueError(f"--out {out} exists and is not a model folder: choose a new folder")
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(model_dir, tmp)
    for name in UNSTACKED_FILES:
        (tmp / name).unlink(missing_ok=True)
    n_pose = len(card.normalization.pose_columns)
    for role in HEAD_ROLES:
        if role in card.files:
            g = stack_graph(onnx.load(str(model_dir / card.files[role])), stacker, n_pose)
            atomic.write_bytes(tmp / card.files[role], g.SerializeToString())
    blob = json.dumps(stacker.to_dict(), sort_keys=True).encode()
    card.placement_columns = PLACEMENT_COLUMNS
    card.model_version = f"{card.model_version}-stk{hashlib.sha256(blob).hexdigest()[:8]}"
    card.export = {**card.export, "stacker": {**record, "weights": stacker.to_dict()}}
    card.calibration = dict(calibration or {})
    before = {k: card.metrics.pop(k) for k in GRAPH_METRICS if k in card.metrics}
    if before:
        card.metrics["before_stacker"] = before
    card.save(tmp)
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return out
