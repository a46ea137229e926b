"""Benchmark scenes: one of the recipe's held-out objects on a stable pose (drawn by its
probability) under a camera drawn from the recipe's ranges, rendered by datagen; the objects
of a held-out crop file, a crop dataset's split, or objects the model's dataset never held."""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np

HELDOUT = "examples/heldout_test_crops.npz"


def recipe_config(model):
    from datagen.config import DatagenConfig, recorded_config

    try:  # upgraded like a dataset manifest's: a recipe recorded before the label setting had the paper's
        return DatagenConfig.from_dict(recorded_config(model.card.dataset["source"]["config"]))
    except Exception:  # an older card without the full config: the defaults are the recipe's
        return DatagenConfig()


def heldout_object_ids(path: str = HELDOUT, split: str = "test") -> list[int]:
    """Test object ids: those of a held-out crop file (.npz with ``object_id``), or the ``split``
    (test by default; train or val to fit something on other objects) of a crop dataset folder
    (e.g. data/v2/crops, whose ids index the recipe's objects, families included)."""
    p = Path(path)
    if p.is_dir():
        from vgq.schema import CROP_FORMAT, read_manifest

        ids = read_manifest(p, CROP_FORMAT)["counts"].get(split, {}).get("objects") or []
        if not ids:
            raise ValueError(f"{p}: its manifest lists no {split} objects")
        return sorted(int(i) for i in ids)
    return sorted(int(i) for i in np.unique(np.load(p)["object_id"]))


UNSEEN = "unseen"  # --heldout: objects outside the model's dataset


def unseen_config(config):
    """The recipe's config with objects outside its dataset: every mesh of its source (the recipe
    takes the first ``num_objects``) and each family's objects drawn with another seed."""
    return dataclasses.replace(config, num_objects=None, seed=config.seed + 1)


def scene_objects(heldout: str, split: str, config) -> tuple[list[int], object]:
    """(object ids, the config whose sources they index) of a benchmark's scenes: ``heldout``
    a held-out crop file or dataset folder (:func:`heldout_object_ids`, the recipe's objects),
    or ``unseen``: objects the model's dataset never held (:func:`unseen_config`; the mesh
    source's meshes past the recipe's and newly drawn family objects), to fit the planner's
    ranker and calibration on objects as new to the model as a user's."""
    if heldout != UNSEEN:
        return heldout_object_ids(heldout, split), config
    cfg = unseen_config(config)
    sources = recipe_sources(json.dumps(cfg.to_dict(), sort_keys=True))
    n = config.num_objects
    ids = [i for i, src in enumerate(sources) if src.family is not None or (n is not None and i >= n)]
    if not ids:
        raise ValueError("the recipe's config leaves no object outside its dataset")
    return ids, cfg


@dataclasses.dataclass
class BenchScene:
    object_id: int
    mesh_object: object  # trimesh, object frame (centre of mass at the origin)
    mesh_world: object
    T_world_object: np.ndarray
    T_world_camera: np.ndarray
    depth: np.ndarray
    torque_scaling: float


@functools.lru_cache(maxsize=4)
def recipe_sources(config_json: str) -> list:
    """The recipe's mesh sources (families included; drawing their parameters takes seconds)."""
    from datagen.config import DatagenConfig
    from datagen.pipeline import run_sources

    return run_sources(DatagenConfig.from_dict(json.loads(config_json)))


def make_scene(object_id: int, config, rng: np.random.Generator) -> BenchScene:
    """One held-out object on a stable pose (drawn by probability), seen by a recipe camera."""
    from datagen.camera import sample_cameras
    from datagen.mesh import load_object, stable_poses
    from datagen.quality import resolve_torque_scaling
    from datagen.render import render_depth

    sources = recipe_sources(json.dumps(config.to_dict(), sort_keys=True))
    obj = load_object(sources[object_id], config.mesh)  # the recipe's objects, families included
    T_poses, probs = stable_poses(obj, config.stable_pose_min_probability, config.max_stable_poses)
    T_wo = T_poses[rng.choice(len(probs), p=probs / probs.sum())]
    mesh_world = obj.mesh.copy()
    mesh_world.apply_transform(T_wo)
    T_wc = sample_cameras(1, config.camera, rng).T_world_camera[0]
    depth = render_depth(mesh_world, T_wc, config.intrinsics)
    return BenchScene(
        object_id, obj.mesh, mesh_world, T_wo, T_wc, depth, resolve_torque_scaling(obj.mesh, config.quality)
    )
