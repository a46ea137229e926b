"""A model trained on another crop window (``datagen crops --window 64``: 64 x 64 source px to
32 x 32, kappa 24) is served on its own geometry, read from its card: grasps anywhere get
that window grid, score as per-window uploads do, and the planner plans on it."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import table_scene
from servers import running_service

from service.client import ServiceClient
from vgq.camera import DEFAULT_INTRINSICS
from vgq.crop import CropGeometry, grid_window_centers

GEOM = CropGeometry(64, 32, 24.0)


@pytest.fixture(scope="module")
def client(tmp_path_factory, briefly_trained):
    from export.onnx_export import export_model

    net, imgs, poses = briefly_trained
    out = tmp_path_factory.mktemp("models") / "w64"
    export_model(net, out, imgs[:32], poses[:32], GEOM, DEFAULT_INTRINSICS, dataset={"recipe": "tests"})
    with running_service(out, "--threads", "1") as url, ServiceClient(url) as c:
        yield c


def test_the_model_cards_window_sets_the_grid_and_scores_match_fixed_windows(client):
    assert client.model()["model_card"]["geometry"] == GEOM.to_dict()
    depth = table_scene(240, 320, box=(90, 150, 130, 190))
    rng = np.random.default_rng(0)
    g = np.zeros((24, 7))
    g[:, 0], g[:, 1] = rng.uniform(0, 319, 24), rng.uniform(0, 239, 24)
    g[:, 2], g[:, 3] = 0.66, 1.0
    one = client.score_details(client.upload(depth), g)
    centres = grid_window_centers(g[:, :2], depth.shape, GEOM)
    assert one["windows"] == len(np.unique(centres, axis=0)) > 4
    assert np.all(np.abs(centres - g[:, :2]) <= GEOM.kappa_px)
    fixed = np.empty(len(g))
    for c in np.unique(centres, axis=0):
        m = np.all(centres == c, axis=1)
        fixed[m] = client.score_details(client.upload(depth, center=tuple(c)), g[m])["raw_score"]
    np.testing.assert_allclose(one["raw_score"], fixed, atol=1e-6)


def test_the_planner_plans_on_the_models_window(client):
    plan = client.plan(table_scene(), k=2, seed=0)
    assert len(plan.grasps) == 2 and plan.reason is None
