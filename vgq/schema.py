"""Dataset schema: field names, dtypes, shapes and units, shared by datagen and training.

Two on-disk datasets exist (both folders with a ``manifest.json``, written atomically):

**Grasp dataset** (``datagen generate``), format ``vgq-grasps`` v1::

    manifest.json          config, seed, library versions, counts, list of shards
    shards/obj_<id>.npz    one shard per object: IMAGE_FIELDS (one row per rendered
                           depth image) + GRASP_FIELDS (one row per grasp and camera pose);
                           grasps point at their image by ``image_index`` (row in the shard)

**Crop dataset** (``datagen crops``), format ``vgq-crops`` v1, training-ready::

    manifest.json          source dataset, crop geometry, architecture, counts per split,
                           native counts (written by :func:`write_crop_manifest` only)
    <split>/<field>.npy    split in train / val / test; CROP_FIELDS, one row per grasp,
                           plain .npy so training can memory-map them

A shard listed in the manifest is complete; files not listed are ignored.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import atomic
from .crop import CropGeometry
from .placement import PLACEMENT_COLUMNS
from .pose import FULL_POSE_COLUMNS

GRASP_FORMAT = "vgq-grasps"
CROP_FORMAT = "vgq-crops"
FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
MANIFEST = "manifest.json"

#: name -> (dtype, per-row shape, meaning and unit)
IMAGE_FIELDS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "depth": ("float32", (300, 300), "rendered depth, metres, camera frame z; 0 where no surface"),
    "object_id": ("int32", (), "object index in the manifest's object list"),
    "stable_pose_id": ("int32", (), "stable pose index of the object"),
    "camera_d": ("float32", (), "camera distance from world origin, metres"),
    "camera_phi": ("float32", (), "camera elevation from the table normal, radians"),
    "camera_theta": ("float32", (), "camera azimuth, radians"),
    "T_world_camera": ("float64", (4, 4), "camera pose in the world frame (OpenCV camera)"),
}

GRASP_FIELDS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "image_index": ("int32", (), "row of the grasp's image in the same shard"),
    "grasp_id": ("int32", (), "grasp index within its object"),
    "u": ("float32", (), "projected TCP column, image px"),
    "v": ("float32", (), "projected TCP row, image px"),
    "z": ("float32", (), "TCP depth in the camera frame, metres"),
    "q": ("float32", (4,), "grasp orientation in the camera frame, canonical (w, x, y, z)"),
    "beta": ("float32", (), "angle approach axis vs downward table normal, radians"),
    "psi": ("float32", (), "angle approach axis vs camera principal ray, radians"),
    "omega": ("float32", (), "rotation about the grasp x-axis, radians"),
    "jaw_angle": ("float32", (), "in-image angle of the grasp x-axis from +u towards +v, radians"),
    "quality": (
        "float32",
        (),
        (
            "label score of the dataset's label (manifest config.label.kind); a grasp is "
            "positive when it exceeds the manifest's label_threshold. Paper label: robust "
            "Ferrari-Canny, 0 if the gripper collides"
        ),
    ),
    "collision_free": ("bool", (), "gripper approach free of object and table collisions (nominal pose)"),
}

#: Optional per-grasp label fields (issue 17). Shards written before them lack them; readers
#: return the ones a shard has, and a shard that has one must have it with this dtype and shape.
GRASP_LABEL_FIELDS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "fc_quality": ("float32", (), "robust Ferrari-Canny at the grasp-line contacts, not gated by collision"),
    "p_collision_free": (
        "float32",
        (),
        (
            "fraction of noisy approaches that keep the clearance (robust "
            "collision); NaN where the nominal approach collides"
        ),
    ),
    "pad_quality": (
        "float32",
        (),
        ("Ferrari-Canny at the pad contacts; 0 where the pads find none, NaN where the nominal approach collides"),
    ),
    "success_rate": ("float32", (), "fraction of noisy physics trials that held; NaN where none ran"),
}

CROP_FIELDS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "images": ("float32", (32, 32), "network input crop, depth in metres"),
    "poses": ("float32", (len(FULL_POSE_COLUMNS),), f"pose row {FULL_POSE_COLUMNS}; u, v in crop px"),
    "labels": ("uint8", (), "1 if quality > the dataset's label threshold"),
    "quality": ("float32", (), "robust Ferrari-Canny"),
    "object_id": ("int32", (), "object index in the grasp dataset"),
    "camera_d": ("float32", (), "camera distance, metres"),
    "camera_phi": ("float32", (), "camera elevation, radians"),
    "beta": ("float32", (), "radians"),
    "psi": ("float32", (), "radians"),
}


#: Crop fields written by ``datagen crops`` since placement rows (``vgq.placement``) and read
#: where present: datasets cropped before them lack them (a network that reads placement needs them).
CROP_EXTRA_FIELDS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "placement": (
        "float32",
        (len(PLACEMENT_COLUMNS),),
        f"placement row {PLACEMENT_COLUMNS} from the (sensor-corrupted) depth image, metres",
    ),
    "context": (
        "float16",
        (32, 32),
        "context view: the window's centre seen `context_scale` times wider (vgq.crop.context_crops), metres",
    ),
}
#: How ``datagen crops`` places a grasp for its placement row (crop manifest key
#: ``placement_grasp_depth``): at the depth its sensor-corrupted image shows it (its depth times the
#: image's scale error), as a service's client reads a grasp off the image it uploads. Crops cut
#: before this key existed placed it at its true depth against the scaled image: rows that disagree
#: with what the service computes.
PLACEMENT_GRASP_DEPTH = "as_seen"


def placement_rows_as_seen(manifest: dict) -> bool:
    """Whether a crop manifest's placement rows were made as the service makes them (:data:`PLACEMENT_GRASP_DEPTH`)."""
    return manifest.get("placement_grasp_depth") == PLACEMENT_GRASP_DEPTH


