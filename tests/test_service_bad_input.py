"""The bad-input matrix against the real service (uvicorn subprocess on loopback): every row
gets a 4xx whose message names the problem; never a 5xx, a hang or a wrong score."""

from __future__ import annotations

import io
import json
import socket
import struct
import time
import zipfile
import zlib

import httpx
import numpy as np
import pytest
from conftest import table_scene
from PIL import Image
from servers import grasps_at, running_service

MAX_BODY = 2_000_000
MAX_GRASPS = 64
TIMEOUT_S = 1.0
NPY = "application/x-npy"
CENTER = (149.5, 149.5)


def npy(a, allow_pickle=False) -> bytes:
    b = io.BytesIO()
    np.save(b, a, allow_pickle=allow_pickle)
    return b.getvalue()


def npy_header_only(shape, descr="<f4") -> bytes:
    """A .npy header promising ``shape`` followed by a few data bytes."""
    header = repr({"descr": descr, "fortran_order": False, "shape": tuple(shape)}).encode()
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + b"\0" * 64


def png(a: np.ndarray) -> bytes:
    b = io.BytesIO()
    Image.fromarray(a).save(b, format="PNG")
    return b.getvalue()


def png_claiming(width: int, height: int) -> bytes:
    """A 16-bit grayscale PNG whose header claims width x height (a decompression bomb's header)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 65536, 9))
        + chunk(b"IEND", b"")
    )


def npz(**arrays) -> bytes:
    b = io.BytesIO()
    np.savez(b, **arrays)
    return b.getvalue()


def zip_bomb(member_bytes: int, lie_size: int | None = None) -> bytes:
    """An .npz whose 'depth' member unpacks to ``member_bytes`` zeros (optionally with the
    size fields in the archive rewritten to ``lie_size``) plus a valid 'grasps' member."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("depth.npy", npy_header_only((300, 300))[:128] + b"\0" * member_bytes)
        z.writestr("grasps.npy", npy(grasps_at(k=2)))
    b = bytearray(buf.getvalue())
    if lie_size is not None:
        struct.pack_into("<I", b, 22, lie_size)  # local header of the first member
        cd = b.find(b"PK\x01\x02")
        struct.pack_into("<I", b, cd + 24, lie_size)  # its central directory entry
    return bytes(b)


def with_depth(**changes) -> np.ndarray:
    d = table_scene()
    for (r, c), v in changes.get("pixels", {}).items():
        d[r, c] = v
    return d


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(
        model_dir,
        "--max-grasps",
        str(MAX_GRASPS),
        "--max-body-bytes",
        str(MAX_BODY),
        "--request-timeout-s",
        str(TIMEOUT_S),
        "--max-image-side",
        "1024",
    ) as u:
        yield u


@pytest.fixture(scope="module")
def image_id(url):
    r = httpx.post(f"{url}/v1/images", content=npy(table_scene()), headers={"content-type": NPY})
    assert r.status_code == 200
    return r.json()["image_id"]


def assert_error(r: httpx.Response, status: int, *words: str) -> None:
    assert r.status_code == status, (r.status_code, r.text[:300])
    msg = r.json()["error"]["message"]
    for w in words:
        assert w.lower() in msg.lower(), (w, msg)


#: integer fields given as text that is not a usable integer (each was a 500 once: ``int(float("inf"))``)
BAD_INTEGERS = [
    ("inf", "inf"),
    ("minus-inf", "-inf"),
    ("nan", "nan"),
    ("1e400", "1e400"),
    ("400-digits", "9" * 400),
    ("fraction", "300.5"),
    ("true", "true"),
    ("negative", "-300"),
    ("zero", "0"),
    ("huge", "1e12"),
]


