"""onnxruntime sessions for a model folder: encode a crop once, score grasps against it."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from vgq.model_card import ENCODER_INPUT, ENCODER_OUTPUT, HEAD_INPUTS, HEAD_OUTPUT, ModelCard

from .config import HEAD_PRECISIONS


class ModelError(RuntimeError):
    """The model folder is missing, unreadable or of an architecture this service can't serve."""


def session_options(threads: int) -> ort.SessionOptions:
    """onnxruntime options of the service's sessions (also used by export.benchmark)."""
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    # Two sessions share the cores: spinning threads of one steal from the other (p99 x5).
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return so


class FastModel:
    """Fast-VGQ-CNN: ``encode`` (1 crop -> 1024 image term) and ``score`` (k poses)."""

    def __init__(self, model_dir: str | Path, threads: int = 1, head_precision: str = "auto"):
        """``head_precision``: ``fp32``, ``int8`` (the card's checked ``head_int8`` graph, see
        export/quantize.py) or ``auto`` (int8 when the model folder has one)."""
        model_dir = Path(model_dir)
        try:
            self.card = ModelCard.load(model_dir)
        except (FileNotFoundError, ValueError, KeyError) as e:
            raise ModelError(f"cannot load model from {model_dir}: {e}") from e
        if self.card.architecture != "fast_vgqcnn":
            raise ModelError(f"{model_dir}: architecture {self.card.architecture!r}; the service serves fast_vgqcnn")
        if head_precision not in HEAD_PRECISIONS:
            raise ModelError(f"head_precision must be one of {HEAD_PRECISIONS}, got {head_precision!r}")
        has_int8 = "head_int8" in self.card.files
        if head_precision == "int8" and not has_int8:
            raise ModelError(f"{model_dir}: head_precision int8 asked for, but the model has no int8 head "
                             "(export it with --int8-head)")
        self.head_precision = "int8" if has_int8 and head_precision != "fp32" else "fp32"
        head_file = self.card.files["head_int8" if self.head_precision == "int8" else "head"]
        so = session_options(threads)
        try:
            self.encoder = ort.InferenceSession(str(model_dir / self.card.files["encoder"]), so, providers=["CPUExecutionProvider"])
            self.head = ort.InferenceSession(str(model_dir / head_file), so, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types
            raise ModelError(f"cannot open ONNX graphs in {model_dir}: {e}") from e
        self.geometry = self.card.geometry
        self.version = self.card.model_version
        self.n_pose = len(self.card.normalization.pose_columns)
        self.encode_seconds = 0.0
        self.score_seconds = 0.0

    def encode(self, crop: np.ndarray) -> np.ndarray:
        """(out, out) or (n, out, out) float32 crops in metres -> (n, 1024) float32 image terms."""
        t = time.perf_counter()
        x = np.ascontiguousarray(crop, dtype=np.float32).reshape(-1, 1, *crop.shape[-2:])
        term = self.encoder.run([ENCODER_OUTPUT], {ENCODER_INPUT: x})[0]
        self.encode_seconds = time.perf_counter() - t
        return term

    def score(self, image_term: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """(1, 1024) image term, (k, 7) network pose rows -> (k,) float32 probabilities."""
        t = time.perf_counter()
        p = self.head.run([HEAD_OUTPUT], {HEAD_INPUTS[0]: image_term, HEAD_INPUTS[1]: poses})[0]
        self.score_seconds = time.perf_counter() - t
        return p

    def warm_up(self, rounds: int = 20) -> None:
        s = self.geometry.out
        rng = np.random.default_rng(0)
        crop = (0.6 + 0.01 * rng.standard_normal((s, s))).astype(np.float32)
        poses = np.zeros((128, self.n_pose), np.float32)
        poses[:, 2] = 0.6
        poses[:, 3] = 1.0
        for _ in range(rounds):
            self.score(self.encode(crop), poses)
