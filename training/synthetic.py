"""Writing crop datasets (format ``vgq-crops`` v1) and small synthetic ones with a known,
learnable signal, for tests and for checking the training pipeline end to end.

Every file is written atomically (``vgq.atomic``); the manifest is written last.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.camera import DEFAULT_INTRINSICS, Intrinsics
from vgq.crop import CropGeometry
from vgq.pose import canonical_quaternion
from vgq.schema import (
    CROP_EXTRA_FIELDS,
    CROP_FIELDS,
    PLACEMENT_GRASP_DEPTH,
    check_extra_fields,
    check_fields,
    crop_counts,
    write_crop_manifest,
)

SIGNALS = ("image", "pose", "placement", "context", "none")
SYNTHETIC_CONTEXT_SCALE = 3  # the "context" signal's views are 3 windows wide


def write_crop_dataset(
    path: str | Path,
    splits: dict[str, dict[str, np.ndarray]],
    geometry: CropGeometry,
    arch: str,
    intrinsics: Intrinsics = DEFAULT_INTRINSICS,
    label_threshold: float = 0.002,
    source: dict | None = None,
    recipe: dict | None = None,
    context_scale: int = 0,
) -> dict:
    """Write ``splits`` (split name -> CROP_FIELDS arrays, and the CROP_EXTRA_FIELDS they have) as a
    crop dataset at ``path``.

    Arrays are checked against ``vgq.schema.CROP_FIELDS`` first. ``context_scale``: the splits'
    ``context`` views are that many windows wide (recorded as ``datagen crops`` records it).
    Returns the manifest.
    """
    path = Path(path)
    counts = {}
    for name, arrays in splits.items():
        n = check_fields(CROP_FIELDS, arrays, f"split {name!r}")
        check_extra_fields(arrays, n, f"split {name!r}")
        counts[name] = crop_counts(n, int(np.asarray(arrays["labels"]).sum()))
    for name, arrays in splits.items():
        for f in [*CROP_FIELDS, *(k for k in CROP_EXTRA_FIELDS if k in arrays)]:
            atomic.save_npy(path / name / f"{f}.npy", arrays[f])
    return write_crop_manifest(
        path,
        arch,
        geometry,
        counts,
        label_threshold,
        source or {},
        intrinsics=intrinsics.to_dict(),
        recipe=recipe or {},
        context_scale=context_scale,
        # drawn rows: no sensor scale to skew them, so they stand as rows the service makes
        **({"placement_grasp_depth": PLACEMENT_GRASP_DEPTH} if any("placement" in a for a in splits.values()) else {}),
    )


def synthetic_split(
    n: int,
    rng: np.random.Generator,
    geometry: CropGeometry,
    signal: str = "image",
    positive_rate: float = 0.3,
    first_object: int = 0,
    n_objects: int = 10,
) -> dict[str, np.ndarray]:
    """``n`` synthetic crop rows whose label is learnable from ``signal``.

    * ``"image"``: positives show a 10 x 10 px block 10 cm nearer the camera at the crop
      centre, negatives do not. Poses carry no signal.
    * ``"pose"``: label = 1 where the quaternion's w > its (data) threshold; images noise.
    * ``"placement"``: label = 1 where the placement row's ``offset`` is below its (data) threshold.
    * ``"context"``: rows also get a context view (field ``context``, float16); in positives a disc of
      radius s / 3 px about its centre (an object wider than the window) stands 10 cm nearer the camera
      than the rest of the view; the window itself carries no signal.
    * ``"none"``: random labels (nothing to learn).

    Every row has a placement row (``vgq.placement``, drawn from its own stream, so the other fields
    are as they were before placement rows). Depth is in metres around the camera distance; (u, v) are uniform within
    +/- kappa_px / scale crop px; quaternions are canonical unit (w, x, y, z).
    """
    if signal not in SIGNALS:
        raise ValueError(f"signal must be one of {SIGNALS}, got {signal!r}")
    s = geometry.out
    d = rng.uniform(0.4, 1.1, n).astype(np.float32)
    phi = rng.uniform(0.0, np.radians(70.0), n).astype(np.float32)
    z = (d + rng.normal(0.0, 0.01, n)).astype(np.float32)
    k = geometry.kappa_px / geometry.scale
    uv = rng.uniform(-k, k, (n, 2)).astype(np.float32)
    q = canonical_quaternion(rng.normal(size=(n, 4))).astype(np.float32)
    images = (z[:, None, None] + 0.03 + rng.normal(0.0, 0.002, (n, s, s))).astype(np.float32)
    prng = np.random.default_rng([n, first_object, 0x706C])
    height = prng.uniform(0.01, 0.1, n)
    place = np.stack(
        [
            np.ones(n),
            prng.uniform(0.0, 0.08, n),
            prng.uniform(0.0, 0.08, n),
            prng.uniform(0.0, 0.04, n),
            prng.uniform(-0.05, 0.05, n),
            height,
            height + prng.uniform(0.0, 0.1, n),
        ],
        axis=1,
    ).astype(np.float32)
    if signal == "image":
        labels = rng.random(n) < positive_rate
        c, h = s // 2, 5
        images[labels, c - h : c + h, c - h : c + h] -= 0.1
    elif signal == "pose":
        thr = np.quantile(q[:, 0], 1.0 - positive_rate) if n else 0.0
        labels = q[:, 0] > thr
    elif signal == "placement":
        labels = place[:, 1] < (np.quantile(place[:, 1], positive_rate) if n else 0.0)
    else:
        labels = rng.random(n) < positive_rate
    extra = {}
    if signal == "context":
        ctx = (z[:, None, None] + 0.03 + rng.normal(0.0, 0.002, (n, s, s))).astype(np.float32)
        yy, xx = np.mgrid[:s, :s] - (s - 1) / 2
        disc = yy**2 + xx**2 < (s / 3) ** 2
        ctx[labels] -= np.float32(0.1) * disc
        extra["context"] = ctx.astype(np.float16)
    quality = np.where(labels, rng.uniform(0.0025, 0.01, n), rng.uniform(0.0, 0.0019, n)).astype(np.float32)
    return {
        "images": images,
        "poses": np.concatenate([uv, z[:, None], q], axis=1).astype(np.float32),
        "labels": labels.astype(np.uint8),
        "quality": quality,
        "object_id": rng.integers(first_object, first_object + n_objects, n).astype(np.int32),
        "camera_d": d,
        "camera_phi": phi,
        "beta": rng.uniform(0.0, np.pi / 2, n).astype(np.float32),
        "psi": rng.uniform(0.0, np.pi / 2, n).astype(np.float32),
        "placement": place,
        **extra,
    }


def make_synthetic_crop_dataset(
    path: str | Path,
    n_train: int = 512,
    n_val: int = 128,
    n_test: int = 128,
    arch: str = "fast_vgqcnn",
    kappa_px: float = 36.0,
    signal: str = "image",
    positive_rate: float = 0.3,
    seed: int = 0,
) -> dict:
    """Write a small synthetic crop dataset (object-disjoint splits). Returns the manifest."""
    rng = np.random.default_rng(seed)
    geom = CropGeometry(window=96, out=32, kappa_px=kappa_px)
    splits = {
        "train": synthetic_split(n_train, rng, geom, signal, positive_rate, first_object=0),
        "val": synthetic_split(n_val, rng, geom, signal, positive_rate, first_object=10),
        "test": synthetic_split(n_test, rng, geom, signal, positive_rate, first_object=20),
    }
    recipe = {"synthetic": True, "signal": signal, "positive_rate": positive_rate, "seed": seed}
    ctx = SYNTHETIC_CONTEXT_SCALE if signal == "context" else 0
    return write_crop_dataset(path, splits, geom, arch, recipe=recipe, source={"kind": "synthetic"}, context_scale=ctx)
