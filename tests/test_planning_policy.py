"""plan(): scored, distinct, ROI-bound grasps in the service's row convention; bad input
raises PlanningError naming it; nothing to grasp gives an empty answer with a reason."""

import numpy as np
import pytest

pytest.importorskip("trimesh")

from planning.policy import frame_from_row, nms, plan
from planning.types import PlanningError, PlanParams
from service.runtime import FastModel
from tests.planning_scenes import boxes_scene
from vgq.camera import DEFAULT_INTRINSICS, Intrinsics, project
from vgq.pose import canonical_quaternion

MODEL_DIR = "models/fast-vgqcnn-default"
FAST = PlanParams(num_candidates=96)


@pytest.fixture(scope="module")
def model():
    return FastModel(MODEL_DIR, threads=1, head_precision="fp32")


@pytest.fixture(scope="module")
def two_boxes():
    return boxes_scene(extents=((0.03, 0.04, 0.05), (0.035, 0.03, 0.04)), at=((-0.07, 0.0), (0.07, 0.02)))


def test_plan_returns_k_distinct_scored_grasps_in_the_service_row_convention(model, two_boxes):
    depth, _, _ = two_boxes
    res = plan(depth, DEFAULT_INTRINSICS, model, k=5, seed=0, params=FAST)
    assert res.reason is None and len(res.grasps) == 5
    assert all(0 <= g.score <= 1 for g in res.grasps)
    assert res.ranked_by == "ranker"  # the bundled model's planner ranker orders them (tests/test_planning_ranker.py)
    cand = res.candidates
    kept = [int(np.flatnonzero(np.all(np.isclose(cand["frames"], g.pose), axis=(1, 2)))[0]) for g in res.grasps]
    utility = cand["utility"][kept]
    assert list(utility) == sorted(utility, reverse=True) and utility[0] == cand["utility"].max()
    for g in res.grasps:
        row = g.row
        assert row.shape == (7,) and np.allclose(row[3:], canonical_quaternion(row[3:])) and row[3] >= 0
        T = frame_from_row(row, DEFAULT_INTRINSICS)  # row -> pose
        assert np.allclose(T, g.pose, atol=1e-9)
        uvz = project(g.pose[None, :3, 3], DEFAULT_INTRINSICS)[0]  # pose -> row
        assert np.allclose(uvz, row[:3])
        assert np.allclose(g.pose[:3, 3], np.mean(g.contacts, axis=0))  # TCP midway
        x = g.contacts[1] - g.contacts[0]
        assert np.allclose(g.pose[:3, 0], x / np.linalg.norm(x))  # x = jaw axis
        assert np.isclose(g.width, np.linalg.norm(x), atol=1e-9)
        assert g.pose[2, 2] > 0  # approaches from the camera side
        assert g.ood_flags == 0 and g.ood == ()
    d = res.to_dict()
    assert len(d["grasps"]) == 5 and d["counts"]["collision_free"] == 96


def test_nms_keeps_only_distinct_grasps():
    def frame(c, a):
        T = np.eye(4)
        T[:3, 0] = a / np.linalg.norm(a)
        T[:3, 3] = c
        return T

    frames = np.stack(
        [
            frame([0, 0, 0.6], np.array([1.0, 0, 0])),
            frame([0.003, 0, 0.6], np.array([1.0, 0.1, 0])),  # same place, same axis: suppressed
            frame([0.003, 0, 0.6], np.array([0.0, 1.0, 0])),  # same place, crossed axis: kept
            frame([0.05, 0, 0.6], np.array([1.0, 0, 0])),  # elsewhere: kept
            frame([0.0, 0, 0.6], np.array([-1.0, 0, 0])),  # reversed axis is the same line: suppressed
        ]
    )
    scores = np.array([0.9, 0.95, 0.5, 0.4, 0.3])
    assert nms(frames, scores, 10, 0.01, np.radians(30)).tolist() == [1, 2, 3]
    assert nms(frames, scores, 2, 0.01, np.radians(30)).tolist() == [1, 2]


@pytest.mark.parametrize("k", [2, 5, 20])
def test_nms_is_the_greedy_suppression_over_many_near_duplicates(k):
    # the 100 best grasps are one grasp (within 2 mm, one axis): the rest are spread over a
    # 10 cm cube with axes near x or y, many of them duplicates of a better one
    rng = np.random.default_rng(k)
    frames = np.tile(np.eye(4), (600, 1, 1))
    frames[:, :3, 3] = rng.uniform(0, 0.1, (600, 3))
    frames[:100, :3, 3] = rng.uniform(0, 0.002, (100, 3))
    axes = np.where(rng.random((600, 1)) < 0.5, [1.0, 0, 0], [0, 1.0, 0]) + rng.normal(0, 0.1, (600, 3))
    axes[:100] = [1.0, 0, 0]
    frames[:, :3, 0] = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    scores = rng.random(600) + (np.arange(600) < 100)
    kept = []
    for i in np.argsort(-scores, kind="stable"):  # the rule, one candidate at a time
        c, a = frames[i, :3, 3], frames[i, :3, 0]
        if not any(
            np.linalg.norm(frames[j, :3, 3] - c) < 0.01 and abs(frames[j, :3, 0] @ a) > np.cos(np.radians(30))
            for j in kept
        ):
            kept.append(int(i))
        if len(kept) == k:
            break
    assert len(kept) == k and kept[0] < 100 and all(i >= 100 for i in kept[1:])
    assert nms(frames, scores, k, 0.01, np.radians(30)).tolist() == kept