def check_placement_rows(manifest: dict, where: str) -> None:
    """ValueError naming ``where`` unless :func:`placement_rows_as_seen`."""
    if not placement_rows_as_seen(manifest):
        got = manifest.get("placement_grasp_depth")
        raise ValueError(
            f"{where}: its placement rows place each grasp at its true depth against the sensor-scaled image "
            f"(placement_grasp_depth {got!r}, need {PLACEMENT_GRASP_DEPTH!r}): cut the crops again with this datagen"
        )


#: every field a crop run writes (``context`` only where asked for: ``datagen crops --context-scale``)
WRITTEN_CROP_FIELDS = {**CROP_FIELDS, "placement": CROP_EXTRA_FIELDS["placement"]}


def check_extra_fields(arrays: dict[str, np.ndarray], n: int, where: str) -> None:
    """Check the ``CROP_EXTRA_FIELDS`` that ``arrays`` holds (any subset): dtype, row shape and
    ``n`` rows. Raises ValueError naming ``where`` and the field."""
    for name, (dtype, shape, _) in CROP_EXTRA_FIELDS.items():
        a = arrays.get(name)
        if a is None:
            continue
        if a.dtype != np.dtype(dtype) or tuple(a.shape) != (n, *shape):
            raise ValueError(
                f"{where}: field {name!r} has dtype {a.dtype} shape {a.shape}, expected {dtype} ({n}, *{shape})"
            )


def check_fields(fields: dict, arrays: dict[str, np.ndarray], where: str) -> int:
    """Check that ``arrays`` holds every field with the right dtype and row shape and the
    same row count; return that count. Raises ValueError naming ``where`` and the field."""
    n = None
    for name, (dtype, shape, _) in fields.items():
        if name not in arrays:
            raise ValueError(f"{where}: missing field {name!r}")
        a = arrays[name]
        if a.dtype != np.dtype(dtype) or tuple(a.shape[1:]) != tuple(shape):
            raise ValueError(
                f"{where}: field {name!r} has dtype {a.dtype} shape {a.shape}, expected {dtype} (n, *{shape})"
            )
        if n is None:
            n = a.shape[0]
        elif a.shape[0] != n:
            raise ValueError(f"{where}: field {name!r} has {a.shape[0]} rows, expected {n}")
    return int(n or 0)