# ---- uploads: (name, body, content type, query params, status, words in the message) ----------------------------
nan_depth = with_depth(pixels={(5, 5): np.nan})
inf_depth = with_depth(pixels={(5, 5): np.inf, (6, 6): -np.inf})
neg_depth = with_depth(pixels={(7, 7): -0.1})
UPLOADS = [
    ("npy-truncated", lambda: npy(table_scene())[:-100], NPY, {}, 422, ["truncated"]),
    ("npy-padded", lambda: npy(table_scene()) + b"\0" * 8, NPY, {}, 422, ["header promises"]),
    (
        "npy-corrupt-header",
        lambda: b"\x93NUMPY\x01\x00\x20\x00{'descr': <f4, garbage" + b"\0" * 200,
        NPY,
        {},
        422,
        [".npy"],
    ),
    ("npy-not-npy", lambda: b"hello world, not an array at all", NPY, {}, 422, ["not a valid .npy"]),
    ("npy-empty-body", lambda: b"", NPY, {}, 422, ["empty"]),
    ("npy-int32", lambda: npy(np.full((300, 300), 700, np.int32)), NPY, {}, 422, ["dtype int32"]),
    ("npy-float16", lambda: npy(table_scene().astype(np.float16)), NPY, {}, 422, ["dtype float16"]),
    ("npy-complex", lambda: npy(table_scene().astype(np.complex64)), NPY, {}, 422, ["dtype complex64"]),
    (
        "npy-object-pickle",
        lambda: npy(np.array([{"a": 1}] * 4, dtype=object), allow_pickle=True),
        NPY,
        {},
        422,
        ["dtype object"],
    ),
    ("npy-unicode", lambda: npy(np.array([["ab"] * 40] * 40)), NPY, {}, 422, ["dtype"]),
    ("npy-zero-size", lambda: npy(np.zeros((0, 0), np.float32)), NPY, {}, 422, ["0x0", "[32, 1024]"]),
    ("npy-1d", lambda: npy(np.full(300, 0.7, np.float32)), NPY, {}, 422, ["shape (300,)"]),
    ("npy-3d", lambda: npy(np.full((2, 64, 64), 0.7, np.float32)), NPY, {}, 422, ["shape (2, 64, 64)"]),
    ("npy-scalar", lambda: npy(np.float32(0.7)), NPY, {}, 422, ["shape ()"]),
    ("npy-too-small", lambda: npy(np.full((8, 8), 0.7, np.float32)), NPY, {}, 422, ["8x8"]),
    ("npy-huge-dims", lambda: npy_header_only((100000, 100000)), NPY, {}, 422, ["100000x100000"]),
    ("npy-negative-dims", lambda: npy_header_only((-300, 300)), NPY, {}, 422, ["non-negative"]),
    ("npy-overflowing-dims", lambda: npy_header_only((2**32, 2**32)), NPY, {}, 422, ["4294967296x4294967296"]),
    ("npy-nan", lambda: npy(nan_depth), NPY, {}, 422, ["1 non-finite"]),
    ("npy-inf", lambda: npy(inf_depth), NPY, {}, 422, ["2 non-finite"]),
    ("npy-negative", lambda: npy(neg_depth), NPY, {}, 422, ["1 negative"]),
    ("npy-all-zero", lambda: npy(np.zeros((300, 300), np.float32)), NPY, {}, 422, ["no valid"]),
    ("png-truncated", lambda: png(np.full((300, 300), 700, np.uint16))[:-200], "image/png", {}, 422, ["PNG"]),
    (
        "png-corrupt",
        lambda: png(np.full((300, 300), 700, np.uint16))[:40] + b"\xff" * 400,
        "image/png",
        {},
        422,
        ["PNG"],
    ),
    ("png-bad-signature", lambda: b"GIF89a" + b"\0" * 100, "image/png", {}, 422, ["signature"]),
    (
        "png-8bit",
        lambda: png(np.full((300, 300), 70, np.uint8)),
        "image/png",
        {},
        422,
        ["8-bit grayscale", "expected 16-bit"],
    ),
    ("png-rgb", lambda: png(np.full((300, 300, 3), 70, np.uint8)), "image/png", {}, 422, ["8-bit RGB"]),
    ("png-bomb-100000", lambda: png_claiming(100000, 100000), "image/png", {}, 422, ["100000x100000"]),
    (
        "png-8bit-claims",
        lambda: png_claiming(300, 300)[:24] + b"\x08" + png_claiming(300, 300)[25:],
        "image/png",
        {},
        422,
        ["8-bit"],
    ),
    ("png-bomb-1025", lambda: png_claiming(1025, 300), "image/png", {}, 422, ["300x1025"]),
    ("png-zero-size", lambda: png_claiming(0, 0), "image/png", {}, 422, ["0x0"]),
    ("png-all-zero", lambda: png(np.zeros((300, 300), np.uint16)), "image/png", {}, 422, ["no valid"]),
    ("raw-no-shape", lambda: table_scene().tobytes(), "application/octet-stream", {}, 422, ["width and height"]),
    (
        "raw-wrong-length",
        lambda: table_scene().tobytes()[:-4],
        "application/octet-stream",
        {"width": 300, "height": 300},
        422,
        ["359996 bytes"],
    ),
    (
        "raw-huge-dims",
        lambda: b"\0" * 1024,
        "application/octet-stream",
        {"width": 100000, "height": 100000},
        422,
        ["100000x100000"],
    ),
    (
        "raw-negative-dims",
        lambda: b"\0" * 1024,
        "application/octet-stream",
        {"width": -16, "height": -16},
        422,
        ["width", ">= 1"],
    ),
    (
        "raw-nan",
        lambda: nan_depth.tobytes(),
        "application/octet-stream",
        {"width": 300, "height": 300},
        422,
        ["non-finite"],
    ),
    (
        "width-not-integer",
        lambda: b"\0" * 1024,
        "application/octet-stream",
        {"width": "abc", "height": 3},
        422,
        ["width"],
    ),
    ("text-plain", lambda: npy(table_scene()), "text/plain", {}, 415, ["text/plain", "application/x-npy"]),
    ("no-content-type", lambda: npy(table_scene()), None, {}, 415, ["content type"]),
    ("json-as-depth", lambda: b'{"depth": [[1]]}', "application/json", {}, 415, ["application/json"]),
    ("centre-outside", lambda: npy(table_scene()), NPY, {"center_u": 400, "center_v": 10}, 422, ["window centre"]),
    ("centre-nan", lambda: npy(table_scene()), NPY, {"center_u": "nan"}, 422, ["center_u", "finite"]),
    ("centre-negative", lambda: npy(table_scene()), NPY, {"center_u": -3}, 422, ["center_u", ">= 0"]),
    ("centre-inf", lambda: npy(table_scene()), NPY, {"center_v": "inf"}, 422, ["center_v", "finite"]),
    ("fx-zero", lambda: npy(table_scene()), NPY, {"fx": 0}, 422, ["fx"]),
    ("fy-nan", lambda: npy(table_scene()), NPY, {"fy": "nan"}, 422, ["fy", "finite"]),
    ("fx-negative", lambda: npy(table_scene()), NPY, {"fx": -500}, 422, ["fx", "> 0"]),
    ("fx-empty", lambda: npy(table_scene()), NPY, {"fx": ""}, 422, ["fx", "a number"]),
    *[
        (
            f"width-{name}",
            lambda: table_scene().tobytes(),
            "application/octet-stream",
            {"width": v, "height": 300},
            422,
            ["width"],
        )
        for name, v in BAD_INTEGERS
    ],
    *[
        (
            f"height-{name}",
            lambda: table_scene().tobytes(),
            "application/octet-stream",
            {"width": 300, "height": v},
            422,
            ["height"],
        )
        for name, v in BAD_INTEGERS
    ],
]


