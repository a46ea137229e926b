"""Table plane by RANSAC; the swept gripper collides with the table and with observed points."""

import numpy as np

from planning.collision import GripperCollision, fit_table, voxel_downsample
from vgq.gripper import GripperGeometry


def _plane_points(rng, n=4000):
    """A tilted table 0.7 m away (normal towards the camera) plus 20% clutter above it."""
    normal = np.array([0.0, -np.sin(0.5), -np.cos(0.5)])
    u = np.cross(normal, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    centre = np.array([0.0, 0.0, 0.7])
    a, b = rng.uniform(-0.3, 0.3, (2, n))
    pts = centre + a[:, None] * u + b[:, None] * v + 0.0005 * rng.standard_normal((n, 1)) * normal
    clutter = centre + rng.uniform(-0.05, 0.05, (n // 4, 3)) + 0.06 * normal
    return np.vstack([pts, clutter]), normal, centre


def test_ransac_finds_the_table_under_clutter():
    rng = np.random.default_rng(0)
    pts, normal, centre = _plane_points(rng)
    table = fit_table(pts, rng)
    assert table is not None
    assert table.normal @ normal > 0.999  # oriented towards the camera
    assert abs(table.height(centre)) < 1e-3
    assert 0.75 <= table.inlier_fraction <= 0.85
    assert table.height(np.zeros(3)) > 0  # the camera is above the table


def _frame(tcp, approach, axis):
    z = np.asarray(approach, float) / np.linalg.norm(approach)
    x = np.asarray(axis, float) - (np.asarray(axis, float) @ z) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, tcp
    return T


def test_a_grasp_through_the_table_collides_and_one_above_it_does_not():
    rng = np.random.default_rng(1)
    pts, normal, centre = _plane_points(rng)
    table = fit_table(pts, rng)
    checker = GripperCollision(GripperGeometry(), table, np.zeros((0, 3)))
    down = -normal
    above = _frame(centre + 0.02 * normal, down, [1.0, 0, 0])  # fingertips 1 cm above the table
    through = _frame(centre + 0.005 * normal, down, [1.0, 0, 0])  # fingertips 5 mm into it
    # a side grasp with a vertical jaw axis 2 cm up: the lower finger is 2.5 to 3.5 cm below the TCP
    sideways = _frame(centre + 0.02 * normal, np.cross(normal, [1.0, 0, 0]), normal)
    assert checker.collides(np.stack([above, through, sideways])).tolist() == [False, True, True]


def test_fingertips_must_keep_the_table_margin():
    """Fingertips 3 mm above the table: free with no margin, a collision with the planner's
    default 5 mm (execution error would put them into the table)."""
    from planning.types import PlanParams

    rng = np.random.default_rng(1)
    pts, normal, centre = _plane_points(rng)
    table = fit_table(pts, rng)
    g = GripperGeometry()
    low = _frame(centre + (g.tip_offset + 0.003) * normal, -normal, [1.0, 0, 0])
    high = _frame(centre + (g.tip_offset + 0.008) * normal, -normal, [1.0, 0, 0])
    frames = np.stack([low, high])
    assert GripperCollision(g, table, np.zeros((0, 3))).collides(frames).tolist() == [False, False]
    margin = PlanParams().table_margin
    assert 0.003 < margin < 0.008
    assert GripperCollision(g, table, np.zeros((0, 3)), margin).collides(frames).tolist() == [True, False]


def test_a_grasp_whose_finger_holds_an_observed_point_collides():
    tcp = np.array([0.0, 0.0, 0.6])
    T = _frame(tcp, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    g = GripperGeometry()
    between = tcp + [0.02, 0.0, 0.0]  # between the jaws (the object): no collision
    in_finger = tcp + [g.max_width / 2 + g.finger_depth / 2, 0.0, -0.02]
    behind_palm = tcp + [0.0, 0.0, -0.12]  # in the swept approach behind the palm
    beside = tcp + [0.0, 0.05, 0.0]
    results = [
        GripperCollision(g, None, np.array([p])).collides(T[None])[0] for p in (between, in_finger, behind_palm, beside)
    ]
    assert results == [False, True, True, False]


def test_the_fast_point_test_matches_a_plain_box_test():
    from vgq.gripper import gripper_boxes

    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.15, 0.15, (40, 3))
    frames = np.stack(
        [_frame(rng.uniform(-0.05, 0.05, 3), rng.standard_normal(3), rng.standard_normal(3)) for _ in range(300)]
    )
    fast = GripperCollision(GripperGeometry(), None, pts, point_clearance=0.0).collides(frames)
    c, h = gripper_boxes(GripperGeometry(), swept=True)
    local = np.einsum("fji,fmj->fmi", frames[:, :3, :3], pts[None] - frames[:, None, :3, 3])
    plain = np.zeros(len(frames), bool)
    for cc, hh in zip(c, h):
        plain |= np.all(np.abs(local - cc) < hh, axis=2).any(axis=1)
    assert 0.1 < plain.mean() < 0.9
    assert np.array_equal(fast, plain)


def test_voxel_downsample_keeps_one_point_per_cube():
    pts = np.array([[0.0, 0, 0], [0.001, 0.001, 0.001], [0.01, 0, 0], [0.0101, 0.0, 0.0]])
    assert len(voxel_downsample(pts, 0.004)) == 2


def test_collisions_say_whether_the_table_or_a_point_was_hit():
    """A frame into the table counts for the table only; one whose finger holds a point, for the points."""
    rng = np.random.default_rng(1)
    pts, normal, centre = _plane_points(rng)
    table = fit_table(pts, rng)
    g = GripperGeometry()
    high = _frame(centre + 0.03 * normal, -normal, [1.0, 0, 0])
    low = _frame(centre + 0.005 * normal, -normal, [1.0, 0, 0])  # fingertips 5 mm into the table
    in_finger = high[:3, 3] + high[:3, :3] @ [g.max_width / 2 + g.finger_depth / 2, 0.0, -0.02]
    checker = GripperCollision(g, table, np.array([in_finger, in_finger - 0.03 * normal]))
    frames = np.stack([high, low, _frame(centre + 0.08 * normal, -normal, [1.0, 0, 0])])
    t, p = checker.collisions(frames)
    assert t.tolist() == [False, True, False] and p.tolist() == [True, False, False]
    assert checker.collides(frames).tolist() == (t | p).tolist()