def read_manifest(root: str | Path, expected_format: str, error: type[Exception] = ValueError) -> dict:
    """The manifest of the dataset folder ``root``, checked to be ``expected_format`` at
    FORMAT_VERSION; anything else raises ``error`` naming the folder or file at fault."""
    root = Path(root)
    if not root.exists():
        raise error(f"dataset folder {root} does not exist")
    if not root.is_dir():
        raise error(f"{root} is not a folder")
    p = root / MANIFEST
    if not p.is_file():
        raise error(f"no {MANIFEST} in {root}: not a {expected_format} dataset")
    try:
        m = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{p} is not valid JSON ({e})") from e
    fmt = m.get("format") if isinstance(m, dict) else None
    if fmt != expected_format:
        raise error(f"{p}: format {fmt!r}, expected {expected_format!r}")
    if m.get("format_version") != FORMAT_VERSION:
        raise error(f"{p}: format_version {m.get('format_version')!r}, expected {FORMAT_VERSION}")
    return m


def crop_counts(n: int, positive: int, **extra) -> dict:
    """One entry of a crop manifest's ``counts`` (or its ``native_counts``): rows ``n``,
    ``positive`` rows and ``positivity`` = positive / n (a fraction, 0 when empty), plus
    ``extra`` (e.g. ``objects``: the object ids of a split)."""
    n, positive = int(n), int(positive)
    if n < 0 or not 0 <= positive <= n:
        raise ValueError(f"crop counts need 0 <= positive <= n, got positive={positive}, n={n}")
    return {"n": n, "positive": positive, "positivity": positive / n if n else 0.0, **extra}


def write_crop_manifest(
    root: str | Path,
    architecture: str,
    geometry: CropGeometry,
    counts: dict[str, dict],
    label_threshold: float,
    source: dict,
    intrinsics: dict | None = None,
    native_counts: dict | None = None,
    context_scale: int = 0,
    **extra,
) -> dict:
    """Write ``root/manifest.json`` of a ``vgq-crops`` dataset atomically (after its split
    arrays: a dataset is complete once its manifest exists) and return it. The one writer;
    :func:`read_manifest` is its reader.

    ``counts``: split -> :func:`crop_counts`. ``intrinsics``: a ``vgq.camera.Intrinsics``
    dict (omitted: readers assume the default sensor). ``native_counts``: :func:`crop_counts`
    of the grasps before any resampling (``datagen sample``'s psi filter, positivity
    equalisation and uniform undersampling), the positivity a deployed model meets;
    default: the crops themselves (all splits), i.e. a dataset that was not resampled.
    ``context_scale`` > 0: the splits also hold context views that many windows wide (recorded as
    ``context``: scale and source window px; :func:`context_scale_of` reads it back).
    ``extra``: further top-level keys (``recipe``, ``seed``, ``versions``, ...).
    """
    for name, c in counts.items():
        if name not in SPLITS or not {"n", "positive", "positivity"} <= set(c):
            raise ValueError(
                f"crop manifest counts: bad entry {name!r}: {c} (need a split of {SPLITS} with n, positive, positivity)"
            )
    if native_counts is None:
        native_counts = crop_counts(sum(c["n"] for c in counts.values()), sum(c["positive"] for c in counts.values()))
    m = {
        "format": CROP_FORMAT,
        "format_version": FORMAT_VERSION,
        "architecture": architecture,
        "geometry": geometry.to_dict(),
        "kappa_px": geometry.kappa_px,
        "pose_columns": list(FULL_POSE_COLUMNS),
        "label_threshold": float(label_threshold),
        "counts": counts,
        "native_counts": native_counts,
        "source": source,
        **({"intrinsics": dict(intrinsics)} if intrinsics else {}),
        **(
            {"context": {"scale": int(context_scale), "window": geometry.window * int(context_scale)}}
            if context_scale
            else {}
        ),
        **extra,
    }
    atomic.write_json(Path(root) / MANIFEST, m)
    return m


def context_scale_of(manifest: dict) -> int:
    """The context views' scale a crop manifest records (:func:`write_crop_manifest`); 0: none."""
    return int((manifest.get("context") or {}).get("scale", 0))
