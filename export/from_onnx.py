"""Read an exported Fast-VGQ-CNN model folder back into torch ``GraspQualityNet`` modules.

Used by the benchmark (a VGQ-CNN with the same image weights as the served model) and to
re-export a model folder with the current ``export.graphs`` (e.g. a faster LRN form).
The graphs hold the pose normalisation folded into pc1 and fc6 as one logit difference;
both are undone exactly: pc1 gets back ``W = W' std``, ``b = b' + W' mean`` with the
model card's statistics, and fc6 becomes ``[[0], [w]]`` (softmax(...)[1] = sigmoid(w x + b)).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from training.checkpoint import net_options
from training.networks import GraspQualityNet
from vgq.model_card import ModelCard

from .graphs import roi_fc1_point_major_columns


def _load(path: Path) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """Initializers by name, and node name -> input names, of an ONNX graph."""
    m = onnx.load(str(path))
    init = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    return init, {n.name: list(n.input) for n in m.graph.node}


def _get(init: dict, name: str, path: Path) -> np.ndarray:
    if name not in init:
        raise ValueError(f"{path}: weight {name!r} not found; not a graph written by export.graphs")
    return init[name]


def _set(param: torch.Tensor, a: np.ndarray, what: str) -> None:
    if tuple(param.shape) != tuple(a.shape):
        raise ValueError(f"{what}: ONNX weight has shape {a.shape}, the network expects {tuple(param.shape)}")
    with torch.no_grad():
        param.copy_(torch.from_numpy(np.array(a, dtype=np.float32)))


def _unfold(net: GraspQualityNet, layer: torch.nn.Linear, head: dict, head_path: Path, name: str, place: bool) -> None:
    """Set ``layer`` from the graph's folded ``head.<name>``: W = W' std, b = b' + W' mean on the pose
    columns (the card's statistics, already on ``net``), and with ``place`` W = W' scale on the row's."""
    wf = _get(head, f"head.{name}.weight", head_path).astype(np.float64)
    bf = _get(head, f"head.{name}.bias", head_path).astype(np.float64)
    n = net.n_other
    mean, std = net.pose_mean.numpy().astype(np.float64)[:n], net.pose_std.numpy().astype(np.float64)[:n]
    w = wf.copy()
    w[:, :n] = wf[:, :n] * std[None, :]
    if place:
        w[:, -net.n_place :] = wf[:, -net.n_place :] * net.place_scale.numpy().astype(np.float64)[None, :]
    _set(layer.weight, w, name)
    _set(layer.bias, bf + wf[:, :n] @ mean, name)


def fast_net_from_model_dir(model_dir: str | Path) -> tuple[GraspQualityNet, ModelCard]:
    """The Fast-VGQ-CNN of an exported folder (encoder.onnx + head.onnx + model card), in eval mode.
    Weights are found by their torch names (``net.conv1_1.weight``, ``head.fc5.bias``, ...). A
    stacked folder (``export.stack_head``) gives the network under its stacker, the stacker left out
    (so ``training train --init`` fine-tunes the network, as from the folder it was stacked on)."""
    model_dir = Path(model_dir)
    card = ModelCard.load(model_dir)
    if card.architecture != "fast_vgqcnn":
        raise ValueError(f"{model_dir}: architecture {card.architecture!r}, expected fast_vgqcnn")
    enc_path, head_path = model_dir / card.files["encoder"], model_dir / card.files["head"]
    (enc, enc_nodes), (head, head_nodes) = _load(enc_path), _load(head_path)
    channels = int(_get(enc, "net.conv2_1.weight", enc_path).shape[0])  # the paper's 64, or wider
    options = net_options({"config": card.training.get("config", {})})
    # the card says what the head reads; a stacked folder's placement rows are its stacker's (export.stack_head)
    options["placement"] = bool(card.placement_columns) and "stacker" not in card.export
    net = GraspQualityNet("fast_vgqcnn", image_size=card.geometry.out, conv2_channels=channels, **options).eval()
    norm = card.normalization
    net.set_normalization(norm)
    for layer in ("conv1_1", "conv1_2", "conv2_1", "conv2_2", "fc3"):
        for what in ("weight", "bias"):
            _set(getattr(getattr(net, layer), what), _get(enc, f"net.{layer}.{what}", enc_path), layer)
    mm = enc_nodes.get("/fc4_image/MatMul")
    if mm is None or len(mm) != 2:
        raise ValueError(f"{enc_path}: node '/fc4_image/MatMul' not found; not a graph written by export.graphs")
    _set(net.fc4_image.weight, _get(enc, mm[1], enc_path).T, "fc4_image")  # MatMul holds W^T
    if net.fc4_ref is not None:
        ref = enc_nodes.get("/fc4_ref/MatMul")
        if ref is None or len(ref) != 2:
            raise ValueError(f"{enc_path}: node '/fc4_ref/MatMul' not found; the card says depth_reference centre")
        _set(net.fc4_ref.weight, _get(enc, ref[1], enc_path).T, "fc4_ref")
    # pc1 with the pose normalisation folded into its first n_other columns: W' = W / std, b' = b - W' mean
    _unfold(net, net.pc1, head, head_path, "pc1", place=bool(net.n_place) and not net.placement_units)
    if net.placement_units:  # the placement stream: place_fc1 folded as pc1, place_fc2 (no bias) a MatMul
        _unfold(net, net.place_fc1, head, head_path, "place_fc1", place=True)
        mm = head_nodes.get("/head/place_fc2/MatMul")
        if mm is not None and len(mm) == 2:
            _set(net.place_fc2.weight, _get(head, mm[1], head_path).T, "place_fc2")
        elif net.roi_head == "none":
            raise ValueError(f"{head_path}: node '/head/place_fc2/MatMul' not found; the card says placement_units")
    for layer in ("fc4_pose", "fc5"):
        for what in ("weight", "bias"):
            _set(getattr(getattr(net, layer), what), _get(head, f"head.{layer}.{what}", head_path), layer)
    if net.roi_head != "none":  # the jaw-grid head: roi_fc1 by name, roi_fc2 (no bias) as its MatMul's W^T
        if "head.roi_fc1.weight" in head:  # read point-major (export.graphs): back to channel-major
            w = _get(head, "head.roi_fc1.weight", head_path)
            order = roi_fc1_point_major_columns(net)
            if w.shape[1] != len(order):
                raise ValueError(f"roi_fc1: ONNX weight has {w.shape[1]} inputs, the network expects {len(order)}")
            channel_major = np.empty_like(w)
            channel_major[:, order] = w
            _set(net.roi_fc1.weight, channel_major, "roi_fc1")
            _set(net.roi_fc1.bias, _get(head, "head.roi_fc1.bias", head_path), "roi_fc1")
        else:  # a graph exported before 2026-12-08: the network's channel-major order
            _set(net.roi_fc1.weight, _get(head, "head.roi.roi_fc1.weight", head_path), "roi_fc1")
            _set(net.roi_fc1.bias, _get(head, "head.roi.roi_fc1.bias", head_path), "roi_fc1")
        _set(net.roi_focal_px, _get(head, "head.roi.roi_focal_px", head_path), "roi_focal_px")
        mm = head_nodes.get("/head/roi_fc2/MatMul")
        if mm is None or len(mm) != 2:
            raise ValueError(f"{head_path}: node '/head/roi_fc2/MatMul' not found; the card says roi_head jaw")
        w = _get(head, mm[1], head_path).T
        roi_units = net.roi_fc2.weight.shape[1]
        if net.placement_units and "/head/place_fc2/MatMul" not in head_nodes:  # place_fc2's columns follow
            _set(net.place_fc2.weight, w[:, roi_units:], "place_fc2")
            w = w[:, :roi_units]
        _set(net.roi_fc2.weight, w, "roi_fc2")
    w, b = _get(head, "head.out.weight", head_path), _get(head, "head.out.bias", head_path)
    _set(net.fc6.weight, np.concatenate([np.zeros_like(w), w]), "fc6")
    _set(net.fc6.bias, np.concatenate([np.zeros_like(b), b]), "fc6")
    return net, card


def init_checkpoint_from_model_dir(model_dir: str | Path) -> dict:
    """An exported Fast-VGQ-CNN folder as the parts of a checkpoint a fine-tune reads (``training
    train --init``): arch, the training config's network options, weights, normalisation, crop
    geometry. The weights are the graphs' (fc6 as ``[[0], [w]]``: the same probabilities)."""
    net, card = fast_net_from_model_dir(model_dir)
    return {
        "arch": card.architecture,
        "config": dict(card.training.get("config", {}), conv2_channels=net.conv2_channels),
        "model": net.state_dict(),
        "normalization": card.normalization.to_dict(),
        "geometry": card.geometry.to_dict(),
    }


def vgq_net_like(fast: GraspQualityNet) -> GraspQualityNet:
    """A VGQ-CNN (pose z, q; one centred crop per grasp) with ``fast``'s image stream, fc4,
    fc5 and fc6, and pc1 restricted to the (z, q) columns (a jaw-grid head left out). Same cost as the paper's VGQ-CNN;
    its scores are not a trained VGQ-CNN's."""
    net = GraspQualityNet(
        "vgqcnn",
        image_size=fast.image_size,
        conv2_channels=fast.conv2_channels,
        depth_reference=fast.depth_reference,
        pose_features=fast.pose_features,
        pose_units=fast.pose_units,
    ).eval()
    cols = [fast.pose_columns.index(c) for c in net.pose_columns]
    feature_cols = cols  # pc1's inputs: the pose columns, or the non-quaternion ones + 9 rotation entries
    if fast.pose_features == "rotation":
        feature_cols = cols[: net.n_other] + list(range(fast.n_other, fast.n_other + 9))
    src = fast.state_dict()
    dst = net.state_dict()
    for k, v in src.items():
        if k not in dst:  # a jaw-grid head's layers: VGQ-CNN's crop is centred, its head the paper's
            continue
        if k.startswith("pc1.weight"):
            dst[k] = v[:, feature_cols].clone()
        elif k in ("pose_mean", "pose_std"):
            dst[k] = v[cols].clone()
        else:
            dst[k] = v.clone()
    net.load_state_dict(dst)
    return net
