"""datagen.physics: pybullet grasp trials (approach, close, lift, shake). World frame: table
z = 0, z up; metres."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from datagen_fakes import grasp_frame

from datagen.physics import GraspSimulator, PhysicsParams, execution_noise, perturbed_frames, run_trials

EX, EY, EZ = np.eye(3)


@pytest.fixture(scope="module")
def box_sim():
    """A 3 x 8 x 5 cm box standing on the table in a simulator."""
    sim = GraspSimulator()
    T = np.eye(4)
    T[2, 3] = 0.025
    info = sim.set_object(trimesh.creation.box(extents=[0.03, 0.08, 0.05]), T)
    yield sim, info
    sim.close()


def test_box_rests_stably_in_its_stable_pose(box_sim):
    _, info = box_sim
    assert info["stable"] and info["convex"] and info["parts"] == 1
    assert info["drift_m"] < 0.002


def test_top_grasp_across_the_short_side_of_a_box_holds_firmly(box_sim):
    sim, _ = box_sim
    reason, firm, touch = sim.trial(grasp_frame([0, 0, 0.03], EX, -EZ), 0.5)
    assert reason == "held" and firm
    # each pad touched its face of the box (object frame: faces at x = -+0.015)
    np.testing.assert_allclose(touch[:, 0], [-0.015, 0.015], atol=0.002)


def test_closing_on_air_fails(box_sim):
    sim, _ = box_sim
    reason, firm, touch = sim.trial(grasp_frame([0.2, 0, 0.03], EX, -EZ), 0.5)
    assert reason == "dropped" and not firm
    assert np.isnan(touch).all()


def test_grasp_across_the_long_side_does_not_fit_and_fails(box_sim):
    sim, _ = box_sim
    reason, _, _ = sim.trial(grasp_frame([0, 0, 0.03], EY, -EZ), 0.5)  # 8 cm > 5 cm opening
    assert reason != "held"


def test_fingers_pushed_into_the_table_fail_the_trial(box_sim):
    sim, _ = box_sim
    reason, _, _ = sim.trial(grasp_frame([0, 0, 0.005], EX, -EZ), 0.5)  # tips 5 mm under the table
    assert reason == "table"


def test_noisy_trials_are_seeded_and_mostly_hold_a_good_grasp(box_sim):
    sim, _ = box_sim
    T = grasp_frame([0, 0, 0.03], EX, -EZ)[None]
    a = run_trials(sim, T, 4, np.random.default_rng(3))
    b = run_trials(sim, T, 4, np.random.default_rng(3))
    np.testing.assert_array_equal(a.mu, b.mu)
    assert a.held.shape == (1, 4) and a.held.mean() >= 0.5


def test_trials_stop_once_the_label_is_decided_on_the_same_side_as_all_trials(box_sim):
    sim, _ = box_sim
    T = np.stack([grasp_frame([0, 0, 0.03], EX, -EZ), grasp_frame([0.2, 0, 0.03], EX, -EZ)])  # holds; air
    full = run_trials(sim, T, 8, np.random.default_rng(5))
    early = run_trials(sim, T, 8, np.random.default_rng(5), stop_above=0.5)
    np.testing.assert_array_equal(early.success_rate > 0.5, full.success_rate > 0.5)
    assert early.ran[1].sum() == 4 and not early.held[1].any()  # 4 drops decide "not above 4 of 8"
    assert early.trials_run < full.trials_run == 16 and early.ran[0].sum() <= 8
    np.testing.assert_array_equal(early.mu, full.mu)  # the noise is drawn before any trial runs


def test_early_stop_labels_a_dataset_as_all_trials_do_with_fewer_trials(tmp_path):
    from datagen.config import DatagenConfig
    from datagen.mesh import MeshSource
    from datagen.pipeline import generate_object_with_info

    box = trimesh.creation.box(extents=[0.035, 0.04, 0.10])
    path = tmp_path / "box.stl"
    box.export(str(path))
    over = {"cameras_per_pose": 1, "max_stable_poses": 1, "antipodal.num_samples": 12, "quality.num_samples": 3}
    over.update({"label.kind": "physics", "label.trials": 4, "mesh.rescale": "keep"})
    runs = {}
    for stop in (False, True):
        cfg = DatagenConfig().with_overrides({**over, "label.early_stop": stop})
        _, g, info = generate_object_with_info(MeshSource("box", path), cfg, 0, 1)
        runs[stop] = (g["quality"] > cfg.label_threshold, info["physics"][0]["trials"])
    np.testing.assert_array_equal(runs[True][0], runs[False][0])
    assert 0 < runs[True][1] < runs[False][1]
    with pytest.raises(ValueError, match="early_stop"):
        DatagenConfig().with_overrides({"label.early_stop": "yes"})


def test_execution_noise_has_the_configured_spread():
    p = PhysicsParams()
    dt, R, mu = execution_noise(400, 5, p, np.random.default_rng(0))
    assert abs(dt.std() - p.sigma_translation) < 0.0005
    np.testing.assert_allclose(R.transpose(0, 1, 3, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert abs(mu.mean() - p.friction_coef) < 0.01 and mu.min() >= p.min_friction
    T = perturbed_frames(np.eye(4)[None], dt[:1], R[:1])
    np.testing.assert_allclose(T[0, :, :3, 3], dt[0])


def test_physics_params_reject_bad_values():
    with pytest.raises(ValueError, match="grip_force"):
        PhysicsParams(grip_force=0.0)


def test_the_physics_label_labels_each_grasp_once_per_pose_for_all_cameras(tmp_path):
    from datagen.config import DatagenConfig
    from datagen.mesh import MeshSource
    from datagen.pipeline import generate_object_with_info

    box = trimesh.creation.box(extents=[0.035, 0.04, 0.10])  # lies on a 4 x 10 cm face, 3.5 cm wide on top
    path = tmp_path / "box.stl"
    box.export(str(path))
    cfg = DatagenConfig().with_overrides(
        {
            "cameras_per_pose": 2,
            "max_stable_poses": 1,
            "antipodal.num_samples": 12,
            "quality.num_samples": 3,
            "label.kind": "physics",
            "label.trials": 2,
            "mesh.rescale": "keep",
        }
    )
    _, g, info = generate_object_with_info(MeshSource("box", path), cfg, 0, 1)
    assert info["label"] == "physics" and info["physics"][0]["pose_stable"]
    assert info["physics"][0]["trials"] > 0
    rate = g["success_rate"]
    assert np.all(np.isin(rate, [0.0, 0.5, 1.0]))
    np.testing.assert_array_equal(g["quality"], np.where(g["collision_free"], rate, 0.0).astype(np.float32))
    # every camera sees the same 6-DOF grasp: one omega per grasp id
    for gid in np.unique(g["grasp_id"]):
        rows = g["grasp_id"] == gid
        assert np.unique(g["omega"][rows]).size == 1
        # and the same robust-collision and pad fields (computed once per pose, not per camera)
        for key in ("p_collision_free", "pad_quality"):
            assert np.unique(g[key][rows]).size == 1 or np.all(np.isnan(g[key][rows]))
    assert cfg.label_threshold == 0.5


def test_a_dataset_recorded_before_the_label_setting_resumes_with_the_papers_label():
    from datagen.config import DatagenConfig, recorded_config

    old = DatagenConfig().to_dict()
    for key in ("label", "collision", "physics"):
        old.pop(key)
    cfg = DatagenConfig.from_dict(recorded_config(old))
    assert cfg.label.kind == "paper" and cfg.label_threshold == 0.002
    assert recorded_config(DatagenConfig().to_dict())["label"]["kind"] == "physics"


def test_soft_finger_pads_hold_a_tapered_object_that_point_contacts_let_swing_out():
    import dataclasses

    import manifold3d

    from datagen.config import DatagenConfig
    from datagen.physics import GraspSimulator

    # an upright frustum tapering 5 deg (statics: holds from mu = 0.09), gripped from above 5 cm up
    m = manifold3d.Manifold.cylinder(0.074, 0.012, 0.012 - 0.074 * np.tan(np.radians(5.0)), 48).to_mesh()
    mesh = trimesh.Trimesh(m.vert_properties[:, :3], m.tri_verts)
    T_grasp = np.eye(4)
    T_grasp[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # jaw axis x, approach down
    T_grasp[:3, 3] = [0, 0, 0.05]
    cfg = DatagenConfig()
    held = {}
    for r in (0.0, cfg.physics.pad_contact_radius):
        with GraspSimulator(cfg.gripper, dataclasses.replace(cfg.physics, pad_contact_radius=r)) as sim:
            sim.set_object(mesh, np.eye(4))
            held[r] = sim.trial(T_grasp, 0.5)[0]
    assert cfg.physics.pad_contact_radius > 0
    assert held == {0.0: "dropped", cfg.physics.pad_contact_radius: "held"}


def test_a_dataset_recorded_before_soft_fingers_resumes_with_point_contacts():
    from datagen.config import DatagenConfig, recorded_config

    old = DatagenConfig().to_dict()
    old["physics"].pop("pad_contact_radius")
    assert DatagenConfig.from_dict(recorded_config(old)).physics.pad_contact_radius == 0.0
    assert recorded_config(DatagenConfig().to_dict())["physics"]["pad_contact_radius"] == 0.003
