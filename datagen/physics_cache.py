"""Physics-trial outcomes kept between generations (``datagen physics-cache``, ``generate
--physics-cache FILE``).

The physics label's trials are most of a generation's time (measured on three v2 objects: 4.4 of
6.3 s, 10.6 of 12.2 s and 20.8 of 22.8 s per object). A grasp's success rate at a stable pose
depends on the mesh, the pose, the grasp and the trial seeds, not on the cameras, so a later
generation with the same recipe can replay it instead of running the trials again: the
dataset comes out the same (the test checks it row for row) in a fraction of the time.

The cache is read from a finished or partial grasp dataset (its shards hold every grasp that
appears in an image, with its success rate, and the manifest each pose's trial record). Per
(object name, stable pose id) it keeps, for those grasps: the grasp id, the tool centre point in
the world frame (m, float16; the fingerprint checked on use), whether the nominal approach was
free, and the success rate as held / run trials. A replay uses a pose only when every grasp the
pose needs (free now and inside an image) is in it, was free then and has its TCP within
:data:`TCP_TOLERANCE_M`, and the cache was made with the same physics settings
(:func:`config_key`); anything else runs the trials as without a cache.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.camera import Intrinsics, deproject

CACHE_FORMAT = "vgq-physics-cache"
CACHE_VERSION = 1
TCP_TOLERANCE_M = 1e-3  # float16 world coordinates below 0.5 m are within 0.25 mm


class PhysicsCacheError(ValueError):
    """A physics cache file is missing, corrupt, foreign, or made with other settings."""


def config_key(config) -> str:
    """The settings a success rate depends on besides the mesh and grasp (canonical JSON of the
    run seed and the label, physics and gripper sections of a ``DatagenConfig`` dict or object)."""
    d = config if isinstance(config, dict) else config.to_dict()
    return json.dumps({k: d[k] for k in ("seed", "label", "physics", "gripper")}, sort_keys=True)


@dataclass(frozen=True)
class PoseTrials:
    """Recorded trials of one object at one stable pose, over the grasps seen in its images.

    ``grasp_id`` (n,) int; ``tcp`` (n, 3) world-frame tool centre points (m); ``held``, ``run``
    (n,) held and run trials (``run`` 0: the nominal approach collided, no trials); ``record``:
    the manifest's entry for the pose (trials, seconds, pose_stable, pose_drift_m)."""

    grasp_id: np.ndarray
    tcp: np.ndarray
    held: np.ndarray
    run: np.ndarray
    record: dict = field(default_factory=dict)

    def replay(self, T_world_grasp: np.ndarray, need: np.ndarray) -> np.ndarray | None:
        """Success rates (n,) float64 of the grasps ``T_world_grasp`` (n, 4, 4; row i = grasp id i)
        where ``need`` (n,) bool is set, 0 elsewhere; None when a needed grasp is not recorded,
        had no trials, or its TCP lies more than :data:`TCP_TOLERANCE_M` from the recorded one."""
        out = np.zeros(len(T_world_grasp))
        idx = np.flatnonzero(need)
        if not len(idx):
            return out
        pos = np.full(len(T_world_grasp), -1)
        pos[self.grasp_id[self.grasp_id < len(pos)]] = np.flatnonzero(self.grasp_id < len(pos))
        j = pos[idx]
        if np.any(j < 0) or np.any(self.run[j] == 0):
            return None
        d = np.abs(T_world_grasp[idx, :3, 3] - self.tcp[j].astype(np.float64)).max()
        if not d <= TCP_TOLERANCE_M:
            return None
        out[idx] = self.held[j].astype(np.float64) / self.run[j]
        return out


