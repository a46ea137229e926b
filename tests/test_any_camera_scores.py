"""Any camera (issue 11): the same scene rendered by datagen at fx = 450, 525 and 615 px,
resampled to the model's focal length with ``vgq.camera.resample_depth``, gets the same
scores from the bundled model as the native render (grasps mapped with ``map_pixels``,
windows from ``vgq.crop.grid_window_centers``)."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("trimesh")

from datagen.camera import CameraParams, sample_cameras
from datagen.config import DatagenConfig
from datagen.grasps import sample_antipodal_grasps
from datagen.gripper import align_to_table, grasp_frames
from datagen.mesh import load_object, mesh_sources, stable_poses
from datagen.project import project_grasps
from datagen.render import render_depth
from service import placement
from service.runtime import FastModel
from vgq.camera import Intrinsics, map_pixels, resample_depth
from vgq.crop import crop, grid_window_centers
from vgq.grasps import pose_rows

MODEL_DIR = "models/fast-vgqcnn-default"


def _placement(model, depth, camera, grasps):
    """A placement head's rows of client ``grasps`` (k, 7) on the image ``depth`` as sent, seen with
    ``camera`` (the service's analysis of an upload, before any resampling); None for other heads."""
    return placement.rows(placement.analyse(depth, camera), grasps) if model.n_pose != 7 else None


def _score(model, depth, rows, extra):
    """Scores of grasps ``rows`` (k, 7) on ``depth``, each pose row followed by its ``extra`` row if any."""
    centres = grid_window_centers(rows[:, :2], depth.shape, model.geometry)
    p = np.empty(len(rows))
    for c in np.unique(centres, axis=0):
        m = np.all(centres == c, axis=1)
        img, actual = crop(depth, c, model.geometry)
        pose = pose_rows(rows[m], actual, model.geometry, 4096)
        p[m] = model.score(model.encode(img), pose if extra is None else np.column_stack([pose, extra[m]]))
    return p


@pytest.fixture(scope="module")
def scene():
    """A held-out recipe object (id 115) on its most probable stable pose, 3 cameras, its grasps."""
    cfg = DatagenConfig()
    src = mesh_sources(None)[115]
    obj = load_object(src, cfg.mesh)
    T_poses, _ = stable_poses(obj, 0.01, 1)
    mesh = obj.mesh.copy()
    mesh.apply_transform(T_poses[0])
    rng = np.random.default_rng(0)
    grasps = sample_antipodal_grasps(obj.mesh, cfg.antipodal, rng)
    T_wg, _, _ = align_to_table(T_poses[0] @ grasp_frames(grasps.centers, grasps.axes, 0.0), rng)
    cams = sample_cameras(3, dataclasses.replace(CameraParams(), phi_range=(0.2, 0.8)), rng)
    return mesh, T_wg, cams.T_world_camera


@pytest.mark.parametrize("fx", [450.0, 615.0])
def test_other_focal_lengths_score_like_the_native_camera(scene, fx):
    mesh, T_wg, T_wcs = scene
    model = FastModel(MODEL_DIR, threads=1, head_precision="fp32", encoder_precision="fp32")
    native = model.card.intrinsics
    # same field of view as the model's 300 px image: a 450 px camera sees it in 257 px, 615 in 351 px
    side = int(round(native.width * fx / native.fx))
    cam = Intrinsics(fx=fx, fy=fx, cx=(side - 1) / 2, cy=(side - 1) / 2, width=side, height=side)
    diffs, unresampled = [], []
    for T_wc in T_wcs:
        ref = project_grasps(T_wg, T_wc, native)
        other = project_grasps(T_wg, T_wc, cam)
        ok = ref["in_image"] & other["in_image"] & (ref["psi"] < np.pi / 2)
        if not ok.any():
            continue
        rows_ref = np.column_stack([ref["u"], ref["v"], ref["z"], ref["q"]])[ok]
        d_ref = render_depth(mesh, T_wc, native)
        p_ref = _score(model, d_ref, rows_ref, _placement(model, d_ref, native, rows_ref))
        raw = render_depth(mesh, T_wc, cam)
        uv_raw = np.column_stack([other["u"], other["v"]])[ok]
        rows_raw = np.column_stack([uv_raw, other["z"][ok], other["q"][ok]])
        d_cam, resampled = resample_depth(raw, cam, native)
        rows = np.column_stack([map_pixels(uv_raw, cam, resampled), other["z"][ok], other["q"][ok]])
        diffs.append(np.abs(_score(model, d_cam, rows, _placement(model, raw, cam, rows_raw)) - p_ref))
        # control: the same image scored as if it came from the model's camera
        unresampled.append(np.abs(_score(model, raw, rows_raw, _placement(model, raw, native, rows_raw)) - p_ref))
    d, control = np.concatenate(diffs), np.concatenate(unresampled)
    assert len(d) >= 50
    # measured: mean |dp| 0.001 resampled vs 0.04-0.07 unresampled (issue 11 asks <= 0.05)
    assert d.mean() <= 0.01, f"mean |dp| {d.mean():.4f} over {len(d)} grasps"
    assert control.mean() >= 4 * d.mean(), "the control should show what a focal-length mismatch costs"


def test_the_service_path_scores_other_cameras_like_the_native_one(scene):
    """The same check through the service's own steps (``Service.prepare_image`` + ``score``):
    client intrinsics, client pixels, windows on the grid. fx 450 / 525 / 615 px renders."""
    from service.config import Settings
    from service.scoring import Service

    mesh, T_wg, T_wcs = scene
    svc = Service(Settings(threads=1, head_precision="fp32", encoder_precision="fp32", model_dir=MODEL_DIR))
    svc.load()
    native = svc.model.card.intrinsics
    cams = {
        fx: Intrinsics(fx=fx, fy=fx, cx=(s - 1) / 2, cy=(s - 1) / 2, width=s, height=s)
        for fx in (450.0, 525.0, 615.0)
        for s in [int(round(native.width * fx / native.fx))]
    }
    p = {fx: [] for fx in cams}
    unsent = {fx: [] for fx in cams}  # control: the same uploads without intrinsics (the model's assumed)
    for n, T_wc in enumerate(T_wcs):
        proj = {fx: project_grasps(T_wg, T_wc, cam) for fx, cam in cams.items()}
        ok = np.logical_and.reduce([pr["in_image"] for pr in proj.values()]) & (proj[525.0]["psi"] < np.pi / 2)
        if not ok.any():
            continue
        for fx, cam in cams.items():
            pr = proj[fx]
            depth = render_depth(mesh, T_wc, cam)
            entry = svc.prepare_image(depth, {"fx": fx, "fy": fx, "cx": cam.cx, "cy": cam.cy})
            rows = np.column_stack([pr["u"], pr["v"], pr["z"], pr["q"]])[ok]
            p[fx].append(svc.score(f"{fx}-{n}", entry, rows).raw_score)
            unsent[fx].append(svc.score(f"{fx}-{n}-unsent", svc.prepare_image(depth, {}), rows).raw_score)
    ref = np.concatenate(p[525.0])
    assert len(ref) >= 50
    for fx in (450.0, 615.0):
        d = np.abs(np.concatenate(p[fx]) - ref)
        control = np.abs(np.concatenate(unsent[fx]) - ref)
        print(f"fx {fx}: mean |dp| {d.mean():.4f} over {len(d)} grasps; without intrinsics {control.mean():.4f}")
        # measured: 0.0009 (450 px) and 0.0006 (615 px); without intrinsics 0.04-0.07 (issue 11 asks <= 0.05)
        assert d.mean() <= 0.01, f"fx {fx}: mean |dp| {d.mean():.4f} over {len(d)} grasps"
        assert control.mean() >= 4 * d.mean()
        # the same decisions at 0.5 for nearly every grasp
        assert np.mean((np.concatenate(p[fx]) > 0.5) == (ref > 0.5)) >= 0.95
