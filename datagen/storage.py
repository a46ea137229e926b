"""On-disk datasets of :mod:`vgq.schema`: the grasp dataset (``vgq-grasps``) and the crop
dataset (``vgq-crops``).

Grasp dataset: ``manifest.json`` + ``shards/obj_<id>.npz`` (one shard per object, IMAGE_FIELDS
and GRASP_FIELDS side by side). Every file is written atomically (:mod:`vgq.atomic`); the
manifest is rewritten after each shard, so a killed writer loses at most the objects in
flight, and files not listed in the manifest (``.*.tmp-*`` leftovers, unlisted shards) are
never read. Crop dataset: ``manifest.json`` + ``<split>/<field>.npy``, plain .npy files that
training can memory-map; large arrays are filled through a memory map into a temporary file
that is renamed into place when complete.
"""

from __future__ import annotations

import hashlib
import io
import os
import platform
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vgq import __version__ as vgq_version
from vgq import atomic, schema
from vgq.schema import (
    CROP_EXTRA_FIELDS,
    CROP_FIELDS,
    CROP_FORMAT,
    FORMAT_VERSION,
    GRASP_FIELDS,
    GRASP_FORMAT,
    GRASP_LABEL_FIELDS,
    IMAGE_FIELDS,
    MANIFEST,
    SPLITS,
    WRITTEN_CROP_FIELDS,
    check_extra_fields,
    check_fields,
)

SHARD_DIR = "shards"
# deflate level of the shards: 1 writes a v2 shard in half the time of numpy's 6 for 11% more bytes
# (0.32 against 0.59 s, 6.1 against 5.5 MB for one random_urdfs object of 300 images)
SHARD_DEFLATE_LEVEL = 1


class DatasetError(ValueError):
    """A dataset folder or file is missing, corrupt or foreign; the message names the file."""


def shard_relpath(object_id: int) -> str:
    return f"{SHARD_DIR}/obj_{int(object_id):05d}.npz"


