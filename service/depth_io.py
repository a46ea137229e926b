"""Decode uploaded depth images into float32 metres, (H, W), checked for sanity.

Accepted bodies (by Content-Type):

* ``application/x-npy``: a NumPy ``.npy`` of float32 or float64 metres, shape (H, W) or
  (H, W, 1); parsed from its header without pickle; truncated data is rejected.
* ``image/png``: 16-bit grayscale PNG in millimetres (0 = no reading).
* ``application/octet-stream``: raw little-endian float32 metres, row-major, with the
  ``width`` and ``height`` given alongside.

Depth must be finite and >= 0 (0 means no reading; values beyond vgq.camera.MAX_DEPTH_M = 10 m
count as no reading too and are filled like 0). Image sides must lie in
[min_side, max_side]; sizes are checked before any pixel buffer is allocated.
"""

from __future__ import annotations

import io
import math
import re
import struct
import warnings
import zipfile
import zlib
from dataclasses import dataclass

import numpy as np
from PIL import Image

from .errors import ApiError
from .media import media_type

NPY_TYPES = ("application/x-npy", "application/npy")
PNG_TYPES = ("image/png",)
RAW_TYPES = ("application/octet-stream",)
DEPTH_TYPES = NPY_TYPES + PNG_TYPES + RAW_TYPES


def _check_size(h: int, w: int, min_side: int, max_side: int) -> None:
    if not (min_side <= h <= max_side and min_side <= w <= max_side):
        raise ApiError(422, f"depth image is {h}x{w} (HxW); each side must be in [{min_side}, {max_side}] px")


NPY_HEADER_MAX = 16 + 10000  # numpy's own bound on a .npy header (max_header_size)


#: the version 1.0 header numpy writes for a float array, e.g. b"{'descr': '<f4', 'fortran_order':
#: False, 'shape': (300, 300), }" padded with spaces and a newline
_NPY_V1_FLOAT = re.compile(
    rb"\{'descr': '([<>]f[48])', 'fortran_order': (True|False), 'shape': \(((?:\d{1,18}, )*\d{1,18},?|)\), \} *\n"
)


def _numpy_written_header(body) -> tuple[tuple[int, ...], bool, np.dtype, int] | None:
    """(shape, fortran order, dtype, data offset) of a float .npy whose version 1.0 header is
    exactly as numpy writes it, without numpy's general parser (``ast.literal_eval``); None for
    any other header."""
    if len(body) < 10 or bytes(body[:8]) != b"\x93NUMPY\x01\x00":
        return None
    end = 10 + int.from_bytes(body[8:10], "little")
    m = _NPY_V1_FLOAT.fullmatch(bytes(body[10:end])) if len(body) >= end else None
    if m is None:
        return None
    shape = tuple(int(d) for d in m[3].split(b",") if d.strip())
    return shape, m[2] == b"True", np.dtype(m[1].decode()), end


def npy_header(body: bytes, what: str) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """(shape, fortran order, dtype, data offset) of a .npy, read and checked without pickle and
    before anything is allocated: every dimension a non-negative integer, a float32 / float64 dtype.
    Raises ApiError 422 naming ``what``."""
    fast = _numpy_written_header(body)
    if fast is not None:
        return fast  # float32 / float64, every dimension a non-negative integer, by its pattern
    f = io.BytesIO(bytes(body[:NPY_HEADER_MAX]))  # the header only: no copy of the data
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except Exception as e:
        raise ApiError(422, f"{what} is not a valid .npy file: {e}") from None
    if not isinstance(shape, tuple) or not all(
        isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape
    ):
        raise ApiError(422, f"{what} .npy declares shape {shape}; dimensions must be non-negative integers")
    if dtype.hasobject or dtype.kind != "f" or dtype.itemsize not in (4, 8):
        raise ApiError(422, f"{what} .npy has dtype {dtype}; expected float32 or float64")
    return shape, bool(fortran), dtype, f.tell()


def _from_buffer(body: bytes, what: str, shape, fortran: bool, dtype, start: int) -> np.ndarray:
    n = math.prod(shape)
    if len(body) - start != n * dtype.itemsize:
        raise ApiError(
            422,
            f"{what} .npy holds {len(body) - start} data bytes, header promises {n * dtype.itemsize} "
            "(truncated or padded)",
        )
    a = np.frombuffer(body, dtype=dtype, count=n, offset=start)
    return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)


def _decode_npy(body: bytes, min_side: int, max_side: int) -> np.ndarray:
    shape, fortran, dtype, start = npy_header(body, "depth body")
    if len(shape) == 3 and shape[2] == 1:
        shape = shape[:2]
    if len(shape) != 2:
        raise ApiError(422, f"depth .npy has shape {shape}; expected (H, W) or (H, W, 1)")
    _check_size(shape[0], shape[1], min_side, max_side)
    a = _from_buffer(body, "depth", shape, fortran, dtype, start)
    return np.ascontiguousarray(a, dtype=np.float32)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOUR = {0: "grayscale", 2: "RGB", 3: "palette", 4: "grayscale + alpha", 6: "RGBA"}


