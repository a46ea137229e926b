"""Any camera, grasps anywhere, flags and calibrated scores through the real service (issue 11):
intrinsics on every endpoint (query, multipart, .npz) with 422s naming the field, windows on
the training grid (also at the image borders) encoded lazily and cached per image, eviction
by bytes, out-of-distribution flags and ``strict``, calibrated vs raw ``p_success``."""

from __future__ import annotations

import io
import json
import shutil

import httpx
import numpy as np
import pytest
from conftest import table_scene
from servers import grasps_at, running_service

from service.client import ServiceClient, ServiceError
from vgq.calibration import Calibration
from vgq.camera import Intrinsics, map_pixels, resampled_intrinsics
from vgq.crop import CropGeometry, grid_window_centers

NPY = {"content-type": "application/x-npy"}
GEOM = CropGeometry(96, 32, 36.0)
MODEL = Intrinsics()  # the test model's: fx = fy = 525


def npy(a) -> bytes:
    b = io.BytesIO()
    np.save(b, np.asarray(a, np.float32))
    return b.getvalue()


def npz(**arrays) -> bytes:
    b = io.BytesIO()
    np.savez(b, **arrays)
    return b.getvalue()


def metric(url: str, name: str) -> float:
    for line in httpx.get(f"{url}/metrics").text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in /metrics")


def wide_scene(h: int = 480, w: int = 640) -> np.ndarray:
    d = table_scene(h, w, box=(200, 280, 280, 360))
    d[20:60, 20:70] = 0.66  # something near the top-left corner
    return d


def spread_grasps(h: int, w: int, k: int = 40, seed: int = 0) -> np.ndarray:
    """k grasps all over an (h, w) image, the four corner pixels among them; approach towards the camera."""
    g = grasps_at(k=k, seed=seed).astype(np.float64)
    rng = np.random.default_rng(seed)
    g[:, 0], g[:, 1] = rng.uniform(-0.5, w - 0.5, k), rng.uniform(-0.5, h - 0.5, k)
    g[:4, :2] = [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]]
    g[:, 3:] = [1.0, 0.0, 0.0, 0.0]  # gripper z = camera z: no approach flag
    g[:, 2] = 0.65
    return g


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(model_dir, "--max-grasps", "512") as u:
        yield u


def upload(url, depth, **params) -> httpx.Response:
    return httpx.post(f"{url}/v1/images", content=npy(depth), headers=NPY, params=params)


def scores(url, iid, grasps, **params) -> dict:
    r = httpx.post(f"{url}/v1/images/{iid}/scores", json={"grasps": np.asarray(grasps).tolist()}, params=params)
    assert r.status_code == 200, r.text
    return r.json()


# ---- intrinsics --------------------------------------------------------------------------------------------
def test_intrinsics_by_query_multipart_and_npz_score_alike(url):
    depth, g = table_scene(360, 360), spread_grasps(360, 360, k=12)
    intr = {"fx": 630.0, "fy": 630.0, "cx": 179.5, "cy": 179.5}
    up = upload(url, depth, **intr).json()
    assert up["intrinsics"] == intr and up["intrinsics_assumed"] == []
    assert up["resampled"]["image_shape"] == [300, 300] and up["resampled"]["intrinsics"]["fx"] == pytest.approx(525.0)
    by_query = scores(url, up["image_id"], g)
    multipart = httpx.post(
        f"{url}/v1/score",
        files={"depth": ("d.npy", npy(depth), "application/x-npy")},
        data={"grasps": json.dumps({"grasps": g.tolist()}), **{k: str(v) for k, v in intr.items()}},
    )
    one_npz = httpx.post(
        f"{url}/v1/score",
        content=npz(depth=depth, grasps=g, intrinsics=list(intr.values())),
        headers={"content-type": "application/x-npz"},
    )
    for r in (multipart, one_npz):
        assert r.status_code == 200, r.text
        assert r.json()["intrinsics"] == intr and r.json()["intrinsics_assumed"] == []
        assert np.allclose(r.json()["p_success"], by_query["p_success"], atol=1e-6)