@pytest.mark.parametrize("name,body,ct,params,status,words", UPLOADS, ids=[u[0] for u in UPLOADS])
def test_bad_upload(url, name, body, ct, params, status, words):
    headers = {} if ct is None else {"content-type": ct}
    r = httpx.post(f"{url}/v1/images", content=body(), headers=headers, params=params, timeout=10)
    assert_error(r, status, *words)


# ---- scoring: (name, body, content type, status, words) -------------------------------------------------------------
def _json(obj) -> bytes:
    return json.dumps(obj).encode()


def _bin(g) -> bytes:
    return np.ascontiguousarray(g, "<f4").tobytes()


def _g(**cells) -> np.ndarray:
    g = grasps_at(k=6).astype(np.float64)
    for key, v in cells.items():  # "r2c3" -> g[2, 3]
        r, c = key[1:].split("c")
        g[int(r), int(c)] = v
    return g


SCORES = [
    ("json-malformed", lambda: b'{"grasps": [[1, 2', "application/json", 400, ["not valid JSON"]),
    ("json-nan-literal", lambda: b'{"grasps": [[NaN, 1, 1, 1, 0, 0, 0]]}', "application/json", 400, ["not valid JSON"]),
    ("json-overflow", lambda: b'{"grasps": [[1e999, 1, 1, 1, 0, 0, 0]]}', "application/json", 400, ["infinity"]),
    ("json-not-object", lambda: b"[[1, 2, 3, 4, 5, 6, 7]]", "application/json", 422, ['"grasps"']),
    ("json-missing-grasps", lambda: b'{"poses": []}', "application/json", 422, ['"grasps"']),
    ("json-grasps-not-list", lambda: b'{"grasps": "abc"}', "application/json", 422, ['"grasps"']),
    ("json-row-of-6", lambda: _json({"grasps": [[150, 150, 0.6, 1, 0, 0]]}), "application/json", 422, ["7 numbers"]),
    (
        "json-ragged",
        lambda: _json({"grasps": [[150, 150, 0.6, 1, 0, 0, 0], [1]]}),
        "application/json",
        422,
        ["7 numbers"],
    ),
    (
        "json-strings",
        lambda: _json({"grasps": [["a", "b", "c", "d", "e", "f", "g"]]}),
        "application/json",
        422,
        ["7 numbers"],
    ),
    ("json-nested", lambda: _json({"grasps": [[[1] * 7] * 7]}), "application/json", 422, ["7 numbers"]),
    (
        "json-object-missing-q",
        lambda: _json({"grasps": [{"u": 150, "v": 150, "z": 0.6}]}),
        "application/json",
        422,
        ['"q"'],
    ),
    (
        "json-object-q-number",
        lambda: _json({"grasps": [{"u": 150, "v": 150, "z": 0.6, "q": 1}]}),
        "application/json",
        422,
        ['"q"'],
    ),
    ("json-true", lambda: b'{"grasps": [[150, 150, 0.6, true, 0, 0, 0]]}', "application/json", 422, ["true / false"]),
    (
        "json-false-object",
        lambda: b'{"grasps": [{"u": 150, "v": 150, "z": false, "q": [1, 0, 0, 0]}]}',
        "application/json",
        422,
        ["true / false"],
    ),
    ("k-zero", lambda: _json({"grasps": []}), "application/json", 422, ["k = 0"]),
    ("k-zero-binary", lambda: b"", "application/octet-stream", 422, ["k = 0"]),
    (
        "k-over-limit",
        lambda: _bin(grasps_at(k=MAX_GRASPS + 1)),
        "application/octet-stream",
        422,
        [f"at most {MAX_GRASPS}"],
    ),
    ("binary-not-28-multiple", lambda: b"\0" * 30, "application/octet-stream", 422, ["multiple of 28"]),
    ("nan-u", lambda: _bin(_g(r1c0=np.nan)), "application/octet-stream", 422, ["non-finite"]),
    ("inf-z", lambda: _bin(_g(r2c2=np.inf)), "application/octet-stream", 422, ["non-finite"]),
    ("nan-quaternion", lambda: _bin(_g(r3c5=np.nan)), "application/octet-stream", 422, ["non-finite"]),
    ("z-zero", lambda: _bin(_g(r0c2=0.0)), "application/octet-stream", 422, ["depth z outside (0, 10]"]),
    ("z-negative", lambda: _bin(_g(r0c2=-0.5)), "application/octet-stream", 422, ["depth z outside (0, 10]"]),
    ("z-absurd", lambda: _json({"grasps": _g(r0c2=1e300).tolist()}), "application/json", 422, ["depth z outside"]),
    (
        "zero-quaternion",
        lambda: _bin(_g(r4c3=0, r4c4=0, r4c5=0, r4c6=0)),
        "application/octet-stream",
        422,
        ["zero quaternion"],
    ),
    (
        "tiny-quaternion",
        lambda: _json({"grasps": (_g() * [1, 1, 1, 1e-300, 1e-300, 1e-300, 1e-300]).tolist()}),
        "application/json",
        422,
        ["zero quaternion"],
    ),
    ("outside-image-u", lambda: _bin(_g(r5c0=-10.0)), "application/octet-stream", 422, ["outside the 300x300 image"]),
    ("outside-image-v", lambda: _bin(_g(r5c1=1e30)), "application/octet-stream", 422, ["outside the 300x300 image"]),
    ("text-plain", lambda: _bin(grasps_at(k=8)), "text/plain", 415, ["text/plain"]),
    ("no-content-type", lambda: _bin(grasps_at(k=8)), None, 415, ["content type"]),
]