def test_roi_restricts_the_grasps_to_the_boxed_object(model, two_boxes):
    depth, T_wc, meshes = two_boxes
    # the image box around the second object's projection
    v = meshes[1].vertices @ np.linalg.inv(T_wc)[:3, :3].T + np.linalg.inv(T_wc)[:3, 3]
    uv = project(v, DEFAULT_INTRINSICS)[:, :2]
    (u0, v0), (u1, v1) = uv.min(axis=0) - 3, uv.max(axis=0) + 3
    res = plan(depth, DEFAULT_INTRINSICS, model, k=5, roi=(u0, v0, u1, v1), seed=0, params=FAST)
    assert len(res.grasps) >= 1
    for g in res.grasps:
        c0 = project(g.contacts[:1], DEFAULT_INTRINSICS)[0]
        assert u0 <= c0[0] <= u1 and v0 <= c0[1] <= v1
    # without the ROI the first object is grasped too
    everywhere = plan(depth, DEFAULT_INTRINSICS, model, k=20, seed=0, params=FAST)
    us = [project(g.contacts[:1], DEFAULT_INTRINSICS)[0, 0] for g in everywhere.grasps]
    assert min(us) < u0 - 10 or max(us) > u1 + 10


def test_another_camera_gets_grasps_in_its_own_pixels(model, two_boxes):
    depth, _, _ = two_boxes
    from PIL import Image

    # the same view at 0.8 x the focal length: a 240 px image
    cam = Intrinsics(fx=420.0, fy=420.0, cx=119.5, cy=119.5, width=240, height=240)
    small = np.asarray(Image.fromarray(depth).resize((240, 240), Image.Resampling.NEAREST))
    res = plan(small, cam, model, k=3, seed=0, params=FAST)
    assert len(res.grasps) == 3
    for g in res.grasps:
        assert np.allclose(project(g.pose[None, :3, 3], cam)[0, :2], [g.u, g.v], atol=1e-6)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"depth": np.zeros((300, 300), np.float32)}, "depth"),
        ({"depth": np.full((300, 300), np.nan, np.float32)}, "depth"),
        ({"depth": np.ones((300, 300, 2), np.float32)}, "depth"),
        ({"depth": np.ones((200, 300), np.float32)}, "intrinsics"),
        ({"k": 0}, "k"),
        ({"k": 101}, "k"),
        ({"k": 2.5}, "k"),
        ({"roi": (400, 400, 500, 500)}, "roi"),
        ({"roi": (50, 50, 10, 10)}, "roi"),
        ({"roi": np.zeros((300, 300), bool)}, "roi"),
        ({"roi": (1, 2, 3)}, "roi"),
        ({"seed": -1}, "seed"),
    ],
)
def test_bad_input_names_the_field(model, two_boxes, kwargs, field):
    args = {"depth": two_boxes[0], "k": 5, "roi": None, "seed": 0, **kwargs}
    with pytest.raises(PlanningError) as e:
        plan(args["depth"], DEFAULT_INTRINSICS, model, k=args["k"], roi=args["roi"], seed=args["seed"], params=FAST)
    assert e.value.field == field and str(e.value)


def test_nothing_to_grasp_gives_no_grasps_and_a_reason(model):
    from datagen.camera import look_at_table_origin
    from datagen.render import render_depth

    table = render_depth(None, look_at_table_origin(0.6, 0.3, 0.2)[0], DEFAULT_INTRINSICS)
    res = plan(table, DEFAULT_INTRINSICS, model, k=5, seed=0, params=FAST)
    assert res.grasps == () and "no object" in res.reason
    assert res.to_dict()["grasps"] == []


def test_the_same_seed_plans_the_same_grasps(model, two_boxes):
    depth, _, _ = two_boxes
    a = plan(depth, DEFAULT_INTRINSICS, model, k=3, seed=7, params=FAST)
    b = plan(depth, DEFAULT_INTRINSICS, model, k=3, seed=7, params=FAST)
    c = plan(depth, DEFAULT_INTRINSICS, model, k=3, seed=8, params=FAST)
    assert [g.row.tolist() for g in a.grasps] == [g.row.tolist() for g in b.grasps]
    assert [g.row.tolist() for g in a.grasps] != [g.row.tolist() for g in c.grasps]


def test_cem_adds_collision_free_rotations_and_never_lowers_the_best_score(model, two_boxes):
    import dataclasses

    depth, _, _ = two_boxes
    plain = plan(depth, DEFAULT_INTRINSICS, model, k=1, seed=3, params=FAST)
    cem = plan(depth, DEFAULT_INTRINSICS, model, k=1, seed=3, params=dataclasses.replace(FAST, cem_iterations=2))
    assert cem.counts["after_cem"] > cem.counts["collision_free"]
    assert cem.grasps[0].score >= plain.grasps[0].score


