"""onnxruntime sessions for a model folder: encode a crop once, score grasps against it."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from planning import calibration as planner_calibration
from planning import ranker as planner_ranker
from vgq.model_card import ENCODER_INPUT, ENCODER_OUTPUT, HEAD_INPUTS, HEAD_OUTPUT, ModelCard
from vgq.placement import PLACEMENT_COLUMNS

from .config import ENCODER_PRECISIONS, HEAD_PRECISIONS

#: card file role of each encoder precision (export: encoder.onnx; export.int8_encoder: encoder_int8.onnx)
ENCODER_FILES = {"fp32": "encoder", "int8": "encoder_int8"}


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
    """Fast-VGQ-CNN: ``encode`` (1 crop -> its encoding: the 1024 image term, with a jaw-grid head
    also the feature map) and ``score`` (k poses against one encoding)."""

    def __init__(
        self,
        model_dir: str | Path,
        threads: int = 1,
        head_precision: str = "auto",
        encoder_precision: str = "auto",
        select_s: float = 0.3,
    ):
        """``head_precision``: ``fp32``, ``int8`` (the card's checked ``head_int8`` graph, see
        export/quantize.py) or ``auto`` (int8 when the model folder has one).
        ``encoder_precision``: ``fp32``, ``int8`` (the card's checked ``encoder_int8`` graph, see
        export/int8_encoder.py) or ``auto``: every encoder the card holds is timed on this machine
        for about ``select_s`` seconds and the fastest is served (``encoder_info`` says which and why)."""
        model_dir = Path(model_dir)
        try:
            self.card = ModelCard.load(model_dir)
        except (FileNotFoundError, ValueError, KeyError) as e:
            raise ModelError(f"cannot load model from {model_dir}: {e}") from e
        if self.card.architecture != "fast_vgqcnn":
            raise ModelError(f"{model_dir}: architecture {self.card.architecture!r}; the service serves fast_vgqcnn")
        if self.card.geometry.align_jaw:  # a crop per grasp, turned exactly: not a shared window
            raise ModelError(
                f"{model_dir}: the model was trained on crops {self.card.geometry.turning()} (one per grasp); "
                "the service scores grasps on shared windows and cannot serve it"
            )
        if self.card.placement_columns and tuple(self.card.placement_columns) != PLACEMENT_COLUMNS:
            raise ModelError(
                f"{model_dir}: the head reads placement columns {list(self.card.placement_columns)}; this service "
                f"computes {list(PLACEMENT_COLUMNS)} (vgq.placement)"
            )
        try:  # planned grasps' p_hold (planning.calibration) and order (planning.ranker); None: none there
            self.planner_calibration = planner_calibration.load(model_dir)
            self.planner_ranker = planner_ranker.load(model_dir)
        except ValueError as e:
            raise ModelError(f"cannot load model from {model_dir}: {e}") from e
        if head_precision not in HEAD_PRECISIONS:
            raise ModelError(f"head_precision must be one of {HEAD_PRECISIONS}, got {head_precision!r}")
        has_int8 = "head_int8" in self.card.files
        if head_precision == "int8" and not has_int8:
            raise ModelError(
                f"{model_dir}: head_precision int8 asked for, but the model has no int8 head "
                "(export it with --int8-head)"
            )
        self.head_precision = "int8" if has_int8 and head_precision != "fp32" else "fp32"
        head_file = self.card.files["head_int8" if self.head_precision == "int8" else "head"]
        if encoder_precision not in ENCODER_PRECISIONS:
            raise ModelError(f"encoder_precision must be one of {ENCODER_PRECISIONS}, got {encoder_precision!r}")
        available = [p for p, role in ENCODER_FILES.items() if role in self.card.files]
        if encoder_precision != "auto" and encoder_precision not in available:
            raise ModelError(
                f"{model_dir}: encoder_precision {encoder_precision} asked for, but the model has no such encoder "
                "(export it with python -m export.int8_encoder)"
            )
        so = session_options(threads)
        try:
            encoders = {
                p: ort.InferenceSession(
                    str(model_dir / self.card.files[ENCODER_FILES[p]]), so, providers=["CPUExecutionProvider"]
                )
                for p in (available if encoder_precision == "auto" else [encoder_precision])
            }
            self.head = ort.InferenceSession(str(model_dir / head_file), so, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types
            raise ModelError(f"cannot open ONNX graphs in {model_dir}: {e}") from e
        self.geometry = self.card.geometry
        timings = time_encoders(encoders, self.geometry.out, select_s) if len(encoders) > 1 else {}
        self.encoder_precision = min(timings, key=timings.get) if timings else next(iter(encoders))
        self.encoder = encoders[self.encoder_precision]  # the others are dropped
        #: how the encoder was chosen: reported by /v1/model and the start-up log
        self.encoder_info = {
            "precision": self.encoder_precision,
            "requested": encoder_precision,
            "available": available,
            "median_ms": {p: round(t * 1e3, 4) for p, t in timings.items()},
            "threads": threads,
        }
        self.version = self.card.model_version
        self.n_pose = self.card.head_pose_width  # the pose columns, then a placement head's placement row
        self.encode_seconds = 0.0
        self.score_seconds = 0.0

    def encode(self, crop: np.ndarray) -> np.ndarray:
        """(out, out) or (n, out, out) float32 crops in metres -> (n, D) float32 encodings (D = 1024, or
        1024 + the feature map for a jaw-grid head: ``training.networks.GraspQualityNet.encoding_width``)."""
        t = time.perf_counter()
        x = np.ascontiguousarray(crop, dtype=np.float32).reshape(-1, 1, *crop.shape[-2:])
        term = self.encoder.run([ENCODER_OUTPUT], {ENCODER_INPUT: x})[0]
        self.encode_seconds = time.perf_counter() - t
        return term

    def score(self, image_term: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """(1, D) encoding, (k, 7) network pose rows (k, 14 for a placement head: each followed by its
        placement row, ``vgq.placement``) -> (k,) float32 probabilities."""
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


def time_encoders(encoders: dict[str, ort.InferenceSession], side: int, seconds: float) -> dict[str, float]:
    """Median seconds per one-crop call of each encoder session, calls interleaved (so load from
    other processes hits them alike) for about ``seconds`` in all, after a short warm-up."""
    rng = np.random.default_rng(0)
    x = (0.6 + 0.01 * rng.standard_normal((1, 1, side, side))).astype(np.float32)
    feed = {ENCODER_INPUT: x}
    for s in encoders.values():
        for _ in range(5):
            s.run([ENCODER_OUTPUT], feed)
    times: dict[str, list[float]] = {p: [] for p in encoders}
    end = time.perf_counter() + seconds
    while time.perf_counter() < end or min(len(t) for t in times.values()) < 5:
        for p, s in encoders.items():
            t = time.perf_counter()
            s.run([ENCODER_OUTPUT], feed)
            times[p].append(time.perf_counter() - t)
    return {p: float(np.median(t)) for p, t in times.items()}