@dataclass
class PhysicsCache:
    """Per object name, per stable pose id, the :class:`PoseTrials` of one physics setting (``key``)."""

    key: str
    objects: dict[str, dict[int, PoseTrials]] = field(default_factory=dict)

    def for_object(self, name: str) -> dict[int, PoseTrials]:
        return self.objects.get(name, {})

    @property
    def num_poses(self) -> int:
        return sum(len(p) for p in self.objects.values())

    def merge(self, other: PhysicsCache) -> PhysicsCache:
        """This cache with ``other``'s objects added (``other`` wins for an object in both)."""
        if other.key != self.key:
            raise PhysicsCacheError("the caches were made with different label, physics or gripper settings")
        return PhysicsCache(self.key, {**self.objects, **other.objects})

    def save(self, path: str | Path) -> None:
        """Write the cache as one compressed .npz, atomically."""
        names, poses, counts, records = [], [], [], []
        cols: dict[str, list] = {"grasp_id": [], "tcp": [], "held": [], "run": []}
        for name in sorted(self.objects):
            for pose_id in sorted(self.objects[name]):
                t = self.objects[name][pose_id]
                names.append(name)
                poses.append(pose_id)
                counts.append(len(t.grasp_id))
                records.append(t.record)
                for k in cols:
                    cols[k].append(getattr(t, k))
        if any(int(r.max(initial=0)) > 255 for r in cols["run"]):
            raise PhysicsCacheError("more than 255 trials per grasp do not fit the cache")
        header = {"format": CACHE_FORMAT, "version": CACHE_VERSION, "key": self.key, "records": records}
        cat = lambda k, dt, shape: np.concatenate(cols[k]).astype(dt) if cols[k] else np.zeros(shape, dt)  # noqa: E731
        atomic.save_npz(
            path,
            header=np.array(json.dumps(header)),
            object_name=np.array(names, dtype=str),
            pose_id=np.array(poses, np.int16),
            count=np.array(counts, np.int32),
            grasp_id=cat("grasp_id", np.uint16, (0,)),
            tcp=cat("tcp", np.float16, (0, 3)),
            held=cat("held", np.uint8, (0,)),
            run=cat("run", np.uint8, (0,)),
        )

    @classmethod
    def load(cls, path: str | Path) -> PhysicsCache:
        try:
            with np.load(path, allow_pickle=False) as z:
                header = json.loads(str(z["header"]))
                if header.get("format") != CACHE_FORMAT or header.get("version") != CACHE_VERSION:
                    raise PhysicsCacheError(f"{path}: not a {CACHE_FORMAT} v{CACHE_VERSION} file")
                a = {k: z[k] for k in ("object_name", "pose_id", "count", "grasp_id", "tcp", "held", "run")}
        except PhysicsCacheError:
            raise
        except (OSError, ValueError, KeyError) as e:
            raise PhysicsCacheError(f"{path}: cannot read a physics cache ({e})") from None
        ends = np.cumsum(a["count"])
        if len(ends) and ends[-1] != len(a["grasp_id"]) or len(header["records"]) != len(a["count"]):
            raise PhysicsCacheError(f"{path}: the cache's arrays disagree in length")
        cache = cls(header["key"])
        for i, (name, pose_id) in enumerate(zip(a["object_name"], a["pose_id"], strict=True)):
            s = slice(ends[i] - a["count"][i], ends[i])
            t = PoseTrials(
                a["grasp_id"][s].astype(np.int64), a["tcp"][s], a["held"][s], a["run"][s], header["records"][i]
            )
            cache.objects.setdefault(str(name), {})[int(pose_id)] = t
        return cache


def _as_fraction(rate: float, max_den: int) -> tuple[int, int]:
    """(held, run) with held / run == ``rate`` (a float32 success rate of at most ``max_den`` trials)."""
    f = Fraction(float(rate)).limit_denominator(max_den)
    return f.numerator, f.denominator


def from_dataset(root: str | Path, verify: bool = True) -> PhysicsCache:
    """The trials recorded in the physics-labelled grasp dataset at ``root`` (done objects only)."""
    from .config import DatagenConfig, recorded_config
    from .storage import DatasetError, open_dataset, read_shard

    ds = open_dataset(root, verify=verify)
    m = ds.manifest
    cfg = DatagenConfig.from_dict(recorded_config(m["config"])).to_dict()
    if cfg.get("label", {}).get("kind") != "physics":
        raise DatasetError(
            f"{root}: its label is {cfg.get('label', {}).get('kind')!r}, not physics: no trials to cache"
        )
    trials = int(cfg["label"]["trials"])
    intr = Intrinsics.from_dict(m["intrinsics"])
    cache = PhysicsCache(config_key(cfg))
    for entry in ds.shard_entries:  # the depth images are not needed: left compressed
        img, g = read_shard(ds.root / entry["file"], entry.get("sha256") if verify else None, skip=("depth",))
        obj = m["objects"][int(entry["object_id"])]
        records = obj.get("physics", [])
        pose_of_row = img["stable_pose_id"][g["image_index"]]
        cam_p = deproject(np.stack([g["u"], g["v"], g["z"]], axis=1), intr)
        T_wc = img["T_world_camera"][g["image_index"]]
        tcp = np.einsum("nij,nj->ni", T_wc[:, :3, :3], cam_p) + T_wc[:, :3, 3]
        poses = {}
        for pose_id in np.unique(pose_of_row):
            rows = np.flatnonzero(pose_of_row == pose_id)
            gid, first = np.unique(g["grasp_id"][rows], return_index=True)
            r = rows[first]
            free = g["collision_free"][r]
            frac = [_as_fraction(x, trials) if f else (0, 0) for x, f in zip(g["success_rate"][r], free, strict=True)]
            held, run = (np.array(c, np.uint8).reshape(-1) for c in zip(*frac, strict=True)) if frac else ([], [])
            record = records[int(pose_id)] if int(pose_id) < len(records) else {}
            poses[int(pose_id)] = PoseTrials(gid.astype(np.int64), tcp[r].astype(np.float16), held, run, record)
        cache.objects[obj["name"]] = poses
    return cache