def test_every_candidate_keeps_the_head_pose_it_was_scored_with(model, two_boxes):
    """candidates["poses"]: what a pose-only ranking (planning.bench --baseline) reads (its first 7
    columns; a placement head's rows go on with each candidate's placement row). CEM grasps too."""
    import dataclasses

    from planning.policy import grasp_rows

    depth, _, _ = two_boxes
    res = plan(depth, DEFAULT_INTRINSICS, model, k=1, seed=3, params=dataclasses.replace(FAST, cem_iterations=2))
    c = res.candidates
    assert c["poses"].shape == (len(c["scores"]), model.n_pose) == (len(c["frames"]), model.n_pose)
    rows = grasp_rows(c["frames"], DEFAULT_INTRINSICS)
    assert np.allclose(c["poses"][:, 2:7], rows[:, 2:], atol=1e-6)  # z, quaternion as given
    kappa = model.geometry.kappa_px
    assert np.abs(c["poses"][:, :2]).max() <= kappa / model.geometry.scale + 1e-3  # crop px from the window centre
    # planning.features reads the rest: each candidate's width and seen flag, and the scene estimate
    assert c["widths"].shape == c["seen"].shape == (len(c["frames"]),) and c["scene"].table is not None
    assert np.allclose(c["widths"], np.linalg.norm(c["contacts"][:, 1] - c["contacts"][:, 0], axis=1))


def test_missing_depth_is_filled_before_the_encoder_as_in_training(two_boxes):
    """A depth image with holes (0 = no reading, as real cameras send) reaches the encoder
    filled by vgq.inpaint, the crop stage's and the service's fill: never a 0."""
    depth, _, _ = two_boxes
    holed = depth.copy()
    for v in range(20, holed.shape[0] - 20, 40):  # 10 x 10 px holes all over (dropout blobs)
        for u in range(20, holed.shape[1] - 20, 40):
            holed[v : v + 10, u : u + 10] = 0.0
    m = FastModel(MODEL_DIR, threads=1, head_precision="fp32")
    seen = []
    run = m.encoder.run

    class Spy:
        def run(self, names, feeds):
            seen.append(next(iter(feeds.values())))
            return run(names, feeds)

    m.encoder = Spy()
    res = plan(holed, DEFAULT_INTRINSICS, m, k=3, seed=0, params=FAST)
    assert len(res.grasps) > 0 and seen
    assert all(np.all(x > 0) for x in seen)


def test_an_object_too_low_to_grasp_from_above_names_the_table(model):
    """A 1.3 cm tall block: every grasp across it puts the fingertips within the table margin."""
    depth = boxes_scene(extents=((0.02, 0.02, 0.013),))[0]
    res = plan(depth, DEFAULT_INTRINSICS, model, k=5, seed=0)
    assert res.grasps == () and res.counts["point_collisions"] == 0
    assert res.counts["table_collisions"] == res.counts["checked"] > 0
    assert "collides with the table: the fingertips would come within 5 mm of the table" in res.reason


@pytest.mark.parametrize(
    "table,points,says",
    [
        (0, 7, "collides with the observed points"),
        (3, 4, "collides: 3 with the table (the fingertips would come within 5 mm of the table), 4 with the observed"),
    ],
)
def test_the_collision_reason_names_what_was_hit(table, points, says):
    from planning.policy import collision_reason

    assert says in collision_reason({"table_collisions": table, "point_collisions": points}, PlanParams())


def _greedy_cover(uv, geom):
    """The cover as specified, written plainly: of the windows centred on each grasp or on it
    shifted by kappa / 2 diagonally (snapped to the pixel grid), take the one holding the most
    grasps not yet covered (ties: the lowest (u, v)), until every grasp is covered."""
    from vgq.crop import window_center, window_origin

    k = geom.kappa_px
    shifts = np.array([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]]) * (k / 2)
    cand = sorted(
        {tuple(window_center(window_origin(np.asarray(g + s)[None], geom), geom)[0]) for g in uv for s in shifts}
    )
    out, left = np.zeros_like(uv), set(range(len(uv)))
    while left:
        holds = [[i for i in left if max(abs(c[0] - uv[i, 0]), abs(c[1] - uv[i, 1])) <= k + 1e-9] for c in cand]
        best = max(range(len(cand)), key=lambda j: (len(holds[j]), -j))
        for i in holds[best]:
            out[i] = cand[best]
        left -= set(holds[best])
    return out


@pytest.mark.parametrize("n", [0, 1, 7, 60])
def test_the_window_cover_is_the_greedy_cover_and_holds_every_grasp(model, n):
    from planning.policy import cover_windows

    rng = np.random.default_rng(n)
    uv = rng.uniform(-20, 320, (n, 2))
    uv[::2] = np.round(uv[::2] * 2) / 2  # pixel and half-pixel positions: the window edges
    got = cover_windows(uv, model.geometry)
    assert np.all(np.abs(got - uv) <= model.geometry.kappa_px + 1e-9)
    assert np.array_equal(got, _greedy_cover(uv, model.geometry))