def library_versions() -> dict[str, str]:
    """Versions of the libraries that shape the generated data (recorded in manifests)."""
    from importlib import metadata

    out = {"python": platform.python_version(), "vgq": vgq_version}
    for dist in ("numpy", "scipy", "trimesh", "python-fcl", "embreex", "pybullet", "pillow"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def empty_arrays(fields: dict) -> dict[str, np.ndarray]:
    """Zero-row arrays with the dtypes and row shapes of ``fields``."""
    return {k: np.zeros((0, *shape), dtype=dtype) for k, (dtype, shape, _) in fields.items()}


# ----------------------------------------------------------------------------- shards


def encode_shard(images: dict[str, np.ndarray], grasps: dict[str, np.ndarray], where: str = "shard") -> bytes:
    """Validate and serialise one object's arrays to compressed .npz bytes."""
    n_img = check_fields(IMAGE_FIELDS, images, f"{where} (images)")
    check_fields(GRASP_FIELDS, grasps, f"{where} (grasps)")
    idx = grasps["image_index"]
    if len(idx) and (idx.min() < 0 or idx.max() >= n_img):
        raise ValueError(f"{where}: image_index outside [0, {n_img})")
    _check_label_fields(grasps, len(idx), f"{where} (grasps)")
    arrays = {k: np.ascontiguousarray(images[k]) for k in IMAGE_FIELDS}
    arrays.update({k: np.ascontiguousarray(grasps[k]) for k in GRASP_FIELDS})
    arrays.update({k: np.ascontiguousarray(grasps[k]) for k in GRASP_LABEL_FIELDS if k in grasps})
    return npz_bytes(arrays)


def npz_bytes(arrays: dict[str, np.ndarray], level: int = SHARD_DEFLATE_LEVEL) -> bytes:
    """``np.savez_compressed``'s .npz bytes at deflate ``level`` (numpy's is zlib's default, 6)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, allowZip64=True, compresslevel=level) as zf:
        for k, v in arrays.items():
            with zf.open(f"{k}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(v), allow_pickle=False)
    return buf.getvalue()


def _check_label_fields(grasps: dict, n: int, where: str) -> None:
    """The optional GRASP_LABEL_FIELDS present in ``grasps`` have their dtype, shape and n rows."""
    present = {k: v for k, v in GRASP_LABEL_FIELDS.items() if k in grasps}
    if present and check_fields(present, grasps, where) != n:
        raise ValueError(f"{where}: label fields have {check_fields(present, grasps, where)} rows, expected {n}")


def shard_counts(images: dict, grasps: dict, label_threshold: float) -> dict[str, int]:
    q = grasps["quality"]
    return {
        "num_images": int(len(images["depth"])),
        "num_grasps": int(len(q)),
        "num_positive": int(np.count_nonzero(q > label_threshold)),
        "num_collision_free": int(np.count_nonzero(grasps["collision_free"])),
    }


def write_shard(root: str | Path, object_id: int, images: dict, grasps: dict, label_threshold: float) -> dict:
    """Write ``shards/obj_<id>.npz`` atomically; return its manifest entry (file, sha256, counts)."""
    rel = shard_relpath(object_id)
    data = encode_shard(images, grasps, where=rel)
    atomic.write_bytes(Path(root) / rel, data)
    return {
        "object_id": int(object_id),
        "file": rel,
        "sha256": hashlib.sha256(data).hexdigest(),
        **shard_counts(images, grasps, label_threshold),
    }


def read_shard(
    path: str | Path, sha256: str | None = None, skip: tuple[str, ...] = ()
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Load and validate one shard; returns (image arrays, grasp arrays). ``skip``: fields left
    compressed and out of the result (e.g. ``("depth",)`` for a pass that reads only the grasps).

    Raises :class:`DatasetError` naming the file when it is missing, not an .npz, fails its
    checksum or lacks a field."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise DatasetError(f"cannot read shard {p}: {e.strerror or e}") from e
    if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
        raise DatasetError(f"shard {p} is corrupt: its sha256 does not match the manifest")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k not in skip}
    except Exception as e:  # zipfile, zlib, numpy format errors: all mean "not a readable shard"
        raise DatasetError(f"shard {p} is not a readable .npz file ({type(e).__name__}: {e})") from e
    try:
        image_fields = {k: v for k, v in IMAGE_FIELDS.items() if k not in skip}
        grasp_fields = {k: v for k, v in GRASP_FIELDS.items() if k not in skip}
        images = {k: arrays[k] for k in image_fields if k in arrays}
        grasps = {k: arrays[k] for k in (*grasp_fields, *GRASP_LABEL_FIELDS) if k in arrays}
        n_img = check_fields(image_fields, images, str(p))
        _check_label_fields(grasps, check_fields(grasp_fields, grasps, str(p)), str(p))
    except ValueError as e:
        raise DatasetError(f"shard {p} is not a {GRASP_FORMAT} shard: {e}") from e
    idx = grasps["image_index"]
    if len(idx) and (idx.min() < 0 or idx.max() >= n_img):
        raise DatasetError(f"shard {p}: image_index outside [0, {n_img})")
    return images, grasps


# ----------------------------------------------------------------------------- manifest


def read_manifest(root: str | Path, expected_format: str) -> dict:
    return schema.read_manifest(root, expected_format, DatasetError)


def new_grasp_manifest(config: dict, seed: int, objects: list[dict], label_threshold: float, **extra) -> dict:
    """A fresh grasp-dataset manifest. ``objects``: [{object_id, name, source, ...}] in id order."""
    m = {
        "format": GRASP_FORMAT,
        "format_version": FORMAT_VERSION,
        "config": config,
        "seed": int(seed),
        "label_threshold": float(label_threshold),
        "versions": library_versions(),
        "objects": [dict(o, status="pending") for o in objects],
        "shards": [],
        "complete": False,
    }
    m.update(extra)
    update_counts(m)
    return m


def update_counts(m: dict) -> None:
    """Recompute the manifest's ``counts`` from its shard and object entries (in place)."""
    shards = m["shards"]
    n = sum(s["num_grasps"] for s in shards)
    pos = sum(s["num_positive"] for s in shards)
    status = [o.get("status") for o in m["objects"]]
    m["counts"] = {
        "objects": len(m["objects"]),
        "objects_done": status.count("done"),
        "objects_skipped": status.count("skipped"),
        "objects_pending": status.count("pending"),
        "shards": len(shards),
        "images": sum(s["num_images"] for s in shards),
        "grasps": n,
        "positive": pos,
        "collision_free": sum(s["num_collision_free"] for s in shards),
        "positivity_rate": pos / n if n else 0.0,
    }


def family_counts(m: dict) -> dict[str, dict]:
    """Per object family of a grasp-dataset manifest ``m`` (``random_urdfs`` etc.; "" where none is
    recorded): objects done / skipped / pending, grasps, positive and collision-free rows,
    positivity, and how many done objects have no positive grasp at all (none of their grasps
    succeeds: too wide, too flat or too slippery for the gripper)."""
    out: dict[str, dict] = {}
    for o in m["objects"]:
        f = out.setdefault(
            o.get("family") or "",
            {"done": 0, "skipped": 0, "pending": 0, "grasps": 0, "positive": 0, "collision_free": 0, "no_positive": 0},
        )
        st = o.get("status", "pending")
        f[st if st in ("done", "skipped") else "pending"] += 1
    fam = {int(o["object_id"]): o.get("family") or "" for o in m["objects"]}
    for s in m["shards"]:
        f = out[fam[int(s["object_id"])]]
        f["grasps"] += s["num_grasps"]
        f["positive"] += s["num_positive"]
        f["collision_free"] += s["num_collision_free"]
        f["no_positive"] += s["num_positive"] == 0
    for f in out.values():
        f["positivity"] = f["positive"] / f["grasps"] if f["grasps"] else 0.0
    return dict(sorted(out.items()))


def record_shard(m: dict, entry: dict, **object_info) -> None:
    """Add/replace a shard entry and mark its object done (in place; keeps id order)."""
    oid = entry["object_id"]
    m["shards"] = sorted([s for s in m["shards"] if s["object_id"] != oid] + [entry], key=lambda s: s["object_id"])
    obj = m["objects"][oid]
    obj.update(object_info)
    obj.update(status="done", shard=entry["file"])
    obj.pop("reason", None)
    obj.pop("retry", None)
    update_counts(m)


def record_skip(m: dict, object_id: int, reason: str, **object_info) -> None:
    obj = m["objects"][object_id]
    obj.update(object_info)
    obj.update(status="skipped", reason=reason)
    obj.pop("shard", None)
    obj.pop("retry", None)
    update_counts(m)


def write_manifest(root: str | Path, m: dict) -> None:
    atomic.write_json(Path(root) / MANIFEST, m)


# ----------------------------------------------------------------------------- reader


@dataclass
class Shard:
    """One object's data: ``images`` (IMAGE_FIELDS arrays) and ``grasps`` (GRASP_FIELDS arrays)."""

    object_id: int
    name: str
    images: dict[str, np.ndarray]
    grasps: dict[str, np.ndarray]


class GraspDataset:
    """Read access to a ``vgq-grasps`` dataset; iterate it for :class:`Shard` objects in id order."""

    def __init__(self, root: str | Path, verify: bool = True):
        self.root = Path(root)
        self.manifest = read_manifest(self.root, GRASP_FORMAT)
        self.verify = verify
        try:
            self.shard_entries = sorted(self.manifest["shards"], key=lambda s: s["object_id"])
            self.objects = self.manifest["objects"]
            for s in self.shard_entries:
                if not 0 <= s["object_id"] < len(self.objects):
                    raise DatasetError(f"{self.root / MANIFEST}: shard {s['file']} has unknown object_id")
        except (KeyError, TypeError) as e:
            raise DatasetError(f"{self.root / MANIFEST}: malformed manifest ({e!r})") from e

    @property
    def label_threshold(self) -> float:
        return float(self.manifest["label_threshold"])

    @property
    def object_ids(self) -> list[int]:
        return [s["object_id"] for s in self.shard_entries]

    def __len__(self) -> int:
        return len(self.shard_entries)

    def load(self, entry: dict) -> Shard:
        path = self.root / entry["file"]
        images, grasps = read_shard(path, entry.get("sha256") if self.verify else None)
        if len(grasps["grasp_id"]) != entry.get("num_grasps", len(grasps["grasp_id"])):
            raise DatasetError(f"shard {path}: {len(grasps['grasp_id'])} grasps, manifest says {entry['num_grasps']}")
        oid = int(entry["object_id"])
        return Shard(oid, str(self.objects[oid].get("name", oid)), images, grasps)

    def __iter__(self) -> Iterator[Shard]:
        for e in self.shard_entries:
            yield self.load(e)


def open_dataset(path: str | Path, verify: bool = True) -> GraspDataset:
    """Open a grasp dataset folder. Shards are checked (sha256 when ``verify``, fields always)
    as they are loaded; a missing, corrupt or foreign file raises :class:`DatasetError`."""
    return GraspDataset(path, verify=verify)


# ----------------------------------------------------------------------------- crop dataset


class NpyWriter:
    """Fill a (rows, *shape) .npy file through a memory map, then rename it into place.

    The data lives in a temporary file until :meth:`close`: ``.<name>.tmp-*`` (an unfinished
    writer leaves only that behind), or with ``partial=True`` the fixed ``.<name>.partial``,
    which ``resume=True`` reopens (same dtype and shape) to go on filling it after a stop."""

    def __init__(
        self, path: str | Path, dtype: str, shape: tuple[int, ...], partial: bool = False, resume: bool = False
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if partial:
            self.tmp = str(self.path.parent / f".{self.path.name}.partial")
        else:
            fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.tmp-", dir=self.path.parent)
            os.close(fd)
        if shape[0] == 0:
            self.array = np.zeros(shape, dtype=dtype)
        elif resume:
            self.array = np.lib.format.open_memmap(self.tmp, mode="r+")
            if self.array.dtype != np.dtype(dtype) or self.array.shape != tuple(shape):
                raise DatasetError(
                    f"{self.tmp}: holds {self.array.dtype} {self.array.shape}, expected {np.dtype(dtype)} {tuple(shape)}"
                )
        else:
            self.array = np.lib.format.open_memmap(self.tmp, mode="w+", dtype=np.dtype(dtype), shape=shape)

    def flush(self) -> None:
        """Write the rows filled so far to the file (kept by a later ``resume``)."""
        if isinstance(self.array, np.memmap):
            self.array.flush()

    def close(self) -> None:
        if isinstance(self.array, np.memmap):
            self.array.flush()
            del self.array
            with open(self.tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(self.tmp, self.path)
        else:
            if os.path.exists(self.tmp):
                os.unlink(self.tmp)
            atomic.save_npy(self.path, self.array)

    def abort(self) -> None:
        self.array = None
        try:
            os.unlink(self.tmp)
        except FileNotFoundError:
            pass


def crop_writers(
    root: str | Path, split: str, n: int, partial: bool = False, resume: bool = False, extra: tuple[str, ...] = ()
) -> dict[str, NpyWriter]:
    """One :class:`NpyWriter` per WRITTEN_CROP_FIELDS field, and per ``extra`` CROP_EXTRA_FIELDS
    field (e.g. ``context``), for ``n`` rows of ``root/split`` (``partial``/``resume``: see
    :class:`NpyWriter`)."""
    fields = {**WRITTEN_CROP_FIELDS, **{k: CROP_EXTRA_FIELDS[k] for k in extra}}
    return {
        k: NpyWriter(Path(root) / split / f"{k}.npy", dtype, (n, *shape), partial=partial, resume=resume)
        for k, (dtype, shape, _) in fields.items()
    }


def open_crops(root: str | Path, split: str, mmap: bool = True) -> dict[str, np.ndarray]:
    """Load (memory-mapped) the CROP_FIELDS arrays of one split of a ``vgq-crops`` dataset, and the
    CROP_EXTRA_FIELDS it has."""
    root = Path(root)
    m = read_manifest(root, CROP_FORMAT)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    arrays = {}
    for k in CROP_FIELDS:
        p = root / split / f"{k}.npy"
        try:
            arrays[k] = np.load(p, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise DatasetError(f"cannot read crop field file {p} ({e})") from e
    for k in CROP_EXTRA_FIELDS:
        p = root / split / f"{k}.npy"
        if p.is_file():
            try:
                arrays[k] = np.load(p, mmap_mode="r" if mmap else None, allow_pickle=False)
            except (OSError, ValueError) as e:
                raise DatasetError(f"cannot read crop field file {p} ({e})") from e
    try:
        n = check_fields(CROP_FIELDS, arrays, str(root / split))
        check_extra_fields(arrays, n, str(root / split))
    except ValueError as e:
        raise DatasetError(str(e)) from e
    expected = m.get("counts", {}).get(split, {}).get("grasps")
    if expected is not None and n != expected:
        raise DatasetError(f"{root / split}: {n} rows, manifest says {expected}")
    return arrays
