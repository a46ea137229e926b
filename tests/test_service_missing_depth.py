"""Missing depth (0 = no reading) through the real service: the window is filled by the shared
vgq.inpaint before the encoder, the upload answer reports the missing fraction, a mostly
missing window is a 422 that says so, and 2% missing pixels (sensor-model blobs + edge
dropouts) leave the bundled model's balanced accuracy on held-out images within 2 points.

Run as a script to measure by hand, also against another code tree (e.g. before the fix):

    python tests/test_service_missing_depth.py [--root /path/to/checkout] [--blob-rate 25]
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from servers import free_port, grasps_at, running_service

from datagen.sensor import SensorModel, image_rng
from service.client import ServiceClient, ServiceError
from service.config import Settings
from service.preprocess import window_input
from vgq import crop as vcrop
from vgq.inpaint import filled_window

ROOT = Path(__file__).resolve().parent.parent
BUNDLED = ROOT / "models" / "fast-vgqcnn-default"
sys.path.insert(0, str(ROOT / "examples"))

#: Dropouts only (no noise): every jump edge (~0.36% of a render) plus Poisson(25) blobs of
#: 2-6 px: 2.0% of the pixels of the held-out renders on average.
MISSING_2PCT = SensorModel(
    edge_jump_m=0.005, edge_angle_deg=5.0, edge_dropout=1.0, blob_rate=25.0, blob_radius_px=(2.0, 6.0)
)
GEOM = vcrop.CropGeometry(96, 32, 36.0)


def holed_scene(fraction_rows: int = 0) -> np.ndarray:
    """Table + box depth image; the first ``fraction_rows`` rows of the centre window and a
    few small holes in it read 0."""
    d = np.full((300, 300), 0.7, np.float32)
    d[120:180, 130:170] = 0.65
    d[140:146, 150:158] = 0.0
    d[178:184, 100:110] = 0.0
    o = vcrop.window_origin((149.5, 149.5), GEOM)
    d[o[1] : o[1] + fraction_rows, :] = 0.0
    return d


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(model_dir) as u:
        yield u


def upload(url, depth, **params):
    """Upload with the one fixed window at the image centre (the window these tests make holes in)."""
    params = {"center_u": 149.5, "center_v": 149.5, **params}
    return httpx.post(
        f"{url}/v1/images",
        content=ServiceClient._npy(depth),
        params=params,
        headers={"content-type": "application/x-npy"},
    )


def test_upload_reports_the_missing_fraction_of_the_window(url):
    d = holed_scene()
    r = upload(url, d)
    assert r.status_code == 200, r.text
    _, expected = filled_window(d, vcrop.window_origin((149.5, 149.5), GEOM), GEOM)
    assert expected > 0 and r.json()["missing_fraction"] == pytest.approx(expected)
    assert upload(url, holed_scene()).json()["missing_fraction"] == pytest.approx(expected)  # cache hit too


def test_the_encoder_sees_the_filled_window_not_zeros(url):
    """Scores of a holed image = scores of a complete image whose window is vgq.inpaint's fill."""
    d = holed_scene()
    origin = vcrop.window_origin((149.5, 149.5), GEOM)
    win, _ = filled_window(d, origin, GEOM)
    complete = d.copy()
    complete[origin[1] : origin[1] + 96, origin[0] : origin[0] + 96] = win
    g = grasps_at(k=32)
    with ServiceClient(url) as c:
        p_holed = c.score(c.upload(d, center=(149.5, 149.5)), g)
        p_complete = c.score(c.upload(complete, center=(149.5, 149.5)), g)
        assert c.last_upload["missing_fraction"] == 0.0
    np.testing.assert_allclose(p_holed, p_complete, atol=1e-6)


def test_window_input_is_finite_and_positive_everywhere():
    d = holed_scene()
    d[150, 150] = np.nan
    d[151, 151] = -np.inf
    w = window_input(d, vcrop.window_origin((149.5, 149.5), GEOM), GEOM, 0.5)
    assert np.all(np.isfinite(w.image)) and np.all(w.image > 0)


def test_mostly_missing_window_is_a_422_that_says_so(url):
    d = holed_scene(fraction_rows=60)  # 62.5% of the rows + the holes
    _, frac = filled_window(d, vcrop.window_origin((149.5, 149.5), GEOM), GEOM)
    r = upload(url, d)
    assert r.status_code == 422
    e = r.json()["error"]
    assert f"{100 * frac:.1f}% of the 96x96 px crop window" in e["message"]
    assert "no depth reading" in e["message"] and "max_missing_fraction" in e["message"]
    assert e["details"]["missing_fraction"] == pytest.approx(frac)


def test_window_without_a_valid_pixel_is_a_422(url):
    d = np.full((300, 300), 0.7, np.float32)
    d[30:270, 30:270] = 0.0  # the window and its margin are empty; the image is not
    r = upload(url, d)
    assert r.status_code == 422 and "no valid depth pixel" in r.json()["error"]["message"]


def test_one_shot_reports_and_refuses_the_same_way(url):
    with ServiceClient(url) as c:
        buf = io.BytesIO()
        np.savez(buf, depth=holed_scene(), grasps=grasps_at(k=4))
        r = c.http.post("/v1/score", content=buf.getvalue(), headers={"content-type": "application/x-npz"})
        assert r.status_code == 200 and r.json()["missing_fraction"] > 0
        with pytest.raises(ServiceError) as e:
            c.score_once(holed_scene(fraction_rows=60), grasps_at(k=4))
        assert e.value.status == 422 and "no depth reading" in e.value.message


def test_shared_cache_entries_keep_the_missing_fraction():
    from service.cache import EncodedWindow
    from service.redis_cache import pack_window, unpack_window

    e = EncodedWindow(np.ones((1, 1024), np.float32), 0.0375)
    assert unpack_window(pack_window(e)).missing_fraction == 0.0375