def test_resampled_upload_scores_as_the_same_scene_at_the_model_focal_length(url):
    """An image of a 630 px camera, made by upscaling a 525 px one (exact 6/5), scores like the original."""
    native = table_scene(300, 300)
    big = np.kron(native, np.ones((6, 6), np.float32))[::5, ::5][:360, :360]  # nearest-neighbour x 1.2
    g_native = spread_grasps(300, 300, k=16, seed=3)
    g_native[:, :2] = np.clip(g_native[:, :2], 20, 279)
    g_cam = g_native.copy()
    g_cam[:, :2] = map_pixels(g_native[:, :2], MODEL, resampled_intrinsics(MODEL, 1.2, 1.2))
    p_native = np.array(scores(url, upload(url, native).json()["image_id"], g_native)["p_success"])
    p_cam = np.array(scores(url, upload(url, big, fx=630, fy=630).json()["image_id"], g_cam)["p_success"])
    assert np.abs(p_cam - p_native).mean() < 0.05


def test_omitted_intrinsics_are_the_model_s_and_the_answer_says_so(url):
    up = upload(url, wide_scene()).json()
    assert up["intrinsics_assumed"] == ["fx", "fy", "cx", "cy"]
    assert up["intrinsics"] == {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5}
    assert up["resampled"]["scale"] == [1.0, 1.0]
    assert scores(url, up["image_id"], grasps_at(center=(320, 240), k=2))["intrinsics_assumed"] == [
        "fx",
        "fy",
        "cx",
        "cy",
    ]
    r = httpx.post(
        f"{url}/v1/score",
        content=npz(depth=table_scene(), grasps=grasps_at(k=2)),
        headers={"content-type": "application/x-npz"},
    ).json()
    assert r["intrinsics_assumed"] == ["fx", "fy", "cx", "cy"]
    assert upload(url, wide_scene(), fx=600).json()["intrinsics_assumed"] == ["fy", "cx", "cy"]


BAD_INTRINSICS = [
    ({"fx": 0}, "fx"),
    ({"fx": -500}, "fx"),
    ({"fy": "nan"}, "fy"),
    ({"fx": "inf"}, "fx"),
    ({"fx": 2000}, "fx"),
    ({"fy": 200}, "fy"),
    ({"cx": -5}, "cx"),
    ({"cy": 480}, "cy"),
    ({"cx": "1e400"}, "cx"),
]


@pytest.mark.parametrize("params, field", BAD_INTRINSICS)
def test_bad_intrinsics_are_a_422_naming_the_field(url, params, field):
    r = upload(url, wide_scene(), **params)
    assert r.status_code == 422, r.text
    e = r.json()["error"]
    assert e["message"].startswith(f"field {field}") and e["details"]["field"] == field
    m = httpx.post(
        f"{url}/v1/score",
        files={"depth": ("d.npy", npy(wide_scene()), "application/x-npy")},
        data={"grasps": json.dumps({"grasps": grasps_at(k=1).tolist()}), **{k: str(v) for k, v in params.items()}},
    )
    assert m.status_code == 422 and m.json()["error"]["details"]["field"] == field


@pytest.mark.parametrize(
    "intr, field",
    [
        ([0, 525, 149.5, 149.5], "fx"),
        ([525, np.nan, 149.5, 149.5], "fy"),
        ([525, 525, 400, 149.5], "cx"),
        ([525, 525, 149.5, -1], "cy"),
    ],
)
def test_bad_npz_intrinsics_are_a_422_naming_the_field(url, intr, field):
    r = httpx.post(
        f"{url}/v1/score",
        content=npz(depth=table_scene(), grasps=grasps_at(k=1), intrinsics=intr),
        headers={"content-type": "application/x-npz"},
    )
    assert r.status_code == 422 and r.json()["error"]["details"]["field"] == field


# ---- grasps anywhere ----------------------------------------------------------------------------------------
def test_grasps_all_over_a_640x480_image_in_one_call_match_per_window_uploads(url):
    depth = wide_scene()
    g = spread_grasps(480, 640, k=40)
    one = scores(url, upload(url, depth).json()["image_id"], g)
    centres = grid_window_centers(g[:, :2], depth.shape, GEOM)
    assert one["windows"] == len(np.unique(centres, axis=0)) > 4
    # the corners' windows reach past the image: their centres lie within kappa of the corner
    assert np.all(np.abs(centres[:4] - g[:4, :2]) <= 36) and (centres[:4] < 48).any()
    per_window = np.empty(len(g))
    for c in np.unique(centres, axis=0):
        m = np.all(centres == c, axis=1)
        iid = upload(url, depth, center_u=c[0], center_v=c[1]).json()["image_id"]
        per_window[m] = scores(url, iid, g[m])["p_success"]
    assert np.allclose(one["p_success"], per_window, atol=1e-6)


