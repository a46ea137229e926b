"""Balanced accuracy of the bundled model on the same labelled scenes rendered at fx = 450, 525
and 615 px (the any-camera check of issue 11), scored as the service scores them: the image
resampled to the model's focal length (``vgq.camera.resample_depth``), grasp pixels mapped
(``map_pixels``), training-grid windows, the shared missing-depth fill, the ONNX graphs.

    python examples/any_camera_bacc.py [--objects 44] [--cameras 8]

Measured 2026-11-30 (defaults; 26,357 grasps, 393 positive): balanced accuracy 0.848 at
450 px, 0.850 at 525 px, 0.849 at 615 px; mean |dp| against the 525 px render 0.002 / 0.0016.

Scenes: held-out test objects of the bundled model's recipe (ids from heldout_test_crops.npz) on
their most probable stable pose; grasps from datagen's antipodal sampler, labelled as the
recipe labels them (robust Ferrari-Canny > 0.002 and collision-free), psi < 90 deg. Each camera
keeps the 525 px image's field of view (a 257 px image at 450 px, 351 px at 615 px).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from datagen.camera import CameraParams, sample_cameras
from datagen.collision import CollisionChecker
from datagen.config import DatagenConfig
from datagen.grasps import sample_antipodal_grasps
from datagen.gripper import align_to_table, grasp_frames
from datagen.mesh import load_object, mesh_sources, stable_poses
from datagen.project import project_grasps
from datagen.quality import resolve_torque_scaling, robust_ferrari_canny
from datagen.render import render_depth
from service.preprocess import window_input
from service.runtime import FastModel
from vgq.camera import Intrinsics, map_pixels, resample_depth
from vgq.crop import grid_window_centers, window_origin
from vgq.grasps import pose_rows

HERE = Path(__file__).resolve().parent


def score(model, depth, rows):
    geom = model.geometry
    centres = grid_window_centers(rows[:, :2], depth.shape, geom)
    p = np.empty(len(rows))
    for c in np.unique(centres, axis=0):
        m = np.all(centres == c, axis=1)
        win = window_input(depth, window_origin(c[None], geom)[0], geom, 1.0)
        p[m] = model.score(model.encode(win.image), pose_rows(rows[m], win.center, geom, 4096))
    return p


def bacc(p, y):
    pred = p > 0.5
    return 0.5 * ((pred & y).sum() / max(y.sum(), 1) + (~pred & ~y).sum() / max((~y).sum(), 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, default=44)
    ap.add_argument("--cameras", type=int, default=8)
    a = ap.parse_args()
    cfg = DatagenConfig().with_overrides({"label.kind": "paper"})
    model = FastModel(HERE.parent / "models" / "fast-vgqcnn-default", threads=1, head_precision="fp32")
    native = model.card.intrinsics
    ids = sorted(set(int(i) for i in np.load(HERE / "heldout_test_crops.npz")["object_id"]))[: a.objects]
    sources = mesh_sources(None)
    fxs = (450.0, 525.0, 615.0)
    p = {fx: [] for fx in fxs}
    labels = []
    for oid in ids:
        obj = load_object(sources[oid], cfg.mesh)
        T_poses, _ = stable_poses(obj, 0.01, 1)
        mesh = obj.mesh.copy()
        mesh.apply_transform(T_poses[0])
        rng = np.random.default_rng(oid)
        g = sample_antipodal_grasps(obj.mesh, cfg.antipodal, rng)
        qp = dataclasses.replace(cfg.quality, torque_scaling=resolve_torque_scaling(obj.mesh, cfg.quality))
        quality = np.asarray(robust_ferrari_canny(obj.mesh, g, qp, rng))
        T_wg, _, _ = align_to_table(T_poses[0] @ grasp_frames(g.centers, g.axes, 0.0), rng)
        free = ~np.asarray(CollisionChecker(mesh, cfg.gripper).collides(T_wg), bool)
        y_all = free & (quality > cfg.label_threshold)
        cams = sample_cameras(a.cameras, dataclasses.replace(CameraParams()), rng)
        for T_wc in cams.T_world_camera:
            keep = None
            views = {}
            for fx in fxs:
                side = int(round(native.width * fx / native.fx))
                cam = Intrinsics(fx=fx, fy=fx, cx=(side - 1) / 2, cy=(side - 1) / 2, width=side, height=side)
                pr = project_grasps(T_wg, T_wc, cam)
                ok = pr["in_image"] & (pr["psi"] < np.pi / 2)
                keep = ok if keep is None else keep & ok
                views[fx] = (cam, pr)
            if not keep.any():
                continue
            for fx, (cam, pr) in views.items():
                d, res = resample_depth(render_depth(mesh, T_wc, cam), cam, native)
                uv = map_pixels(np.column_stack([pr["u"], pr["v"]])[keep], cam, res)
                p[fx].append(score(model, d, np.column_stack([uv, pr["z"][keep], pr["q"][keep]])))
            labels.append(y_all[keep])
    y = np.concatenate(labels)
    print(f"{len(ids)} objects x {a.cameras} cameras: {len(y)} grasps, {int(y.sum())} positive")
    ref = np.concatenate(p[525.0])
    for fx in fxs:
        q = np.concatenate(p[fx])
        print(f"fx {fx:.0f}: balanced accuracy {bacc(q, y):.4f}, mean |dp| vs 525 px {np.abs(q - ref).mean():.4f}")


if __name__ == "__main__":
    main()