def test_max_missing_fraction_is_a_setting(model_dir):
    with pytest.raises(ValueError, match="max_missing_fraction"):
        Settings(max_missing_fraction=1.5)
    with running_service(model_dir, "--max-missing-fraction", "0.9") as u:
        r = upload(u, holed_scene(fraction_rows=60))
        assert r.status_code == 200 and 0.6 < r.json()["missing_fraction"] < 0.9


# ------------------------------------------------------------------ held-out images, bundled model


def corrupt(depth: np.ndarray, object_id: int, index: int, model: SensorModel = MISSING_2PCT) -> np.ndarray:
    return model.apply(depth, image_rng(0, object_id, index))


def score_heldout(url: str, images: np.ndarray, held) -> tuple[np.ndarray, np.ndarray]:
    """p_success (m,) of every held-out grasp, each sent with its image and its own window
    centre in one one-shot request, and the missing fraction the service reported for its
    window (nan if not reported)."""
    p = np.empty(len(held), np.float32)
    miss = np.full(len(held), np.nan)
    with ServiceClient(url) as c:
        for j in range(len(held)):
            buf = io.BytesIO()
            np.savez(
                buf,
                depth=images[int(held.image_index[j])],
                grasps=held.grasps[j : j + 1],
                center=held.center[j].astype(np.float64),
            )
            r = c.http.post("/v1/score", content=buf.getvalue(), headers={"content-type": "application/x-npz"})
            c._raise(r)
            body = r.json()
            p[j] = body["raw_score"][0]
            miss[j] = body.get("missing_fraction", np.nan)
    return p, miss


def balanced_accuracy(labels: np.ndarray, p: np.ndarray) -> float:
    y, pred = labels == 1, p > 0.5
    return float((pred[y].mean() + (~pred[~y]).mean()) / 2)


def heldout_comparison(url: str, blob_rate: float = 25.0, model: SensorModel | None = None) -> dict:
    """Scores of the held-out images clean and corrupted by ``model`` (default: MISSING_2PCT
    with ``blob_rate``) through the service at ``url``."""
    from heldout import load_heldout_images

    held = load_heldout_images()
    model = model or MISSING_2PCT.with_overrides({"blob_rate": blob_rate})
    holed = np.stack([corrupt(d, int(o), i, model) for i, (d, o) in enumerate(zip(held.depth, held.object_id))])
    image_missing = float(np.mean(holed == 0))
    p_clean, _ = score_heldout(url, held.depth, held)
    p_holed, window_missing = score_heldout(url, holed, held)
    return {
        "grasps": len(held),
        "images": len(held.depth),
        "image_missing": image_missing,
        "window_missing_mean": float(np.nanmean(window_missing)) if np.isfinite(window_missing).any() else None,
        "ba_clean": balanced_accuracy(held.labels, p_clean),
        "ba_holed": balanced_accuracy(held.labels, p_holed),
        "p_clean_mean": float(p_clean.mean()),
        "p_holed_mean": float(p_holed.mean()),
    }


@pytest.fixture(scope="module")
def bundled_url():
    with running_service(BUNDLED) as u:
        yield u


def test_two_percent_missing_moves_heldout_balanced_accuracy_less_than_two_points(bundled_url):
    r = heldout_comparison(bundled_url)
    assert 0.015 < r["image_missing"] < 0.025, r
    assert r["window_missing_mean"] > 0.01, r  # the windows around the objects do have holes
    assert r["ba_clean"] > 0.7, r  # the bundled model classifies the clean held-out images
    assert abs(r["ba_holed"] - r["ba_clean"]) < 0.02, r


# ------------------------------------------------------------------ by hand


@contextmanager
def service_from(root: Path, model_dir: Path):
    """A service subprocess running the code of checkout ``root`` (cwd and PYTHONPATH)."""
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", "--model-dir", str(model_dir), "--port", str(port), "--threads", "1"],
        cwd=root,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        for _ in range(600):
            try:
                if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        yield url
    finally:
        proc.terminate()
        proc.wait(10)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description="Balanced accuracy of the bundled model on held-out images, clean vs "
        "2%-missing uploads (sensor-model blobs + edge dropouts)."
    )
    p.add_argument("--root", default=str(ROOT), help="code tree whose service to run (default: this one)")
    p.add_argument("--blob-rate", type=float, default=25.0, help="dropout blobs per image (25: ~2%% missing)")
    p.add_argument("--sensor", help="corrupt with this datagen.sensor preset (e.g. realistic) instead")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    model = None
    if a.sensor:
        from datagen.sensor import resolve

        model = resolve(a.sensor)[1]
    with service_from(Path(a.root).resolve(), BUNDLED) as u:
        r = heldout_comparison(u, a.blob_rate, model)
    print(f"service code: {Path(a.root).resolve()}")
    print(
        f"{r['grasps']} grasps on {r['images']} held-out images; missing pixels {100 * r['image_missing']:.2f}% "
        f"of the images, {100 * r['window_missing_mean']:.2f}% of the windows"
        if r["window_missing_mean"] is not None
        else f"{r['grasps']} grasps; missing pixels {100 * r['image_missing']:.2f}% of the images (windows: not reported)"
    )
    print(
        f"balanced accuracy clean {100 * r['ba_clean']:.1f}%, with missing pixels {100 * r['ba_holed']:.1f}% "
        f"(change {100 * (r['ba_holed'] - r['ba_clean']):+.1f} points); mean p_success {r['p_clean_mean']:.3f} -> "
        f"{r['p_holed_mean']:.3f}  [{time.perf_counter() - t0:.0f} s]"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