def test_grasps_outside_the_image_are_a_422_naming_them(url):
    iid = upload(url, wide_scene()).json()["image_id"]
    g = spread_grasps(480, 640, k=6)
    g[2, 0], g[4, 1] = 640.0, -3.0
    r = httpx.post(f"{url}/v1/images/{iid}/scores", json={"grasps": g.tolist()})
    assert r.status_code == 422 and r.json()["error"]["details"]["grasps"] == [2, 4]
    assert "outside the 480x640 image" in r.json()["error"]["message"]


def test_fixed_window_keeps_the_kappa_check_in_client_pixels(url):
    up = upload(url, table_scene(360, 360), fx=630, center_u=180, center_v=180).json()
    assert up["windows"] == "fixed"
    lo, hi = up["grasp_range"]["u"]
    assert hi - lo == pytest.approx(2 * 36 * 1.2)  # kappa in the client's (longer focal length) pixels
    g = grasps_at(center=(180, 180), k=3).astype(np.float64)
    g[1, 0] = hi + 2
    r = httpx.post(f"{url}/v1/images/{up['image_id']}/scores", json={"grasps": g.tolist()})
    assert r.status_code == 422 and r.json()["error"]["details"]["grasps"] == [1]


# ---- lazy window cache --------------------------------------------------------------------------------------
def test_windows_are_encoded_once_when_first_needed(url):
    depth = wide_scene() + 0.002
    up = upload(url, depth).json()
    iid, before = up["image_id"], metric(url, "vgq_windows_encoded_total")
    assert metric(url, "vgq_windows_encoded_total") == before  # an upload encodes nothing
    a = np.array([[100, 100], [110, 90], [400, 300], [600, 50]], np.float64)
    g = np.column_stack([a, np.full(4, 0.65), np.tile([1.0, 0, 0, 0], (4, 1))])
    first = scores(url, iid, g)
    assert first["windows"] == first["windows_encoded"] == 3
    again = scores(url, iid, g[::-1])
    assert again["windows_encoded"] == 0 and np.allclose(again["p_success"], first["p_success"][::-1], atol=1e-6)
    more = scores(url, iid, np.vstack([g, [[320, 240, 0.65, 1, 0, 0, 0]]]))
    assert more["windows"] == 4 and more["windows_encoded"] == 1
    assert metric(url, "vgq_windows_encoded_total") == before + 4
    up2 = upload(url, depth).json()
    assert up2["cached"] is True and scores(url, up2["image_id"], g)["windows_encoded"] == 0


def test_eviction_by_bytes_counts_the_depth_image_and_the_windows(model_dir):
    depth_bytes = 300 * 300 * 4
    with running_service(model_dir, "--cache-bytes", str(2 * depth_bytes + 4096)) as u, ServiceClient(u) as c:
        a = c.upload(table_scene() + 0.001)
        b = c.upload(table_scene() + 0.002)
        s = httpx.get(f"{u}/v1/cache").json()
        assert s["entries"] == 2 and s["bytes"] > 2 * depth_bytes and s["evictions"] == 0
        g = spread_grasps(300, 300, k=30)
        assert len(c.score(b, g)) == 30  # B's new windows (4.2 kB each) push the cache over its bound
        s = httpx.get(f"{u}/v1/cache").json()
        assert s["evictions"] == 1 and s["entries"] == 1 and s["bytes"] <= 2 * depth_bytes + 4096
        with pytest.raises(ServiceError) as e:
            c.score(a, g)
        assert e.value.status == 404


# ---- out-of-distribution flags -----------------------------------------------------------------------------
def flagged_scene():
    d = table_scene()
    d[140:146, 140:146] = 0.0  # a hole under grasp 2
    d[102:140, 174:270] = 0.0  # 40% of the window right of the centre missing (10% of the centre one)
    return d


