"""In-process units of the service's input handling and cache backend (no server)."""

from __future__ import annotations

import asyncio
import io
import struct
import zipfile

import numpy as np
import pytest
from PIL import Image

from service.cache import CachedImage, EncodedWindow, MemoryCache
from service.config import Settings, from_env
from service.depth_io import decode_depth, encode_npy, parse_npy, png_header, read_npz
from service.errors import ApiError
from service.protocol import CoalescingTransport
from service.redis_cache import (
    pack_entry,
    pack_window,
    redacted,
    unpack_entry,
    unpack_window,
)
from vgq.camera import Intrinsics, resampled_intrinsics
from vgq.crop import CropGeometry
from vgq.grasps import MAX_Z_M, GraspError, pose_rows

GEOM = CropGeometry(96, 32, 36.0)


def depth(h=40, w=50) -> np.ndarray:
    return np.full((h, w), 0.7, np.float32)


def png16(a_mm: np.ndarray) -> bytes:
    b = io.BytesIO()
    Image.fromarray(a_mm).save(b, format="PNG")
    return b.getvalue()


def zip_of(**members: bytes) -> bytes:
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", zipfile.ZIP_DEFLATED) as z:
        for k, v in members.items():
            z.writestr(k, v)
    return b.getvalue()


def status_of(fn, *a, **kw) -> tuple[int, str]:
    with pytest.raises(ApiError) as e:
        fn(*a, **kw)
    return e.value.status, e.value.message


# ---- depth decoding ------------------------------------------------------------------------------------------------
def test_npy_float64_and_big_endian_decode_to_float32_metres():
    for a in (depth().astype(np.float64), depth().astype(">f4")):
        out = decode_depth(encode_npy(a) if a.dtype == np.float64 else _raw_npy(a), "application/x-npy")
        assert out.dtype == np.float32 and out.shape == (40, 50) and np.allclose(out, 0.7)


def _raw_npy(a) -> bytes:
    b = io.BytesIO()
    np.save(b, a)
    return b.getvalue()


def test_fortran_order_npy_keeps_rows_and_columns():
    a = np.asfortranarray(np.arange(40 * 50, dtype=np.float32).reshape(40, 50) + 1)
    assert np.array_equal(decode_depth(_raw_npy(a), "application/x-npy"), a)


def test_npy_h_w_1_is_accepted_as_h_w():
    assert decode_depth(_raw_npy(depth()[..., None]), "application/x-npy").shape == (40, 50)


def test_png_millimetres_become_metres():
    out = decode_depth(png16(np.full((40, 50), 700, np.uint16)), "image/png")
    assert out.shape == (40, 50) and np.allclose(out, 0.7)


def test_png_header_is_read_without_decoding():
    body = png16(np.full((40, 50), 700, np.uint16))
    assert png_header(body) == (40, 50, 16, 0)
    assert status_of(png_header, b"\x89PNG\r\n\x1a\n")[0] == 422


def test_png_size_is_checked_before_decoding():
    body = bytearray(png16(np.full((40, 50), 700, np.uint16)))
    struct.pack_into(">II", body, 16, 5000, 5000)  # IHDR claims 5000 x 5000 (CRC now wrong too)
    status, msg = status_of(decode_depth, bytes(body), "image/png", max_side=4096)
    assert status == 422 and "5000x5000" in msg


def test_raw_float32_with_shape():
    assert decode_depth(depth().tobytes(), "application/octet-stream", width=50, height=40).shape == (40, 50)


def test_content_type_parameters_and_case_are_ignored():
    assert decode_depth(_raw_npy(depth()), "Application/X-NPY; charset=binary").shape == (40, 50)


@pytest.mark.parametrize("value,word", [(np.nan, "non-finite"), (-np.inf, "non-finite"), (-1e-3, "negative")])
def test_invalid_depth_values_are_named(value, word):
    d = depth()
    d[3, 4] = value
    status, msg = status_of(decode_depth, _raw_npy(d), "application/x-npy")
    assert status == 422 and word in msg


def test_min_side_is_enforced():
    status, msg = status_of(decode_depth, _raw_npy(depth(40, 31)), "application/x-npy")
    assert status == 422 and "40x31" in msg


def test_parse_npy_refuses_more_values_than_allowed():
    status, msg = status_of(parse_npy, _raw_npy(np.zeros((100, 7))), "grasps", 70)
    assert status == 422 and "700 values" in msg


# ---- .npz ---------------------------------------------------------------------------------------------------------
def test_read_npz_returns_only_named_members():
    body = zip_of(**{"depth.npy": b"a", "grasps.npy": b"b", "extra.npy": b"c"})
    assert read_npz(body, 1000, names=("depth", "grasps")) == {"depth": b"a", "grasps": b"b"}


