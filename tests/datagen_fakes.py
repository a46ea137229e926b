"""Small synthetic grasp datasets in the vgq-grasps format (for datagen's storage, sampling
and crop tests; no mesh processing involved)."""

from __future__ import annotations

import numpy as np

from datagen import storage
from vgq.pose import canonical_quaternion


def fake_object(
    rng: np.random.Generator, object_id: int, n_images: int = 3, n_grasps: int = 40, positive_rate: float = 0.3
):
    """Image and grasp arrays of one object with plausible values (metres, radians)."""
    depth = np.full((n_images, 300, 300), 0.7, np.float32)
    depth[:, 100:200, 120:180] -= rng.uniform(0.02, 0.08, (n_images, 1, 1)).astype(np.float32)
    depth += rng.uniform(0, 1e-3, depth.shape).astype(np.float32)
    images = {
        "depth": depth,
        "object_id": np.full(n_images, object_id, np.int32),
        "stable_pose_id": np.zeros(n_images, np.int32),
        "camera_d": rng.uniform(0.4, 1.1, n_images).astype(np.float32),
        "camera_phi": rng.uniform(0, np.radians(70), n_images).astype(np.float32),
        "camera_theta": rng.uniform(0, 2 * np.pi, n_images).astype(np.float32),
        "T_world_camera": np.tile(np.eye(4), (n_images, 1, 1)),
    }
    q = canonical_quaternion(rng.standard_normal((n_grasps, 4))).astype(np.float32)
    quality = np.where(
        rng.random(n_grasps) < positive_rate, rng.uniform(0.0021, 0.01, n_grasps), rng.uniform(0, 0.0019, n_grasps)
    )
    grasps = {
        "image_index": rng.integers(0, n_images, n_grasps).astype(np.int32),
        "grasp_id": np.arange(n_grasps, dtype=np.int32),
        "u": rng.uniform(0, 299, n_grasps).astype(np.float32),
        "v": rng.uniform(0, 299, n_grasps).astype(np.float32),
        "z": rng.uniform(0.4, 1.1, n_grasps).astype(np.float32),
        "q": q,
        "beta": rng.uniform(0, np.pi / 2, n_grasps).astype(np.float32),
        "psi": rng.uniform(0, np.pi, n_grasps).astype(np.float32),
        "omega": rng.uniform(0, 2 * np.pi, n_grasps).astype(np.float32),
        "jaw_angle": rng.uniform(-np.pi, np.pi, n_grasps).astype(np.float32),
        "quality": quality.astype(np.float32),
        "collision_free": rng.random(n_grasps) < 0.8,
    }
    return images, grasps


def fake_dataset(root, n_objects: int = 4, seed: int = 0, **kw):
    """Write a complete vgq-grasps dataset of ``n_objects`` fake objects; return the manifest."""
    rng = np.random.default_rng(seed)
    objects = [{"object_id": i, "name": f"fake{i:03d}", "source": "synthetic"} for i in range(n_objects)]
    m = storage.new_grasp_manifest({"intrinsics": None}, seed, objects, 0.002)
    for i in range(n_objects):
        images, grasps = fake_object(rng, i, **kw)
        storage.record_shard(m, storage.write_shard(root, i, images, grasps, 0.002))
        storage.write_manifest(root, m)
    m["complete"] = True
    storage.write_manifest(root, m)
    return m


def grasp_frame(center, x, z) -> np.ndarray:
    """Grasp frame (4, 4) with jaw axis ``x`` and approach ``z`` (orthonormalised), origin ``center`` (m)."""
    x = np.asarray(x, float) / np.linalg.norm(x)
    z = np.asarray(z, float) - np.dot(z, x) * x
    z /= np.linalg.norm(z)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, center
    return T