def flagged_grasps():
    g = np.tile([149.5, 149.5, 0.65, 1.0, 0.0, 0.0, 0.0], (5, 1))
    g[1, 3:] = [0.0, 1.0, 0.0, 0.0]  # 180 deg about x: approach away from the camera
    g[2, :2] = [142, 143]  # on the hole
    g[3, 2] = 2.5  # far beyond the training z range
    g[4, :2] = [230, 170]  # in the window right of the centre: mostly without depth
    return g


def test_each_grasp_carries_the_reasons_its_score_is_not_to_be_trusted(url):
    up = upload(url, flagged_scene()).json()
    r = scores(url, up["image_id"], flagged_grasps())
    assert r["ood"] == [
        [],
        ["approach_away_from_camera"],
        ["center_on_missing_depth"],
        ["z_outside_training_range"],
        ["window_mostly_missing"],
    ]
    assert r["ood_mask"] == [0, 1, 4, 2, 8]
    info = httpx.get(f"{url}/v1/model").json()["ood"]
    assert info["flags"]["2"] == "z_outside_training_range" and info["z_range"][0] < 0.65 < info["z_range"][1]
    assert info["z_range_source"]


def test_strict_turns_flags_into_a_422_listing_grasps_and_reasons(url):
    iid = upload(url, flagged_scene()).json()["image_id"]
    r = httpx.post(
        f"{url}/v1/images/{iid}/scores", params={"strict": "true"}, json={"grasps": flagged_grasps().tolist()}
    )
    assert r.status_code == 422
    e = r.json()["error"]
    assert e["details"]["grasps"] == [1, 2, 3, 4] and e["details"]["ood"]["3"] == ["z_outside_training_range"]
    assert "strict" in e["message"] and "approach_away_from_camera" in e["message"]
    ok = scores(url, iid, flagged_grasps()[:1], strict="true")
    assert ok["ood"] == [[]]
    shot = httpx.post(
        f"{url}/v1/score?strict=1",
        content=npz(depth=flagged_scene(), grasps=flagged_grasps()),
        headers={"content-type": "application/x-npz"},
    )
    assert shot.status_code == 422 and shot.json()["error"]["details"]["grasps"] == [1, 2, 3, 4]
    bad = httpx.post(
        f"{url}/v1/images/{iid}/scores", params={"strict": "maybe"}, json={"grasps": flagged_grasps().tolist()}
    )
    assert bad.status_code == 422 and bad.json()["error"]["details"]["field"] == "strict"


def test_binary_answers_count_flagged_grasps_in_a_header(url):
    iid = upload(url, flagged_scene()).json()["image_id"]
    r = httpx.post(
        f"{url}/v1/images/{iid}/scores",
        content=flagged_grasps().astype("<f4").tobytes(),
        headers={"content-type": "application/octet-stream", "accept": "application/octet-stream"},
    )
    assert r.status_code == 200 and len(r.content) == 5 * 4
    assert r.headers["x-ood-count"] == "4" and r.headers["x-calibrated"] in ("true", "false")


# ---- calibrated probabilities -------------------------------------------------------------------------------
def test_uncalibrated_model_returns_the_raw_score_and_says_so(url):
    assert httpx.get(f"{url}/v1/model").json()["calibrated"] is False
    r = scores(url, upload(url, table_scene()).json()["image_id"], grasps_at(k=8))
    assert r["calibrated"] is False and np.allclose(r["p_success"], r["raw_score"], atol=1e-7)


def test_calibrated_model_maps_raw_scores_through_the_card_s_calibration(model_dir, tmp_path):
    cal = Calibration("platt", 0.8, -0.3, 0.19, 0.047)
    calibrated = tmp_path / "calibrated"
    shutil.copytree(model_dir, calibrated)
    card = json.loads((calibrated / "model_card.json").read_text())
    card["calibration"] = cal.to_dict()
    (calibrated / "model_card.json").write_text(json.dumps(card))
    with running_service(calibrated) as u:
        assert httpx.get(f"{u}/v1/model").json()["calibrated"] is True
        r = scores(u, upload(u, table_scene()).json()["image_id"], grasps_at(k=16))
        raw = np.array(r["raw_score"])
        assert r["calibrated"] is True and np.allclose(r["p_success"], cal.apply(raw), atol=1e-6)
        assert not np.allclose(r["p_success"], raw, atol=1e-3)