@pytest.mark.parametrize("name,body,ct,status,words", SCORES, ids=[s[0] for s in SCORES])
def test_bad_scores(url, image_id, name, body, ct, status, words):
    headers = {} if ct is None else {"content-type": ct}
    r = httpx.post(f"{url}/v1/images/{image_id}/scores", content=body(), headers=headers, timeout=10)
    assert_error(r, status, *words)


def test_bad_grasp_rows_are_named_by_index(url, image_id):
    g = _g(r1c0=np.nan, r4c2=np.nan)
    r = httpx.post(
        f"{url}/v1/images/{image_id}/scores", content=_bin(g), headers={"content-type": "application/octet-stream"}
    )
    assert r.status_code == 422 and r.json()["error"]["details"]["grasps"] == [1, 4]


@pytest.mark.parametrize("scale", [1e-3, 7.0, 1e30, 1e200])
def test_non_unit_quaternion_scores_like_the_unit_one(url, image_id, scale):
    g = grasps_at(k=6).astype(np.float64)
    ref = httpx.post(f"{url}/v1/images/{image_id}/scores", json={"grasps": g.tolist()}).json()["p_success"]
    g[:, 3:] *= scale
    r = httpx.post(f"{url}/v1/images/{image_id}/scores", json={"grasps": g.tolist()})
    assert r.status_code == 200, r.text
    assert np.allclose(r.json()["p_success"], ref, atol=1e-6)