def png_header(body: bytes) -> tuple[int, int, int, int]:
    """(height, width, bit depth, colour type) from a PNG's IHDR chunk, read without decoding.
    Raises ApiError 422 if the body is not a PNG."""
    if bytes(body[:8]) != PNG_SIGNATURE:
        raise ApiError(422, "depth body is not a PNG file (bad signature)")
    if len(body) < 33 or bytes(body[12:16]) != b"IHDR" or struct.unpack(">I", body[8:12])[0] != 13:
        raise ApiError(422, "depth PNG is truncated or corrupt: no IHDR header chunk")
    w, h, bits, colour = struct.unpack(">IIBB", body[16:26])
    return h, w, bits, colour


def _decode_png(body: bytes, min_side: int, max_side: int) -> np.ndarray:
    # size and format from the header before any pixel is decompressed (decompression bombs)
    h, w, bits, colour = png_header(body)
    _check_size(h, w, min_side, max_side)
    if bits != 16 or colour != 0:
        raise ApiError(
            422,
            f"depth PNG is {bits}-bit {_PNG_COLOUR.get(colour, f'colour type {colour}')}; "
            "expected 16-bit grayscale in millimetres",
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(body), formats=["PNG"])
            if img.size != (w, h) or img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise ApiError(422, f"depth PNG has mode {img.mode}; expected 16-bit grayscale in millimetres")
            img.load()
    except ApiError:
        raise
    except Exception as e:
        raise ApiError(422, f"depth PNG cannot be decoded (truncated or corrupt): {e}") from None
    a = np.asarray(img)
    if a.dtype.kind not in "ui" or a.min(initial=0) < 0 or a.max(initial=0) > 65535:
        raise ApiError(422, "depth PNG must hold 16-bit unsigned millimetres")
    return a.astype(np.float32) * np.float32(0.001)


def _decode_raw(body: bytes, width: int | None, height: int | None, min_side: int, max_side: int) -> np.ndarray:
    if width is None or height is None:
        raise ApiError(422, "raw float32 depth needs the width and height parameters")
    _check_size(height, width, min_side, max_side)
    if len(body) != width * height * 4:
        raise ApiError(422, f"raw depth has {len(body)} bytes; {height}x{width} float32 needs {width * height * 4}")
    return np.frombuffer(body, dtype="<f4").reshape(height, width).astype(np.float32)


def validate_depth(a: np.ndarray) -> np.ndarray:
    """Reject non-finite or negative depth (422); return ``a``."""
    lo, hi = (float(a.min()), float(a.max())) if a.size else (0.0, 0.0)  # NaN and inf show in min / max
    if math.isfinite(lo) and math.isfinite(hi) and lo >= 0 and hi > 0:
        return a  # the usual case: two passes, no temporary masks
    if not np.isfinite(a).all():
        n = int((~np.isfinite(a)).sum())
        raise ApiError(422, f"depth image has {n} non-finite pixels (NaN or inf); use 0 for missing readings")
    if (a < 0).any():
        raise ApiError(422, f"depth image has {int((a < 0).sum())} negative pixels; depth is in metres, >= 0")
    if not (a > 0).any():
        raise ApiError(422, "depth image has no valid (> 0) pixel")
    return a


def decode_depth(
    body: bytes,
    content_type: str,
    *,
    width: int | None = None,
    height: int | None = None,
    min_side: int = 32,
    max_side: int = 4096,
) -> np.ndarray:
    """Decode and validate a depth upload. Raises ApiError (415 or 422) naming the problem."""
    ct = media_type(content_type)
    if not body:
        raise ApiError(422, "depth body is empty")
    if ct in NPY_TYPES:
        a = _decode_npy(body, min_side, max_side)
    elif ct in PNG_TYPES:
        a = _decode_png(body, min_side, max_side)
    elif ct in RAW_TYPES:
        a = _decode_raw(body, width, height, min_side, max_side)
    else:
        raise ApiError(415, f"unsupported depth content type {ct!r}; use one of {', '.join(DEPTH_TYPES)}")
    return validate_depth(a)


