"""service.depth_io's readers of what numpy writes, .npz archives of uncompressed members
(np.savez) and version 1.0 .npy headers: the same result as zipfile / numpy, and whatever
they are unsure of left to zipfile / numpy (same errors)."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from service.depth_io import _numpy_written_header, npy_header, read_npz, stored_members
from service.errors import ApiError
from service.oneshot import parse_npz


def _savez(compressed: bool = False, **arrays) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def _zipfile_members(body: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(body)) as z:
        return {i.filename[:-4]: z.read(i) for i in z.infolist()}


def test_savez_members_are_read_as_zipfile_reads_them():
    rng = np.random.default_rng(0)
    body = _savez(depth=rng.uniform(0.5, 1, (64, 48)).astype(np.float32), grasps=rng.random((5, 7)), center=np.ones(2))
    fast = stored_members(body, 8)
    assert fast is not None and [m.filename for m in fast] == ["depth.npy", "grasps.npy", "center.npy"]
    assert {k: bytes(v) for k, v in read_npz(body, 1 << 20).items()} == _zipfile_members(body)


def test_a_member_with_a_wrong_crc_gets_zipfiles_error():
    body = bytearray(_savez(depth=np.full((40, 40), 0.7, np.float32), grasps=np.zeros((1, 7))))
    body[200] ^= 0xFF  # a byte of the depth data: its CRC-32 no longer matches
    assert stored_members(body, 8) is None
    with pytest.raises(ApiError, match=r"'depth' cannot be read \(corrupt archive\): Bad CRC-32") as e:
        read_npz(body, 1 << 20)
    assert e.value.status == 422


@pytest.mark.parametrize(
    "change",
    ["compressed", "comment", "truncated", "prefix"],
)
def test_archives_it_is_unsure_of_go_to_zipfile(change):
    arrays = {"depth": np.full((40, 40), 0.7, np.float32), "grasps": np.zeros((2, 7), np.float32)}
    body = _savez(compressed=change == "compressed", **arrays)
    if change == "comment":
        buf = io.BytesIO(body)
        with zipfile.ZipFile(buf, "a") as z:
            z.comment = b"hello"
        body = buf.getvalue()
    elif change == "truncated":
        body = body[:-30]
    elif change == "prefix":
        body = b"junk" + body  # zipfile reads past a prefix; this reader does not try
    assert stored_members(body, 8) is None
    if change == "truncated":
        with pytest.raises(ApiError, match="not a valid .npz archive"):
            read_npz(body, 1 << 20)
    else:
        assert set(read_npz(body, 1 << 20)) == {"depth", "grasps"}


def test_one_shot_depth_is_aligned_float32_equal_to_the_upload():
    depth = np.random.default_rng(1).uniform(0.4, 0.9, (50, 60)).astype(np.float32)
    shot = parse_npz(_savez(depth=depth, grasps=np.ones((3, 7))), 1 << 20, 4096, 2048)
    assert shot.depth.dtype == np.float32 and shot.depth.flags.c_contiguous and shot.depth.flags.aligned
    assert np.array_equal(shot.depth, depth) and shot.grasps.dtype == np.float64


@pytest.mark.parametrize(
    "a",
    [
        np.zeros((300, 200), np.float32),
        np.zeros((5, 7)),
        np.zeros(2),
        np.zeros((3, 4), order="F"),
        np.zeros((), np.float32),
        np.zeros((2, 3), ">f4"),
        np.zeros((0, 7)),
    ],
    ids=["f4", "f8", "1d", "fortran", "scalar", "big-endian", "empty"],
)
def test_numpy_written_headers_read_as_numpy_reads_them(a):
    buf = io.BytesIO()
    np.save(buf, a)
    body = buf.getvalue()
    f = io.BytesIO(body)
    np.lib.format.read_magic(f)
    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    assert _numpy_written_header(body) == (shape, fortran, dtype, f.tell()) == npy_header(body, "x")


@pytest.mark.parametrize(
    "header, message",
    [
        (b"{'descr': '<f4', 'fortran_order': False, 'shape': (-1, 3), }", "non-negative integers"),
        (b"{'descr': '<i4', 'fortran_order': False, 'shape': (2, 3), }", "expected float32 or float64"),
        (b"{'shape': (2, 3), 'fortran_order': False, 'descr': '<f4'}", None),  # valid, not as numpy writes it
    ],
)
def test_other_headers_go_through_numpys_parser(header, message):
    header += b" " * (-(len(header) + 11) % 64) + b"\n"
    body = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(24)
    assert _numpy_written_header(body) is None
    if message is None:
        assert npy_header(body, "x")[:3] == ((2, 3), False, np.dtype("<f4"))
    else:
        with pytest.raises(ApiError, match=message):
            npy_header(body, "x")
