"""Golden end-to-end scores: the real service on the bundled model scores the example image
exactly as an independent computation does (window and offsets written out by hand in
examples/golden.py, then the ONNX encoder and head run directly), and as the stored golden
scores say (examples/golden_scores.json, regenerated only with the model by
scripts/make_default_model.sh). A wrong sign, a swapped u / v, a shifted window or a changed
resize in the serving path moves these scores far beyond the 1e-5 allowed.
Service answers are compared through ``raw_score`` (the network's output); ``p_success`` is
that score through the card's calibration."""

from __future__ import annotations

import io
import json
import sys
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from servers import running_service

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "examples"))
import golden  # noqa: E402  (examples/golden.py)

TOL = 1e-5


@pytest.fixture(scope="module")
def stored() -> dict:
    return json.loads(golden.GOLDEN.read_text())


@pytest.fixture(scope="module")
def depth() -> np.ndarray:
    return np.load(golden.DEPTH)


def _npy(a: np.ndarray) -> bytes:
    b = io.BytesIO()
    np.save(b, a, allow_pickle=False)
    return b.getvalue()


def test_golden_file_is_of_the_bundled_model_and_its_grasps(stored):
    card = json.loads((golden.MODEL / "model_card.json").read_text())
    assert stored["model_version"] == card["model_version"], "golden scores of another model: rerun examples/golden.py"
    np.testing.assert_allclose(stored["grasps"], golden.golden_grasps(), atol=1e-6)


def test_golden_grasps_see_a_flipped_sign_or_swapped_axes(stored, depth):
    """The golden grasps can tell: offsets negated or u and v swapped score far apart."""
    g = np.array(stored["grasps"])
    flipped, swapped = g.copy(), g.copy()
    flipped[:, :2] = 2 * golden.CENTRE - g[:, :2]
    swapped[:, :2] = g[:, 1::-1]
    for other in (flipped, swapped):
        assert np.abs(golden.hand_scores(depth, other) - stored["p_success"]).max() > 0.1


def test_hand_computation_reproduces_the_stored_golden_scores(stored, depth):
    p = golden.hand_scores(depth, np.array(stored["grasps"]))
    np.testing.assert_allclose(p, stored["p_success"], atol=TOL, rtol=0)


@pytest.fixture(scope="module")
def fp32_url():
    # fp32 graphs: the golden scores are the fp32 encoder's and head's (auto may pick the int8 encoder)
    with running_service(golden.MODEL, "--head-precision", "fp32", "--encoder-precision", "fp32") as u:
        yield u


def test_service_upload_then_score_equals_golden(fp32_url, stored, depth):
    up = httpx.post(f"{fp32_url}/v1/images", content=_npy(depth), headers={"content-type": "application/x-npy"})
    assert up.status_code == 200, up.text
    assert up.json()["image_shape"] == [300, 300]  # every golden grasp lies within kappa of the central window
    r = httpx.post(f"{fp32_url}/v1/images/{up.json()['image_id']}/scores", json={"grasps": stored["grasps"]})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(r.json()["raw_score"], stored["p_success"], atol=TOL, rtol=0)


def test_service_one_shot_npz_with_off_centre_window_equals_hand_computation(fp32_url, depth):
    """A window centred elsewhere: the image is shifted by hand so that the hand computation's
    fixed window sees what the service's window at (149.5 + 21, 149.5 - 15) sees."""
    du, dv = 21, -15
    shifted = np.pad(depth, ((15, 0), (0, 21)), mode="edge")[:300, 21:]  # shifted[v, u] = depth[v + dv, u + du]
    assert shifted[150, 100] == depth[135, 121]
    g = golden.golden_grasps()
    moved = g.copy()
    moved[:, 0] += du
    moved[:, 1] += dv
    ref = golden.hand_scores(shifted, g, placement_from=(depth, moved))  # a placement head's rows: as uploaded
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w") as z:
        z.writestr("depth.npy", _npy(depth))
        z.writestr("grasps.npy", _npy(moved.astype(np.float32)))
        z.writestr("center.npy", _npy(np.array([golden.CENTRE + du, golden.CENTRE + dv])))
    r = httpx.post(f"{fp32_url}/v1/score", content=b.getvalue(), headers={"content-type": "application/x-npz"})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(r.json()["raw_score"], ref, atol=TOL, rtol=0)


def test_default_int8_service_equals_the_int8_head_run_directly(stored, depth):
    with running_service(golden.MODEL, "--encoder-precision", "fp32") as url:  # the int8 head, the fp32 encoder
        up = httpx.post(f"{url}/v1/images", content=_npy(depth), headers={"content-type": "application/x-npy"})
        r = httpx.post(f"{url}/v1/images/{up.json()['image_id']}/scores", json={"grasps": stored["grasps"]})
    assert r.status_code == 200, r.text
    p8 = np.asarray(r.json()["raw_score"])
    np.testing.assert_allclose(
        p8, golden.hand_scores(depth, np.array(stored["grasps"]), head="head_int8.onnx"), atol=TOL, rtol=0
    )
    assert np.abs(p8 - stored["p_success"]).max() <= 0.05  # the card's int8 check bound
