"""Grasp pose vector layouts and the quaternion convention.

Quaternions are unit (w, x, y, z) and canonical: w >= 0 (q and -q are the same
rotation; for w == 0 the first non-zero of x, y, z is made positive). A grasp's
rotation maps gripper-frame vectors to camera-frame vectors; the gripper frame has
x along the jaw axis (contact to contact) and z along the approach direction.
"""

from __future__ import annotations

import numpy as np

#: Pose columns each architecture consumes, in order. (u, v) are crop-pixel offsets of
#: the grasp centre from the crop window centre (see ``vgq.crop``); z is the TCP depth in
#: the camera frame in metres; (qw, qx, qy, qz) the canonical unit quaternion.
POSE_COLUMNS: dict[str, tuple[str, ...]] = {
    "fast_vgqcnn": ("u", "v", "z", "qw", "qx", "qy", "qz"),
    "vgqcnn": ("z", "qw", "qx", "qy", "qz"),
    "gqcnn": ("z",),
}
#: The full per-grasp pose row stored in crop datasets; the architectures select from it.
FULL_POSE_COLUMNS: tuple[str, ...] = POSE_COLUMNS["fast_vgqcnn"]
QUATERNION_COLUMNS: frozenset[str] = frozenset({"qw", "qx", "qy", "qz"})


def pose_column_indices(arch: str) -> list[int]:
    """Indices into a ``FULL_POSE_COLUMNS`` row of the columns ``arch`` consumes."""
    if arch not in POSE_COLUMNS:
        raise ValueError(f"unknown architecture {arch!r}; expected one of {sorted(POSE_COLUMNS)}")
    return [FULL_POSE_COLUMNS.index(c) for c in POSE_COLUMNS[arch]]


class PoseError(ValueError):
    """Pose rows that cannot be used; ``indices``: the offending rows (the first
    ``MAX_LISTED``), so a caller can name them."""

    MAX_LISTED = 20

    def __init__(self, message: str, indices=()):
        super().__init__(message)
        self.indices = [int(i) for i in list(indices)[: self.MAX_LISTED]]


def largest_component(q: np.ndarray) -> np.ndarray:
    """(n,) largest |component| of each of (n, 4) quaternions (the scale that normalises them
    without overflow; below a tolerance: a zero quaternion)."""
    a = np.abs(q)
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), np.maximum(a[:, 2], a[:, 3]))