def test_read_npz_refuses_too_many_members():
    body = zip_of(**{f"m{i}.npy": b"x" for i in range(9)})
    status, msg = status_of(read_npz, body, 1000)
    assert status == 422 and "9 members" in msg


def test_read_npz_refuses_declared_total_over_the_limit():
    body = zip_of(**{"depth.npy": b"\0" * 600, "grasps.npy": b"\0" * 600})
    status, msg = status_of(read_npz, body, 1000)
    assert status == 413 and "1200 in all" in msg


# ---- grasps ---------------------------------------------------------------------------------------------------------
def _grasps(k=4) -> np.ndarray:
    g = np.zeros((k, 7))
    g[:, :2] = 149.5
    g[:, 2] = 0.6
    g[:, 3:] = [0.5, 0.5, 0.5, 0.5]
    return g


@pytest.mark.parametrize("scale", [1e-5, 3.0, 1e200])
def test_quaternion_scale_does_not_change_pose_rows(scale):
    g = _grasps()
    s = g.copy()
    s[:, 3:] *= scale
    c = np.array([149.5, 149.5])
    assert np.allclose(pose_rows(s, c, GEOM, 16), pose_rows(g, c, GEOM, 16))


def test_depth_beyond_bound_is_rejected():
    g = _grasps()
    g[1, 2] = MAX_Z_M * 1.5
    with pytest.raises(GraspError, match="depth z") as e:
        pose_rows(g, np.array([149.5, 149.5]), GEOM, 16)
    assert e.value.indices == [1] and isinstance(e.value, ValueError)


# ---- redis entry format -------------------------------------------------------------------------------------------
def _entry(fixed=True) -> CachedImage:
    cam = Intrinsics(fx=600.0, fy=610.0, cx=170.0, cy=160.0, width=320, height=300)
    res = resampled_intrinsics(cam, 525 / 600, 525 / 610)
    depth = np.random.default_rng(0).uniform(0.5, 0.8, (res.height, res.width)).astype(np.float32)
    depth[:10] = 0.0
    return CachedImage(depth, cam, res, ("cy",), np.array([140.5, 151.5]) if fixed else None)


@pytest.mark.parametrize("fixed", [True, False])
def test_cache_entry_bytes_round_trip(fixed):
    e = _entry(fixed)
    back = unpack_entry(pack_entry(e))
    assert np.array_equal(back.depth, e.depth) and back.depth.dtype == np.float32
    assert back.camera == e.camera and back.resampled == e.resampled and back.assumed == ("cy",)
    assert (back.fixed_center is None) == (not fixed) and (
        not fixed or np.array_equal(back.fixed_center, e.fixed_center)
    )
    assert back.windows == {}
    assert back.up is None and back.roll == 0.0


def test_a_level_entry_keeps_its_up_and_roll_through_the_bytes():
    e = _entry(False)
    e.up, e.roll = (0.5, 0.1, -0.8), -1.37340076694502
    back = unpack_entry(pack_entry(e))
    assert back.up == e.up and back.roll == e.roll and back.up_from is None
    e.up_from = "table"
    assert unpack_entry(pack_entry(e)).up_from == "table"


def test_window_entry_bytes_round_trip():
    w = EncodedWindow(np.arange(1024, dtype=np.float32).reshape(1, 1024), 0.0375)
    data = pack_window(w)
    assert len(data) < 4096 + 32
    back = unpack_window(data)
    assert np.array_equal(back.term, w.term) and back.term.shape == (1, 1024) and back.missing_fraction == 0.0375
    with pytest.raises(ValueError):
        unpack_window(data[:-4])


@pytest.mark.parametrize("data", [b"", b"VGQ1", b"XXXX" + b"\0" * 4200, b"VGQ3" + b"\xff" * 40])
def test_cache_entry_garbage_is_a_value_error(data):
    with pytest.raises(ValueError):
        unpack_entry(data)


def test_cache_entry_truncated_is_a_value_error():
    with pytest.raises(ValueError):
        unpack_entry(pack_entry(_entry())[:-4])


def test_memory_cache_recounts_bytes_when_windows_are_added_and_evicts_by_bytes():
    e1, e2 = _entry(), _entry(False)
    n1, n2 = e1.nbytes, e2.nbytes
    w = EncodedWindow(np.zeros((1, 1024), np.float32), 0.0)
    cache = MemoryCache(10, n1 + n2 + w.nbytes + 1000)
    cache.put("a", e1)
    cache.put("b", e2)
    assert cache.bytes == n1 + n2 and cache.evictions == 0
    cache.add_windows("b", e2, {(0, 0): w})
    assert cache.bytes == n1 + n2 + w.nbytes and len(cache) == 2  # 4.2 kB more still fits
    cache.add_windows("b", e2, {(72, 0): w})  # now it does not: the least recently used image goes
    assert cache.get("a") is None and cache.get("b") is e2 and cache.evictions == 1 and cache.bytes == e2.nbytes
    assert cache.stats()["windows"] == 2 and cache.stats()["windows_encoded"] == 2