def encode_npy(depth: np.ndarray) -> bytes:
    """The .npy bytes of a depth image (what clients upload)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


def parse_npy(body: bytes, what: str, max_elements: int) -> np.ndarray:
    """A float .npy of any shape (<= max_elements values), parsed without pickle; the header's
    dimensions are checked before anything is allocated."""
    shape, fortran, dtype, start = npy_header(body, what)
    n = math.prod(shape)
    if n > max_elements:
        raise ApiError(422, f"{what} has {n} values; at most {max_elements}")
    return _from_buffer(body, what, shape, fortran, dtype, start)


NPZ_MAX_MEMBERS = 8


def read_npz(
    body: bytes, max_total_bytes: int, names: tuple[str, ...] | None = None, max_members: int = NPZ_MAX_MEMBERS
) -> dict[str, bytes]:
    """Members of an .npz (zip of .npy) as raw .npy bytes (only ``names`` if given).

    Zip bombs are refused before anything is decompressed: at most ``max_members`` members,
    and their declared uncompressed sizes must add up to at most ``max_total_bytes`` (413).
    A member whose data does not match its declared size fails its CRC check (422).

    An archive of uncompressed members (``np.savez``) whose every field is plain is read
    without zipfile, its members returned as views of ``body`` (each CRC still checked); any
    other archive, and any doubt, goes through zipfile, which words the errors."""
    stored = stored_members(body, max_members)
    if stored is not None:
        infos, zf = stored, None
    else:
        try:
            zf = zipfile.ZipFile(BufferReader(body))
            infos = zf.infolist()
        except Exception as e:
            raise ApiError(422, f"body is not a valid .npz archive: {e}") from None
    if len(infos) > max_members:
        raise ApiError(422, f".npz archive has {len(infos)} members; at most {max_members}")
    wanted = [i for i in infos if names is None or _npz_name(i) in names]
    total = 0
    for info in wanted:
        total += info.file_size
        if info.file_size > max_total_bytes or total > max_total_bytes:
            raise ApiError(
                413,
                f".npz member {_npz_name(info)!r} unpacks to {info.file_size} bytes "
                f"({total} in all); limit {max_total_bytes}",
            )
    out = {}
    for info in wanted:
        name = _npz_name(info)
        if zf is None:
            out[name] = info.data
            continue
        try:
            out[name] = zf.read(info)
        except Exception as e:
            raise ApiError(422, f".npz member {name!r} cannot be read (corrupt archive): {e}") from None
    return out


@dataclass(frozen=True)
class StoredMember:
    """An uncompressed zip member (the fields of zipfile.ZipInfo that read_npz uses)."""

    filename: str
    file_size: int
    data: memoryview


_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record (22 bytes)
_CENTRAL = struct.Struct("<4s6H3L5H2L")  # central directory file header (46 bytes)
_LOCAL = struct.Struct("<4s5H3L2H")  # local file header (30 bytes)


def stored_members(body, max_members: int) -> list[StoredMember] | None:
    """The members of a plain zip of uncompressed members (no comment, no zip64 directory, no
    encryption, local and central headers agreeing, every CRC-32 right), as views of ``body``;
    None for anything else (zipfile then reads the archive and words its errors)."""
    try:
        view = memoryview(body).cast("B")
    except (TypeError, ValueError):
        return None
    n = len(view)
    if n < _EOCD.size:
        return None
    sig, disk, cd_disk, count, total, cd_size, cd_offset, comment = _EOCD.unpack_from(view, n - _EOCD.size)
    if sig != b"PK\x05\x06" or disk or cd_disk or count != total or comment or total > max_members:
        return None
    if cd_offset + cd_size != n - _EOCD.size:  # nothing between the directory and its end record
        return None
    out, pos, end = [], cd_offset, 0
    for _ in range(total):
        if pos + _CENTRAL.size > cd_offset + cd_size:
            return None
        f = _CENTRAL.unpack_from(view, pos)
        sig, flags, method, crc, csize, usize = f[0], f[3], f[4], f[7], f[8], f[9]
        name_len, extra_len, comment_len, offset = f[10], f[11], f[12], f[16]
        if (
            sig != b"PK\x01\x02"
            or f[2] & 0xFF > 63  # zipfile's MAX_EXTRACT_VERSION
            or flags & 0x1  # encrypted
            or method != 0  # compressed
            or csize != usize
            or extra_len  # zip64 sizes, or anything zipfile would decode
            or 0xFFFFFFFF in (csize, offset)
            or offset < end  # members in order, none overlapping
        ):
            return None
        name = bytes(view[pos + _CENTRAL.size : pos + _CENTRAL.size + name_len])
        pos += _CENTRAL.size + name_len + extra_len + comment_len
        if offset + _LOCAL.size > cd_offset:
            return None
        lf = _LOCAL.unpack_from(view, offset)
        start = offset + _LOCAL.size + lf[9] + lf[10]
        if (
            lf[0] != b"PK\x03\x04"
            or lf[3] != 0
            or bytes(view[offset + _LOCAL.size : offset + _LOCAL.size + lf[9]]) != name
        ):
            return None
        if start + csize > cd_offset or zlib.crc32(view[start : start + csize]) != crc:
            return None
        try:
            filename = name.decode("utf-8" if flags & 0x800 else "cp437")
        except UnicodeDecodeError:
            return None
        if "\x00" in filename:  # zipfile cuts the name there
            return None
        out.append(StoredMember(filename, usize, view[start : start + csize]))
        end = start + csize
    return out if pos == cd_offset + cd_size else None


class BufferReader(io.RawIOBase):
    """A seekable read-only file over a bytes-like object, without copying it (io.BytesIO copies
    anything but bytes)."""

    def __init__(self, buf):
        self.view, self.pos = memoryview(buf).cast("B"), 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {0: 0, 1: self.pos, 2: len(self.view)}[whence]
        self.pos = max(0, base + offset)
        return self.pos

    def readinto(self, b) -> int:
        n = max(0, min(len(b), len(self.view) - self.pos))
        b[:n] = self.view[self.pos : self.pos + n]
        self.pos += n
        return n


def _npz_name(info) -> str:
    return info.filename[:-4] if info.filename.endswith(".npy") else info.filename