def canonical_quaternion(q: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Normalise (..., 4) quaternions (w, x, y, z) and flip their sign so w >= 0 (for
    |w| <= 1e-12 after normalising: the first non-zero of x, y, z positive).

    Raises PoseError (a ValueError) naming the rows with zero-norm or non-finite quaternions.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise PoseError(f"quaternions must have 4 components (w, x, y, z), got shape {q.shape}")
    flat = q.reshape(-1, 4)
    # whole-array checks first (row-wise reductions over 4 columns cost ~10 us each in numpy);
    # the offending rows are only looked for when a check fails
    if not np.isfinite(flat).all():
        bad = ~np.isfinite(flat).all(axis=1)
        raise PoseError(f"{int(bad.sum())} quaternions have non-finite components", np.flatnonzero(bad))
    m = largest_component(flat)
    if len(m) and m.min() < eps:
        bad = m < eps
        raise PoseError(f"{int(bad.sum())} quaternions have zero norm", np.flatnonzero(bad))
    return canonical_rows(flat, m).reshape(q.shape)


def canonical_rows(q: np.ndarray, largest: np.ndarray) -> np.ndarray:
    """:func:`canonical_quaternion` of (n, 4) finite quaternions whose ``largest_component``
    (n,) the caller has computed and checked (>= 1e-12): a new (n, 4) array, no checks."""
    u = q / largest[:, None]  # scale first: no overflow
    u /= np.sqrt(np.einsum("ij,ij->i", u, u))[:, None]
    tol = 1e-12
    flip = u[:, 0] < 0
    tiny = np.abs(u[:, 0]) <= tol  # rare: w ~ 0, the first non-zero of (x, y, z) decides
    if tiny.any():
        t = u[tiny]
        first = np.argmax(np.abs(t) > tol, axis=1)
        flip[tiny] = t[np.arange(len(t)), first] < 0
    return np.negative(u, out=u, where=flip[:, None])  # -u is exactly u * -1.0


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to canonical quaternions (..., 4) in (w, x, y, z)."""
    R = np.asarray(R, dtype=np.float64)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    m = [[R[:, i, j] for j in range(3)] for i in range(3)]
    tr = m[0][0] + m[1][1] + m[2][2]
    # Shepperd's method, vectorised: four candidate formulas, keep the best conditioned.
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = np.sqrt(np.maximum(1.0 + tr, 0)) * 2
        s1 = np.sqrt(np.maximum(1.0 + m[0][0] - m[1][1] - m[2][2], 0)) * 2
        s2 = np.sqrt(np.maximum(1.0 + m[1][1] - m[0][0] - m[2][2], 0)) * 2
        s3 = np.sqrt(np.maximum(1.0 + m[2][2] - m[0][0] - m[1][1], 0)) * 2
        c0 = np.stack([0.25 * s0, (m[2][1] - m[1][2]) / s0, (m[0][2] - m[2][0]) / s0, (m[1][0] - m[0][1]) / s0], -1)
        c1 = np.stack([(m[2][1] - m[1][2]) / s1, 0.25 * s1, (m[0][1] + m[1][0]) / s1, (m[0][2] + m[2][0]) / s1], -1)
        c2 = np.stack([(m[0][2] - m[2][0]) / s2, (m[0][1] + m[1][0]) / s2, 0.25 * s2, (m[1][2] + m[2][1]) / s2], -1)
        c3 = np.stack([(m[1][0] - m[0][1]) / s3, (m[0][2] + m[2][0]) / s3, (m[1][2] + m[2][1]) / s3, 0.25 * s3], -1)
    k = np.argmax(np.stack([tr, m[0][0], m[1][1], m[2][2]], axis=1), axis=1)
    q = np.choose(k[:, None], [c0, c1, c2, c3])
    return canonical_quaternion(q).reshape(*shape, 4)


def approach_angle(q: np.ndarray) -> np.ndarray:
    """(...,) angle psi (radians, 0..pi) between the approach axis (gripper z) and the camera's
    optical axis (camera z) for unit quaternions (..., 4) (w, x, y, z): cos psi = R[2, 2] =
    1 - 2 (x^2 + y^2). 0: approaching straight along the view direction; VG-dset keeps psi < 90 deg."""
    q = np.asarray(q, dtype=np.float64)
    return np.arccos(np.clip(1.0 - 2.0 * (q[..., 1] ** 2 + q[..., 2] ** 2), -1.0, 1.0))


def roll_quaternions(q: np.ndarray, roll: float) -> np.ndarray:
    """Orientations (..., 4) (w, x, y, z) given in a camera's frame, expressed in the frame of
    that camera rolled by ``roll`` radians about its optical axis (``vgq.camera.roll_matrix``):
    R' = R_z(roll)^T R, i.e. q' = (cos roll/2, 0, 0, -sin roll/2) q. Neither normalised nor made
    canonical: a zero or non-finite row stays one, for ``canonical_quaternion`` to name."""
    q = np.asarray(q, dtype=np.float64)
    w1, z1 = np.cos(roll / 2.0), -np.sin(roll / 2.0)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([w1 * w - z1 * z, w1 * x - z1 * y, w1 * y + z1 * x, w1 * z + z1 * w], -1)


def mirror_poses(poses: np.ndarray, pose_columns) -> np.ndarray:
    """Pose rows (k, len(pose_columns)) of the same grasps in the camera-frame mirror image
    x -> -x (the depth image and its crops flipped left to right: ``crop[..., ::-1]``): u -> -u,
    v and z unchanged, rotation R -> M R M with M = diag(-1, 1, 1) on both sides (the camera's x
    and the jaw axis reversed: the parallel-jaw gripper is symmetric under swapping its jaws), i.e.
    q = (w, x, y, z) -> (w, x, -y, -z), made canonical. A mirrored scene is as physical as the
    original (friction and gravity, up = -v, are mirror-symmetric), so its grasps keep their labels."""
    cols = tuple(pose_columns)
    out = np.array(poses, dtype=np.float64, copy=True)
    if out.ndim != 2 or out.shape[1] != len(cols):
        raise ValueError(f"pose rows must be (k, {len(cols)}) for columns {cols}, got {out.shape}")
    if "u" in cols:
        out[:, cols.index("u")] *= -1.0
    if QUATERNION_COLUMNS <= set(cols):
        qi = [cols.index(c) for c in ("qw", "qx", "qy", "qz")]
        q = out[:, qi] * np.array([1.0, 1.0, -1.0, -1.0])
        out[:, qi] = canonical_quaternion(q)
    return out


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) in (w, x, y, z) to rotation matrices (..., 3, 3)."""
    q = canonical_quaternion(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


#: what a network's pose stream (pc1) reads: "raw" the pose columns as they are (the paper's);
#: "rotation" the non-quaternion columns, then the 9 row-major entries of the grasp's rotation
#: matrix (computed inside the graphs, so clients still send (u, v, z, q))
POSE_FEATURES: tuple[str, ...] = ("raw", "rotation")


def pose_stream_features(poses: np.ndarray, pose_columns, kind: str = "raw") -> np.ndarray:
    """(k, n_features) the pose stream's input for (k, len(pose_columns)) raw pose rows (before
    the pose normalisation, which touches only the non-quaternion columns). Needs the quaternion
    as the last 4 columns for "rotation"; for unit quaternions (the service sends canonical ones)
    equal to what the graphs compute (``training.networks.rotation_entries``, no re-normalising)."""
    poses = np.asarray(poses, dtype=np.float64)
    if kind == "raw":
        return poses
    if kind != "rotation":
        raise ValueError(f"pose features must be one of {POSE_FEATURES}, got {kind!r}")
    if tuple(pose_columns[-4:]) != ("qw", "qx", "qy", "qz"):
        raise ValueError(f"pose features 'rotation' need (qw, qx, qy, qz) last; columns are {tuple(pose_columns)}")
    rot = matrix_from_quaternion(poses[:, -4:]).reshape(len(poses), 9)  # = the graphs' for unit q
    return np.concatenate([poses[:, :-4], rot], axis=1)