def test_redis_url_password_is_redacted():
    assert redacted("redis://:hunter2@cache:6379/0") == "redis://:***@cache:6379/0"
    assert redacted("redis://127.0.0.1:6379/0") == "redis://127.0.0.1:6379/0"


# ---- settings -----------------------------------------------------------------------------------------------------
def test_limits_come_from_the_environment():
    s = from_env(
        {
            "VGQ_MAX_BODY_BYTES": "4096",
            "VGQ_MAX_GRASPS": "7",
            "VGQ_CACHE_BYTES": "8192",
            "VGQ_REQUEST_TIMEOUT_S": "2.5",
            "VGQ_CACHE_TTL_S": "60",
            "VGQ_CACHE_BACKEND": "redis",
        }
    )
    assert (s.max_body_bytes, s.max_grasps, s.cache_bytes, s.request_timeout_s, s.cache_ttl_s, s.cache_backend) == (
        4096,
        7,
        8192,
        2.5,
        60.0,
        "redis",
    )


@pytest.mark.parametrize(
    "kw,word",
    [
        ({"cache_ttl_s": 0}, "cache_ttl_s"),
        ({"request_timeout_s": -1}, "request_timeout_s"),
        ({"max_body_bytes": 10}, "max_body_bytes"),
        ({"cache_backend": "memcached"}, "cache_backend"),
        ({"cache_backend": "redis", "redis_url": "localhost:6379"}, "redis_url"),
        ({"workers": 2}, "workers = 2 needs cache_backend 'redis'"),
        ({"port": 65536}, "port must be an integer in \\[0, 65535\\]"),
    ],
)
def test_bad_limits_are_refused_by_name(kw, word):
    with pytest.raises(ValueError, match=word):
        Settings(**kw)