@pytest.mark.parametrize(
    "iid",
    [
        "0" * 32,
        "not-an-id",
        "x" * 5000,
        "..",
        "%2e%2e",
        "..%2F..%2Fetc%2Fpasswd",
        "%2Fetc%2Fpasswd",
        "..%5C..%5Cwindows",
        "model_card.json",
        "%00",
    ],
)
def test_unknown_or_path_like_image_id_is_404(url, iid):
    r = httpx.post(
        f"{url}/v1/images/{iid}/scores",
        content=_bin(grasps_at(k=8)),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 404
    assert "error" in r.json()


def test_raw_dot_dot_path_is_404(url):
    """A literal ../../ path (sent as is, not normalised by the client) never reaches a file."""
    host, port = url.removeprefix("http://").split(":")
    body = _bin(grasps_at(k=1))
    req = (
        f"POST /v1/images/../../etc/passwd/scores HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/octet-stream\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    ).encode() + body
    with socket.create_connection((host, int(port)), timeout=5) as s:
        s.sendall(req)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    assert data.split(b"\r\n", 1)[0].split(b" ")[1] == b"404"
    assert b"root:" not in data


# ---- one-shot ------------------------------------------------------------------------------------------------------
ONE_SHOT = [
    ("npz-not-zip", lambda: b"PK\x03\x04 definitely not a zip", "application/x-npz", 422, [".npz"]),
    ("npz-zip-bomb", lambda: zip_bomb(50_000_000), "application/x-npz", 413, ["'depth'", "unpacks to"]),
    ("npz-zip-bomb-lying-size", lambda: zip_bomb(5_000_000, lie_size=1000), "application/x-npz", 422, ["'depth'"]),
    (
        "npz-many-members",
        lambda: npz(**{f"a{i}": np.zeros(1) for i in range(200)}),
        "application/x-npz",
        422,
        ["members"],
    ),
    ("npz-missing-grasps", lambda: npz(depth=table_scene()), "application/x-npz", 422, ["'grasps'"]),
    (
        "npz-depth-1d",
        lambda: npz(depth=np.full(300, 0.7, np.float32), grasps=grasps_at(k=8)),
        "application/x-npz",
        422,
        ["depth has shape"],
    ),
    (
        "npz-depth-huge-dims",
        lambda: _npz_raw(depth=npy_header_only((100000, 100000)), grasps=npy(grasps_at(k=8))),
        "application/x-npz",
        422,
        ["depth"],
    ),
    (
        "npz-depth-int",
        lambda: npz(depth=np.full((300, 300), 7, np.int64), grasps=grasps_at(k=8)),
        "application/x-npz",
        422,
        ["dtype int64"],
    ),
    ("npz-depth-nan", lambda: npz(depth=nan_depth, grasps=grasps_at(k=8)), "application/x-npz", 422, ["non-finite"]),
    (
        "npz-grasps-shape",
        lambda: npz(depth=table_scene(), grasps=np.zeros((3, 6))),
        "application/x-npz",
        422,
        ["(k, 7)"],
    ),
    ("npz-grasps-k0", lambda: npz(depth=table_scene(), grasps=np.zeros((0, 7))), "application/x-npz", 422, ["k = 0"]),
    (
        "npz-grasps-outside",
        lambda: npz(depth=table_scene(), grasps=grasps_at(center=(20, 20), k=8)),
        "application/x-npz",
        422,
        ["outside"],
    ),
    (
        "npz-center-3",
        lambda: npz(depth=table_scene(), grasps=grasps_at(k=8), center=np.zeros(3)),
        "application/x-npz",
        422,
        ["center"],
    ),
    (
        "npz-pickled-member",
        lambda: _npz_raw(depth=npy(np.array([None] * 4), allow_pickle=True), grasps=npy(grasps_at(k=8))),
        "application/x-npz",
        422,
        ["dtype object"],
    ),
    (
        "npz-depth-negative-dims",
        lambda: _npz_raw(depth=npy_header_only((-300, -300)), grasps=npy(grasps_at(k=8))),
        "application/x-npz",
        422,
        ["depth", "non-negative"],
    ),
    (
        "npz-grasps-negative-dims",
        lambda: _npz_raw(depth=npy(table_scene()), grasps=npy_header_only((-16, -7))),
        "application/x-npz",
        422,
        ["grasps", "non-negative"],
    ),
    (
        "npz-grasps-overflowing-dims",
        lambda: _npz_raw(depth=npy(table_scene()), grasps=npy_header_only((2**32, 2**32))),
        "application/x-npz",
        422,
        ["grasps", "values"],
    ),
    (
        "npz-center-negative-dims",
        lambda: _npz_raw(depth=npy(table_scene()), grasps=npy(grasps_at(k=8)), center=npy_header_only((-1, -2))),
        "application/x-npz",
        422,
        ["center", "non-negative"],
    ),
    (
        "npz-center-negative",
        lambda: npz(depth=table_scene(), grasps=grasps_at(k=8), center=np.array([-5.0, 10.0])),
        "application/x-npz",
        422,
        ["center_u", ">= 0"],
    ),
    (
        "npz-center-nan",
        lambda: npz(depth=table_scene(), grasps=grasps_at(k=8), center=np.array([149.5, np.nan])),
        "application/x-npz",
        422,
        ["center_v", "finite"],
    ),
    (
        "multipart-garbage",
        lambda: b"--xyz\r\nnot a part",
        "multipart/form-data; boundary=xyz",
        400,
        ["malformed multipart"],
    ),
    ("multipart-no-boundary", lambda: b"abc", "multipart/form-data", 400, ["multipart"]),
    ("json-one-shot", lambda: b"{}", "application/json", 415, ["multipart/form-data"]),
]


def _npz_raw(**members: bytes) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for k, v in members.items():
            z.writestr(k + ".npy", v)
    return buf.getvalue()


@pytest.mark.parametrize("name,body,ct,status,words", ONE_SHOT, ids=[o[0] for o in ONE_SHOT])
def test_bad_one_shot(url, name, body, ct, status, words):
    r = httpx.post(f"{url}/v1/score", content=body(), headers={"content-type": ct}, timeout=10)
    assert_error(r, status, *words)


def test_multipart_without_depth_part_is_422(url):
    r = httpx.post(
        f"{url}/v1/score", files={"grasps": ("g.json", _json({"grasps": grasps_at(k=8).tolist()}), "application/json")}
    )
    assert_error(r, 422, '"depth"')


def test_multipart_without_grasps_part_is_422(url):
    r = httpx.post(f"{url}/v1/score", files={"depth": ("d.npy", npy(table_scene()), NPY)})
    assert_error(r, 422, '"grasps"')


MULTIPART_NUMBERS = [(f, v) for f in ("width", "height") for _, v in BAD_INTEGERS] + [
    (f, v) for f in ("center_u", "center_v") for v in ("inf", "-inf", "nan", "1e400", "9" * 400, "-1", "abc")
]


@pytest.mark.parametrize("field,value", MULTIPART_NUMBERS, ids=[f"{f}={v[:12]}" for f, v in MULTIPART_NUMBERS])
def test_multipart_number_fields_are_checked(url, field, value):
    """The issue's reproducer (width=inf answered 500) and its relatives: 422 naming the field."""
    fields = {"width": "300", "height": "300", field: value}
    r = httpx.post(
        f"{url}/v1/score",
        files={"depth": ("d.raw", table_scene().tobytes(), "application/octet-stream")},
        data={"grasps": _json({"grasps": grasps_at(k=8).tolist()}).decode(), **fields},
    )
    assert_error(r, 422, field)


@pytest.mark.parametrize(
    "grasps,words",
    [
        ("", ["empty"]),
        ("{not json", ["not valid JSON"]),
        ('{"grasps": [[150, 150, 0.6, 1, 0, 0, false]]}', ["true / false"]),
    ],
    ids=["empty", "not-json", "boolean"],
)
def test_multipart_grasps_field_is_checked(url, grasps, words):
    """A form field's bad value is a 422 (the multipart body itself is well formed)."""
    files = {"depth": ("d.npy", npy(table_scene()), NPY), "grasps": (None, grasps.encode())}
    r = httpx.post(f"{url}/v1/score", files=files)
    assert_error(r, 422, *words)


def test_multipart_with_bad_depth_names_it(url):
    r = httpx.post(
        f"{url}/v1/score",
        files={"depth": ("d.npy", npy(nan_depth), NPY)},
        data={"grasps": _json({"grasps": grasps_at(k=8).tolist()}).decode()},
    )
    assert_error(r, 422, "non-finite")


# ---- size limits and timeouts -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", ["/v1/images", "/v1/images/{iid}/scores", "/v1/score", "/v1/plan"])
def test_body_over_limit_with_content_length_is_413(url, image_id, path):
    r = httpx.post(url + path.format(iid=image_id), content=b"\0" * (MAX_BODY + 1), headers={"content-type": NPY})
    assert_error(r, 413, f"limit of {MAX_BODY} bytes")


def test_body_over_limit_chunked_is_413(url):
    def chunks():
        for _ in range(MAX_BODY // 65536 + 2):
            yield b"\0" * 65536

    try:
        r = httpx.post(f"{url}/v1/images", content=chunks(), headers={"content-type": NPY}, timeout=10)
    except httpx.HTTPError as e:  # the server may close the connection before the client finishes sending
        pytest.fail(f"no 413 response: {e!r}")
    assert "content-length" not in r.request.headers
    assert_error(r, 413, f"limit of {MAX_BODY} bytes")


def test_bad_content_length_is_400(url):
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=5) as s:
        s.sendall(
            b"POST /v1/images HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-npy\r\nContent-Length: -5\r\n"
            b"Connection: close\r\n\r\n"
        )
        status = s.recv(65536).split(b"\r\n", 1)[0]
    assert status.split(b" ")[1] == b"400"


def _slow_request(url: str, path: str, ct: str, declared: int, sent: bytes) -> tuple[bytes, float]:
    """Send headers and part of a body, then stall; return (status line, seconds to answer)."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=TIMEOUT_S + 5) as s:
        s.sendall(
            f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {ct}\r\nContent-Length: {declared}\r\n\r\n".encode()
            + sent
        )
        t0 = time.monotonic()
        data = s.recv(65536)
        return data.split(b"\r\n", 1)[0], time.monotonic() - t0


@pytest.mark.parametrize("path,ct", [("/v1/images", NPY), ("/v1/score", "application/x-npz"), ("/v1/plan", NPY)])
def test_slow_loris_body_is_408(url, path, ct):
    status, dt = _slow_request(url, path, ct, 100_000, b"\x93NUMPY")
    assert status.split(b" ")[1] == b"408", status
    assert TIMEOUT_S * 0.9 <= dt < TIMEOUT_S + 3


def test_slow_loris_trickle_is_408(url, image_id):
    """A body that keeps trickling in (one byte every 0.2 s) still ends with 408 after the request timeout."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=TIMEOUT_S + 5) as s:
        s.sendall(
            f"POST /v1/images/{image_id}/scores HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            f"Content-Length: 1000\r\n\r\n".encode()
        )
        t0 = time.monotonic()
        s.settimeout(0.2)
        data = b""
        while not data and time.monotonic() - t0 < TIMEOUT_S + 3:
            try:
                s.sendall(b" ")
                data = s.recv(65536)
            except TimeoutError:
                continue
    assert data.split(b" ", 2)[1] == b"408", data[:100]


def _silent_client(url: str, sent: bytes) -> tuple[bytes, float]:
    """Connect, send ``sent`` (maybe nothing) and stall; return (all the server sent, seconds until it closed)."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=TIMEOUT_S + 5) as s:
        t0 = time.monotonic()
        s.sendall(sent)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
        return data, time.monotonic() - t0


@pytest.mark.parametrize(
    "sent",
    [b"", b"POST /v1/ima", b"POST /v1/images HTTP/1.1\r\nHost: x\r\nContent-Ty"],
    ids=["nothing", "half-request-line", "half-headers"],
)
def test_slow_loris_headers_get_408_and_the_connection_closed(url, sent):
    data, dt = _silent_client(url, sent)
    assert data.startswith(b"HTTP/1.1 408 "), data[:100]
    assert b"request headers not received within" in data
    assert TIMEOUT_S * 0.9 <= dt < TIMEOUT_S + 3


def _read_response(s: socket.socket) -> bytes:
    """One whole HTTP/1.1 response (headers + content-length body) from a keep-alive socket."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = s.recv(65536)
        assert chunk, f"connection closed after {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = next(
        int(line.split(b":", 1)[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:")
    )
    while len(body) < length:
        chunk = s.recv(65536)
        assert chunk, "connection closed mid-body"
        body += chunk
    assert len(body) == length, "more bytes than one response"
    return head


def test_idle_keep_alive_connection_outlives_the_header_deadline(url):
    """The deadline covers a request's headers, not the idle time between keep-alive requests
    (bounded by uvicorn's keep-alive timeout): one socket, two requests 1.5 deadlines apart."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=TIMEOUT_S + 5) as s:
        for _ in range(2):
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert _read_response(s).startswith(b"HTTP/1.1 200 ")
            time.sleep(TIMEOUT_S * 1.5)


def test_service_still_answers_after_the_matrix(url, image_id):
    r = httpx.post(
        f"{url}/v1/images/{image_id}/scores",
        content=_bin(grasps_at(k=8)),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 200 and len(r.json()["p_success"]) == 8
    text = httpx.get(f"{url}/metrics").text
    assert 'status="500"' not in text


# ---- authentication ---------------------------------------------------------------------------------------------------
def test_api_key_guards_upload_score_and_one_shot_only(model_dir):
    with running_service(model_dir, env={"VGQ_API_KEY": "s3cret"}) as u:
        body, octet = npy(table_scene()), {"content-type": "application/octet-stream"}
        guarded = [
            ("/v1/images", body, {"content-type": NPY}),
            ("/v1/images/" + "0" * 32 + "/scores", _bin(grasps_at(k=8)), octet),
            ("/v1/score", npz(depth=table_scene(), grasps=grasps_at(k=8)), {"content-type": "application/x-npz"}),
        ]
        for path, content, headers in guarded:
            for key in (None, "wrong", "s3cre", "s3cret" * 2):
                h = headers if key is None else {**headers, "x-api-key": key}
                assert_error(httpx.post(u + path, content=content, headers=h), 401, "X-API-Key")
        ok = httpx.post(u + "/v1/images", content=body, headers={"content-type": NPY, "x-api-key": "s3cret"})
        assert ok.status_code == 200
        r = httpx.post(
            f"{u}/v1/images/{ok.json()['image_id']}/scores",
            content=_bin(grasps_at(k=8)),
            headers={**octet, "x-api-key": "s3cret"},
        )
        assert r.status_code == 200
        for path in ("/healthz", "/readyz", "/metrics"):
            assert httpx.get(u + path).status_code == 200, path