# ---- held-out images, bundled model: one upload + one call per image vs one upload per window ---------------
def heldout_balanced_accuracies(url: str) -> dict:
    """Balanced accuracy (raw score > 0.5) of the held-out grasps scored (a) per window: each
    image uploaded once per window centre of examples/heldout_images.npz (the crop stage's
    draw), (b) anywhere: each image uploaded once, all its grasps in one score call."""
    import sys

    from servers import ROOT

    sys.path.insert(0, str(ROOT / "examples"))
    from heldout import load_heldout_images

    held = load_heldout_images()
    per_window, anywhere = np.empty(len(held)), np.empty(len(held))
    windows = 0
    with ServiceClient(url) as c:
        for i in range(len(held.depth)):
            rows = np.flatnonzero(held.image_index == i)
            if not len(rows):
                continue
            r = c.score_details(c.upload(held.depth[i]), held.grasps[rows])
            anywhere[rows], windows = r["raw_score"], windows + r["windows"]
            for ctr in np.unique(held.center[rows], axis=0):
                m = rows[np.all(held.center[rows] == ctr, axis=1)]
                per_window[m] = c.score_details(c.upload(held.depth[i], center=tuple(map(float, ctr))), held.grasps[m])[
                    "raw_score"
                ]

    def ba(p):
        y, pred = held.labels == 1, p > 0.5
        return float((pred[y].mean() + (~pred[~y]).mean()) / 2)

    return {
        "grasps": len(held),
        "images": len(held.depth),
        "per_window": ba(per_window),
        "anywhere": ba(anywhere),
        "uploads_per_window": len(np.unique(np.column_stack([held.image_index, held.center]), axis=0)),
        "windows_anywhere": windows,
    }


BUNDLED = __import__("servers").ROOT / "models" / "fast-vgqcnn-default"


@pytest.mark.skipif(not (BUNDLED / "model_card.json").is_file(), reason="no bundled model")
def test_one_upload_per_image_scores_heldout_grasps_as_well_as_per_window_uploads():
    with running_service(BUNDLED) as u:
        r = heldout_balanced_accuracies(u)
    print(r)
    assert r["grasps"] >= 500 and r["uploads_per_window"] > r["images"]
    assert abs(r["anywhere"] - r["per_window"]) <= 0.02, r


if __name__ == "__main__":  # measure by hand: python tests/test_service_any_camera.py
    import sys

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
    with running_service(BUNDLED) as u:
        print(heldout_balanced_accuracies(u))


def test_python_client_sends_intrinsics_and_returns_flags(url):
    depth, g = table_scene(360, 360), flagged_grasps()
    g[:, :2] = g[:, :2] * 1.2 + 0.1  # the 300 px grasps in the 630 px camera's pixels
    cam = Intrinsics(fx=630.0, fy=630.0, cx=179.5, cy=179.5, width=360, height=360)
    with ServiceClient(url) as c:
        iid = c.upload(depth, intrinsics=cam)
        assert c.last_upload["intrinsics_assumed"] == [] and c.last_upload["resampled"]["image_shape"] == [300, 300]
        assert c.upload(depth, intrinsics=(630.0, 630.0, 179.5, 179.5)) == iid
        assert c.upload(depth, intrinsics={"fx": 630.0, "fy": 630.0, "cx": 179.5, "cy": 179.5}) == iid
        r = c.score_details(iid, g)
        assert r["ood_mask"].dtype == np.uint8 and r["ood"][1] == ["approach_away_from_camera"]
        p = c.score(iid, g)
        assert np.allclose(p, r["p_success"], atol=1e-6) and c.last_ood_count == int(np.count_nonzero(r["ood_mask"]))
        once = c.score_once(depth, g, intrinsics=cam, details=True)
        assert np.allclose(once["p_success"], p, atol=1e-6)
        assert once["image_id"] == iid and once["cached"] is True  # the same .npy bytes and camera: the same id
        with pytest.raises(ServiceError) as e:
            c.score(iid, g, strict=True)
        assert e.value.status == 422 and 1 in e.value.details["grasps"]