def test_several_workers_need_the_shared_cache(capsys):
    """Each worker has its own memory: with --workers 2 an upload would be a 404 on the other worker."""
    from service.config import parse_args

    assert Settings(workers=2, cache_backend="redis").ort_threads >= 1
    with pytest.raises(SystemExit) as e:
        parse_args(["--workers", "2"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and "workers = 2 needs cache_backend 'redis'" in err


def test_head_precision_setting_is_checked():
    with pytest.raises(ValueError, match="head_precision"):
        Settings(head_precision="bf16")


def test_int8_head_asked_of_a_model_without_one_is_a_clear_error(model_dir):
    from service.runtime import FastModel, ModelError

    assert FastModel(model_dir).head_precision == "fp32"  # auto falls back to fp32
    with pytest.raises(ModelError, match="no int8 head"):
        FastModel(model_dir, head_precision="int8")


def test_a_model_trained_on_turned_windows_is_refused_not_served_unturned(model_dir, tmp_path):
    import json
    import shutil

    from service.runtime import FastModel, ModelError

    turned = tmp_path / "turned"
    shutil.copytree(model_dir, turned)
    card = json.loads((turned / "model_card.json").read_text())
    card["geometry"].update(align_jaw=True, kappa_px=0.0)
    (turned / "model_card.json").write_text(json.dumps(card))
    with pytest.raises(ModelError, match="crops turned to the jaw axis.*cannot serve it"):
        FastModel(turned)


# ---- the one number path, paths in answers, multipart without copies ------------------------------------------------
@pytest.mark.parametrize("raw", ["inf", "-inf", "nan", "1e400", "9" * 400, "2.5", "abc", True, "-1", "0", "3e9"])
def test_integer_fields_refuse_what_is_not_a_usable_integer(raw):
    from service.numbers import WIDTH

    status, msg = status_of(WIDTH.parse, raw)
    assert status == 422 and "field width must be" in msg


def test_an_empty_number_or_choice_is_refused_not_taken_as_absent():
    from service.numbers import FX, LEVEL

    assert status_of(FX.parse, "") == (422, "field fx must be a number, got ''")
    status, msg = status_of(LEVEL.parse, "")
    assert status == 422 and msg.startswith("field level must be 'table'")


def test_numbers_accept_text_and_array_elements():
    from service.numbers import CENTER_U, FX, WIDTH

    assert WIDTH.parse("300") == 300 and WIDTH.parse("300.0") == 300 and WIDTH.parse(None) is None
    assert CENTER_U.parse(np.float64(12.5)) == 12.5 and CENTER_U.parse("0") == 0.0
    assert status_of(CENTER_U.parse, np.float32(np.nan))[1] == "field center_u must be finite, got np.float32(nan)"
    assert status_of(FX.parse, "0")[0] == 422 and FX.schema()["exclusiveMinimum"] == 0.0


def test_absolute_paths_are_cut_to_their_last_part():
    from service.errors import redact_paths

    doc = {
        "root": "/home/ci/data/crops",
        "msg": "cannot load model from /srv/models/fast: no card",
        "rel": "examples/x.npy",
        "win": "C:\\build\\data\\shard.npz",
        "n": 3,
        "list": ["/a/b/c.json"],
        "quantized_nodes": ["/head/fc5/Gemm"],
        "url": "redis://cache:6379/0 and http://host/a/b/c",
    }
    out = redact_paths(doc)
    assert (
        out["root"] == "crops"
        and out["msg"] == "cannot load model from fast: no card"
        and out["rel"] == "examples/x.npy"
    )
    assert out["win"] == "shard.npz" and out["n"] == 3 and out["list"] == ["c.json"]
    assert out["quantized_nodes"] == ["/head/fc5/Gemm"] and out["url"] == doc["url"]
    # the service's own routes are not host paths: a message pointing the client at one keeps it whole
    hint = "unknown or evicted image id 'x'; upload the image again (POST /v1/images)"
    assert redact_paths(hint) == hint


def test_multipart_parts_are_views_into_the_body():
    from service.oneshot import parse_multipart

    d = depth()
    body = bytearray(
        b'--b\r\nContent-Disposition: form-data; name="depth"; filename="d.npy"\r\n'
        b"Content-Type: application/x-npy\r\n\r\n"
        + _raw_npy(d)
        + b'\r\n--b\r\nContent-Disposition: form-data; name="grasps"\r\n\r\n'
        b'{"grasps": [[25, 20, 0.6, 1, 0, 0, 0]]}\r\n--b\r\nContent-Disposition: form-data; name="center_u"\r\n\r\n'
        b"24.5\r\n--b--\r\n"
    )
    shot = parse_multipart(body, "multipart/form-data; boundary=b")
    assert isinstance(shot.depth_body, memoryview) and shot.depth_body.obj is body  # no copy of the depth bytes
    assert np.array_equal(shot.decode(4096), d) and shot.numbers["center_u"] == 24.5 and shot.grasps.shape == (1, 7)


class _RecordingTransport:
    """What a CoalescingTransport hands to the real transport."""

    def __init__(self):
        self.sends, self.closed, self.aborted = [], False, False

    def writelines(self, chunks):
        self.sends.append(b"".join(chunks))

    def is_closing(self):
        return self.closed or self.aborted

    def close(self):
        self.closed = True

    def abort(self):
        self.aborted = True

    def get_extra_info(self, name, default=None):
        return ("127.0.0.1", 1) if name == "peername" else default


def test_coalescing_transport_sends_one_step_s_writes_together_in_order():
    async def run():
        raw = _RecordingTransport()
        t = CoalescingTransport(raw, asyncio.get_running_loop())
        t.write(b"HTTP/1.1 200 OK\r\n\r\n")
        t.write(b"body")
        assert raw.sends == []  # nothing leaves before the step ends
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert raw.sends == [b"HTTP/1.1 200 OK\r\n\r\nbody"]
        t.write(b"last")
        t.close()  # what is pending leaves before the close
        assert raw.sends[-1] == b"last" and raw.closed
        t2 = CoalescingTransport(raw2 := _RecordingTransport(), asyncio.get_running_loop())
        t2.write(b"dropped")
        t2.abort()
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert raw2.sends == [] and raw2.aborted
        assert t.get_extra_info("peername") == ("127.0.0.1", 1)  # the rest is the transport's

    asyncio.run(run())


@pytest.mark.parametrize("raw, expected", [(None, False), ("true", True), ("1", True), (" Off ", False), ("0", False)])
def test_strict_flag_reads_true_false_and_absent(raw, expected):
    from service.numbers import parse_flag

    assert parse_flag("strict", raw) is expected


@pytest.mark.parametrize("raw", ["", "maybe", "2"])
def test_strict_flag_refuses_anything_else_even_empty(raw):
    """``?strict=`` is a value the schema's boolean does not allow (schemathesis sends it): 422."""
    from service.numbers import parse_flag

    with pytest.raises(ApiError) as e:
        parse_flag("strict", raw)
    assert e.value.status == 422 and "field strict must be true or false" in e.value.message
