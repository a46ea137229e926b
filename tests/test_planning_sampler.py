"""The depth-image sampler finds antipodal contact pairs on a rendered box."""

import numpy as np
import pytest

pytest.importorskip("trimesh")

from planning.sampler import analyse_scene, collision_checker, sample_contact_pairs, sample_grasps
from planning.types import PlanParams
from tests.planning_scenes import boxes_scene, mesh_scene, open_box
from vgq.camera import DEFAULT_INTRINSICS


@pytest.fixture(scope="module")
def box():
    return boxes_scene(extents=((0.03, 0.04, 0.05),))


def _world(T_wc, x):
    return x @ T_wc[:3, :3].T + T_wc[:3, 3]


def test_contact_pairs_on_a_box_are_antipodal_across_its_faces(box):
    depth, T_wc, _ = box
    params = PlanParams()
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, params, np.random.default_rng(0))
    assert scene.table is not None and scene.objects.sum() > 300
    contacts, axes, widths, _ = sample_contact_pairs(scene, 800, params, np.random.default_rng(1))
    assert len(axes) >= 50
    a = axes @ T_wc[:3, :3].T  # world frame
    cos_cone = np.cos(np.arctan(params.friction_coef))
    # across a pair of opposite vertical faces: the axis is within the friction cone of x or y
    # (seeds on a vertical edge get a blend of two faces' normals: a few per cent miss)
    across_x = np.abs(a[:, 0]) >= cos_cone
    across_y = np.abs(a[:, 1]) >= cos_cone
    assert np.mean(across_x | across_y) >= 0.9
    # contact 0 lies on a face the camera sees; contact 1 may lie on a hidden face, which the
    # height-field reading places at the edge of the box's shadow: at most the shadow's
    # length (height x tan(phi)) beyond it
    c0 = _world(T_wc, contacts[:, 0])
    assert np.all(np.abs(c0[:, 0]) <= 0.015 + 0.002) and np.all(np.abs(c0[:, 1]) <= 0.02 + 0.002)
    assert np.all((c0[:, 2] >= 0.0) & (c0[:, 2] <= 0.05 + 0.002))
    c1 = _world(T_wc, contacts[:, 1])
    shadow = 0.05 * np.tan(0.35) + 0.003
    assert np.all(np.abs(c1[:, 0]) <= 0.015 + shadow) and np.all(np.abs(c1[:, 1]) <= 0.02 + shadow)
    # widths: mostly at least the box's (3 cm across x, 4 cm across y; a line near a vertical
    # edge may leave through the neighbouring face), at most the opening
    assert np.median(widths[across_x]) >= 0.03 - 0.003 and np.median(widths[across_y]) >= 0.04 - 0.003
    assert np.all(widths <= params.max_opening)


def test_sampled_grasps_are_collision_free_frames_with_the_tcp_between_the_contacts(box):
    depth, T_wc, _ = box
    params = PlanParams(num_candidates=64)
    rng = np.random.default_rng(2)
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, params, rng)
    checker = collision_checker(scene, params, rng)
    cands, counts = sample_grasps(scene, params, rng, checker)
    assert len(cands) == 64 and counts["checked"] >= 64
    R = cands.frames[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(cands.frames[:, :3, 3], cands.contacts.mean(axis=1))
    x = cands.contacts[:, 1] - cands.contacts[:, 0]
    assert np.allclose(x / np.linalg.norm(x, axis=1, keepdims=True), R[:, :, 0], atol=1e-9)
    assert not checker.collides(cands.frames).any()
    # approach from above the table (beta < 90 deg) and from the camera side (psi < 90 deg)
    z_world = R[:, :, 2] @ T_wc[:3, :3].T
    assert np.all(z_world[:, 2] < 0) and np.all(R[:, 2, 2] > 0)


def _horizontal_pair_widths(depth, T_wc, params):
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, params, np.random.default_rng(0))
    contacts, axes, widths, _ = sample_contact_pairs(scene, 2000, params, np.random.default_rng(1))
    return contacts, widths[np.abs((axes @ T_wc[:3, :3].T)[:, 2]) < 0.3]


def test_the_top_view_ends_a_line_into_an_open_container_at_its_inner_wall():
    # an 8 x 8 x 5 cm box with 4 mm walls and no lid: the camera cannot see behind the near
    # wall, but from above the inside is floor, so a jaw line through the wall leaves it there
    depth, T_wc = mesh_scene(open_box(wall=0.004), phi=0.6)
    _, with_top = _horizontal_pair_widths(depth, T_wc, PlanParams())
    _, without = _horizontal_pair_widths(depth, T_wc, PlanParams(top_view_cell=None))
    assert len(with_top) >= 100 and np.mean(with_top <= 0.004 + 0.003) >= 0.95
    assert np.mean(without <= 0.004 + 0.003) <= 0.5  # the camera's height field alone: the wall reads far thicker


def test_the_top_view_puts_a_hidden_contact_at_the_far_face_not_the_shadows_end(box):
    depth, T_wc, _ = box
    contacts, _ = _horizontal_pair_widths(depth, T_wc, PlanParams())
    c1 = _world(T_wc, contacts[:, 1])
    beyond = np.maximum(np.abs(c1[:, 0]) - 0.015, np.abs(c1[:, 1]) - 0.02)  # outside the 3 x 4 cm footprint
    assert len(c1) >= 100 and np.median(beyond) <= 0.0015 and np.all(beyond <= 0.004)


def test_the_top_view_along_lines_reads_the_heights_it_reads_point_by_point(box):
    depth, _, _ = box
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, PlanParams(), np.random.default_rng(0))
    rng = np.random.default_rng(1)
    p = scene.points[scene.objects][rng.integers(0, scene.objects.sum(), 200)].astype(np.float64)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ts = 0.0015 * np.arange(1, 40)
    along = scene.top.top_along(p, axes, ts)
    pointwise = scene.top.top(p[:, None, :] + ts[None, :, None] * axes[:, None, :])
    assert np.isfinite(along).mean() > 0.3  # the lines cross the box's footprint and leave it
    assert np.array_equal(along, pointwise)


@pytest.mark.parametrize("n", [1, 3, 900, 70_000])
def test_region_max_is_ndimage_maximum(n):
    from scipy import ndimage

    from planning.sampler import region_max

    rng = np.random.default_rng(n)
    labels = np.r_[np.arange(1, n + 1), rng.integers(1, n + 1, 20_000)][rng.permutation(n + 20_000)]
    values = rng.normal(size=len(labels)).astype(np.float32)
    want = ndimage.maximum(values, labels, index=np.arange(1, n + 1))
    assert np.array_equal(region_max(values, labels, n), np.asarray(want, np.float64))
