"""Export a trained ``GraspQualityNet`` to a model folder of ONNX graphs + a model card.

Nothing is written unless onnxruntime reproduces torch on the given real inputs:
success probabilities within ``tolerance`` (absolute) and the encoder's image term within
``tolerance`` relative to its magnitude. The folder is swapped in atomically.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from service.runtime import session_options
from training.networks import GraspQualityNet
from vgq.camera import Intrinsics
from vgq.crop import CropGeometry
from vgq.model_card import (
    ENCODER_INPUT,
    ENCODER_OUTPUT,
    HEAD_INPUTS,
    HEAD_OUTPUT,
    VGQ_INPUTS,
    VGQ_OUTPUT,
    ModelCard,
)
from vgq.placement import PLACEMENT_COLUMNS

from .calibrate import DIAGRAM, CalibrationReport, plot_reliability
from .graphs import EncoderGraph, HeadGraph, OnePieceGraph
from .prune_head import build_int8_head
from .quantize import QuantizationError

log = logging.getLogger(__name__)
OPSET = 17
DEFAULT_TOLERANCE = 1e-4


class ExportError(RuntimeError):
    """The exported graphs do not reproduce torch, or the inputs are unusable."""


@dataclass
class Verification:
    max_abs_diff_probability: float
    max_rel_diff_image_term: float | None
    n_inputs: int

    def to_dict(self) -> dict:
        return {
            "max_abs_diff_probability": self.max_abs_diff_probability,
            "max_rel_diff_image_term": self.max_rel_diff_image_term,
            "n_inputs": self.n_inputs,
        }


def _session(path: Path) -> ort.InferenceSession:
    """A session with the service's options (``service.runtime.session_options``): the graphs
    are checked as they will be run."""
    return ort.InferenceSession(str(path), session_options(1), providers=["CPUExecutionProvider"])


def _export(module: torch.nn.Module, args: tuple, path: Path, inputs, outputs, dynamic_axes) -> None:
    # The TorchScript exporter (dynamo=False) on purpose, its two deprecation warnings silenced
    # here and only here. Tried with torch 2.13 + onnxscript 0.7.2 (not a dependency): the
    # dynamo exporter keeps the band-Conv + Sqrt LRN and the weight names, but (1) the head
    # graph no longer broadcasts one image term against k poses (torch.export ties the two
    # batch dims; onnxruntime fails "Shape mismatch ... {1,1024} != {16,1024}"), (2) it renames
    # nodes ("node_linear_1", not "/head/fc5/Gemm" / "/fc4_image/MatMul" that export.from_onnx
    # and the int8 check rely on), (3) it raises FutureWarnings of its own. The outputs are
    # verified against torch below whichever exporter writes them.
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message="You are using the legacy TorchScript-based ONNX export", category=DeprecationWarning
        )
        warnings.filterwarnings(
            "ignore",
            message="The feature will be removed. Please remove usage of this function",
            category=DeprecationWarning,
            module=r"torch\.onnx\._internal\.torchscript_exporter",
        )
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=list(inputs),
            output_names=list(outputs),
            dynamic_axes=dynamic_axes,
            opset_version=OPSET,
            do_constant_folding=True,
            dynamo=False,
        )


def _sha(paths) -> str:
    h = hashlib.sha256()
    for p in sorted(paths):
        h.update(Path(p).read_bytes())
    return h.hexdigest()


def _check_inputs(net: GraspQualityNet, crops: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    crops = np.asarray(crops, dtype=np.float32)
    poses = np.asarray(poses, dtype=np.float32)
    s = net.image_size
    if crops.ndim == 3:
        crops = crops[:, None]
    if crops.ndim != 4 or crops.shape[1:] != (1, s, s) or len(crops) == 0:
        raise ExportError(f"verification crops must be (n, {s}, {s}) with n >= 1, got {crops.shape}")
    width = len(net.pose_columns) + net.n_place  # a placement head: its placement row after the pose columns
    if poses.shape != (len(crops), width):
        raise ExportError(f"verification poses must be ({len(crops)}, {width}), got {poses.shape}")
    if not (np.all(np.isfinite(crops)) and np.all(np.isfinite(poses))):
        raise ExportError("verification inputs contain non-finite values")
    return crops, poses


def _verify_fast(net, enc_path, head_path, crops, poses) -> Verification:
    enc, head = _session(enc_path), _session(head_path)
    with torch.no_grad():
        ref_terms = net.encode(torch.from_numpy(crops)).numpy()
        ref_p = net.head(torch.from_numpy(ref_terms), torch.from_numpy(poses)).numpy()
    terms = enc.run([ENCODER_OUTPUT], {ENCODER_INPUT: crops})[0]
    rel = float(np.abs(terms - ref_terms).max() / max(1.0, float(np.abs(ref_terms).max())))
    # head on one image term at a time, all poses against it (the serving pattern)
    p = np.concatenate(
        [
            head.run([HEAD_OUTPUT], {HEAD_INPUTS[0]: terms[i : i + 1], HEAD_INPUTS[1]: poses[i : i + 1]})[0]
            for i in range(len(crops))
        ]
    )
    k_all = head.run([HEAD_OUTPUT], {HEAD_INPUTS[0]: terms[:1], HEAD_INPUTS[1]: poses})[0]
    with torch.no_grad():
        ref_k_all = net.head(torch.from_numpy(ref_terms[:1]), torch.from_numpy(poses)).numpy()
    diff = max(float(np.abs(p - ref_p).max()), float(np.abs(k_all - ref_k_all).max()))
    return Verification(diff, rel, len(crops))


def _verify_one_piece(net, path, crops, poses) -> Verification:
    sess = _session(path)
    with torch.no_grad():
        ref = torch.softmax(net(torch.from_numpy(crops), torch.from_numpy(poses)), 1)[:, 1].numpy()
    got = sess.run([VGQ_OUTPUT], {VGQ_INPUTS[0]: crops, VGQ_INPUTS[1]: poses})[0]
    return Verification(float(np.abs(got - ref).max()), None, len(crops))


def export_model(
    net: GraspQualityNet,
    out_dir: str | Path,
    crops: np.ndarray,
    poses: np.ndarray,
    geometry: CropGeometry,
    intrinsics: Intrinsics,
    dataset: dict | None = None,
    training: dict | None = None,
    metrics: dict | None = None,
    label_threshold: float = 0.002,
    tolerance: float = DEFAULT_TOLERANCE,
    int8_check: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    calibration: CalibrationReport | None = None,
    prune_calibration: tuple[np.ndarray, np.ndarray] | None = None,
) -> ModelCard:
    """Export ``net`` to ``out_dir`` after verifying ONNX against torch on ``crops`` (n, S, S)
    metres and raw ``poses`` (n, n_pose) in the net's pose columns. Returns the model card.

    ``int8_check`` (Fast-VGQ-CNN only): labelled (crops, poses, labels) on which an int8 head
    (``export.quantize``) must score like the fp32 one; it is then added as ``head_int8.onnx``
    and its check recorded in the card (``export.int8_head``). ``prune_calibration`` (crops, poses),
    e.g. of the train split: the int8 head is quantised from the head with its dead units removed
    (``export.prune_head``; the pruned graph is checked against the unpruned one on ``int8_check``).

    ``calibration`` (``export.calibrate.calibration_report``): recorded in the card's
    ``calibration``, its reliability diagram written beside the graphs."""
    net = net.eval()
    if getattr(net, "context_scale", 0):
        raise ExportError(
            f"a network with a context view (context_scale {net.context_scale}) is a training probe: the service "
            "cuts no context views yet, so it is not exported"
        )
    crops, poses = _check_inputs(net, crops, poses)
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        s = net.image_size
        d1 = torch.zeros(1, 1, s, s)
        k_poses = torch.from_numpy(poses[:1])
        if net.arch == "fast_vgqcnn":
            files = {"encoder": "encoder.onnx", "head": "head.onnx"}
            log.info("exporting encoder graph")
            _export(
                EncoderGraph(net),
                (d1,),
                tmp / files["encoder"],
                [ENCODER_INPUT],
                [ENCODER_OUTPUT],
                {ENCODER_INPUT: {0: "n"}, ENCODER_OUTPUT: {0: "n"}},
            )
            log.info("exporting head graph")
            with torch.no_grad():
                term = net.encode(d1)
            _export(
                HeadGraph(net),
                (term, k_poses),
                tmp / files["head"],
                HEAD_INPUTS,
                [HEAD_OUTPUT],
                {HEAD_INPUTS[0]: {0: "n"}, HEAD_INPUTS[1]: {0: "k"}, HEAD_OUTPUT: {0: "k"}},
            )
            log.info("verifying against torch on %d inputs", len(crops))
            ver = _verify_fast(net, tmp / files["encoder"], tmp / files["head"], crops, poses)
        else:
            files = {"model": f"{net.arch}.onnx"}
            log.info("exporting one-piece graph")
            _export(
                OnePieceGraph(net),
                (d1, k_poses),
                tmp / files["model"],
                VGQ_INPUTS,
                [VGQ_OUTPUT],
                {VGQ_INPUTS[0]: {0: "k"}, VGQ_INPUTS[1]: {0: "k"}, VGQ_OUTPUT: {0: "k"}},
            )
            log.info("verifying against torch on %d inputs", len(crops))
            ver = _verify_one_piece(net, tmp / files["model"], crops, poses)
        bad = ver.max_abs_diff_probability > tolerance or (
            ver.max_rel_diff_image_term is not None and ver.max_rel_diff_image_term > tolerance
        )
        if bad:
            raise ExportError(f"ONNX does not reproduce torch: {ver.to_dict()} (tolerance {tolerance})")
        extra = {}
        if int8_check is not None:
            if net.arch != "fast_vgqcnn":
                raise ExportError(f"an int8 head exists for fast_vgqcnn only, not {net.arch}")
            log.info("quantising the head to int8 and checking it on %d labelled crops", len(int8_check[0]))
            files["head_int8"] = "head_int8.onnx"
            try:
                extra["int8_head"] = build_int8_head(
                    tmp / files["encoder"],
                    tmp / files["head"],
                    tmp / files["head_int8"],
                    prune_calibration,
                    int8_check,
                    prune=prune_calibration is not None,
                )
            except QuantizationError as e:
                raise ExportError(str(e)) from e
        digest = _sha(tmp / f for f in files.values())
        card = ModelCard(
            model_version=f"{net.arch}-{digest[:12]}",
            architecture=net.arch,
            geometry=geometry,
            intrinsics=intrinsics,
            normalization=net.normalization(),
            files=files,
            dataset=dict(dataset or {}),
            training=dict(training or {}),
            metrics=dict(metrics or {}),
            export={
                "opset": OPSET,
                "torch": torch.__version__,
                "onnxruntime": ort.__version__,
                "verification": ver.to_dict(),
                "tolerance": tolerance,
                "sha256": digest,
                **extra,
            },
            label_threshold=label_threshold,
            calibration=calibration.to_dict() if calibration is not None else {},
            placement_columns=PLACEMENT_COLUMNS if net.n_place else (),
        )
        if calibration is not None:
            plot_reliability(calibration, tmp / DIAGRAM)
        card.save(tmp)
        os.chmod(tmp, 0o755)
        _swap_in(tmp, out_dir)
        return card
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _swap_in(new: Path, dest: Path) -> None:
    """Replace folder ``dest`` by ``new``; readers see the old or the new folder, whole."""
    if dest.exists():
        old = dest.with_name(f".{dest.name}.old-{os.getpid()}")
        os.replace(dest, old)
        os.replace(new, dest)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(new, dest)
