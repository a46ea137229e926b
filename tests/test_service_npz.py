"""service.depth_io.read_npz's reader for archives of uncompressed members (np.savez): the same
members as zipfile reads, and every archive it is unsure of left to zipfile (same errors)."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from service.depth_io import read_npz, stored_members
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
