"""Parse a one-shot request (``POST /v1/score``): a depth image and grasps in one body.

* ``multipart/form-data``: parts ``depth`` (a file: .npy, 16-bit PNG, or raw float32 with
  ``width`` / ``height`` fields), ``grasps`` (JSON text or a float32 k x 7 file with content
  type application/octet-stream) and optional fields ``center_u`` / ``center_v`` and the
  camera's ``fx``, ``fy``, ``cx``, ``cy``. The body is
  already in memory: parts are parsed from it with python-multipart's streaming parser and
  kept as views into it where possible (no temporary files, no second copy).
* ``application/x-npz``: arrays ``depth`` (H, W) float metres, ``grasps`` (k, 7) and optional
  ``center`` (2,) = (u, v) and ``intrinsics`` (4,) = (fx, fy, cx, cy) px; every .npy header is checked before anything is allocated.

Every number goes through ``service.numbers``. Returns a ``OneShot``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from python_multipart.multipart import MultipartParser, parse_options_header

from vgq.grasps import GRASP_WIDTH

from .depth_io import NPY_TYPES, decode_depth, parse_npy, read_npz, validate_depth
from .errors import ApiError
from .grasps import parse_binary, parse_json
from .media import OCTET, media_type
from .numbers import (
    CENTER_U,
    CENTER_V,
    INTRINSICS,
    ONE_SHOT_NUMBERS,
    UP,
    parse_all,
    request_key,
)

MAX_PARTS = 16  # depth, grasps and up to 11 numeric fields (the image size, intrinsics, window centre, up)
MAX_PART_HEADER_BYTES = 4096


@dataclass
class OneShot:
    """A parsed one-shot request: the depth upload's bytes and content type (the cache key is
    made from them), the grasps (k, 7) float64 and the numeric fields (None when absent)."""

    depth_body: bytes | memoryview
    depth_type: str
    grasps: np.ndarray
    numbers: dict
    depth: np.ndarray | None = None  # already decoded (.npz)

    def cache_params(self) -> str:
        return request_key(self.depth_type, self.numbers)

    def decode(self, max_side: int) -> np.ndarray:
        if self.depth is not None:
            return self.depth
        return decode_depth(
            self.depth_body,
            self.depth_type,
            width=self.numbers["width"],
            height=self.numbers["height"],
            max_side=max_side,
        )


@dataclass
class _Part:
    name: str = ""
    filename: str | None = None
    content_type: str = ""
    start: int = -1
    end: int = -1
    chunks: list | None = None  # only when the parser handed data from its own buffer

    def data(self, body) -> bytes | memoryview:
        if self.chunks is not None:
            return b"".join(self.chunks)
        return memoryview(body)[self.start : self.end] if self.start >= 0 else b""


def split_multipart(body, content_type_header: str) -> dict[str, _Part]:
    """The parts of an in-memory multipart body by name (400 when malformed)."""
    _, options = parse_options_header(content_type_header)
    boundary = options.get(b"boundary")
    if not boundary:
        raise ApiError(400, "malformed multipart body: no boundary in the content type")
    parts: dict[str, _Part] = {}
    state = {"part": None, "field": b"", "value": b"", "header_bytes": 0, "ended": False}

    def on_part_begin():
        if len(parts) >= MAX_PARTS:
            raise ApiError(422, f"multipart body has more than {MAX_PARTS} parts")
        state["part"], state["header_bytes"] = _Part(), 0

    def on_header_field(data, start, end):
        state["field"] += bytes(data[start:end])
        state["header_bytes"] += end - start

    def on_header_value(data, start, end):
        state["value"] += bytes(data[start:end])
        state["header_bytes"] += end - start
        if state["header_bytes"] > MAX_PART_HEADER_BYTES:
            raise ApiError(400, f"malformed multipart body: part headers over {MAX_PART_HEADER_BYTES} bytes")

    def on_header_end():
        field, value, part = state["field"].lower(), state["value"], state["part"]
        if field == b"content-disposition":
            _, opts = parse_options_header(value)
            part.name = opts.get(b"name", b"").decode("latin-1")
            fn = opts.get(b"filename")
            part.filename = None if fn is None else fn.decode("latin-1")
        elif field == b"content-type":
            part.content_type = media_type(value.decode("latin-1"))
        state["field"], state["value"] = b"", b""

    def on_part_data(data, start, end):
        part = state["part"]
        if part.chunks is None and data is body and (part.start < 0 or part.end == start):
            part.start = start if part.start < 0 else part.start
            part.end = end
            return
        if part.chunks is None:  # data from the parser's look-behind buffer: fall back to copies
            part.chunks = [bytes(memoryview(body)[part.start : part.end])] if part.start >= 0 else []
        part.chunks.append(bytes(data[start:end]))

    def on_part_end():
        part = state["part"]
        if part.name and part.name not in parts:
            parts[part.name] = part

    def on_end():
        state["ended"] = True

    try:
        parser = MultipartParser(
            boundary,
            {
                "on_part_begin": on_part_begin,
                "on_header_field": on_header_field,
                "on_header_value": on_header_value,
                "on_header_end": on_header_end,
                "on_part_data": on_part_data,
                "on_part_end": on_part_end,
                "on_end": on_end,
            },
        )
        parser.write(body)
        parser.finalize()
    except ApiError:
        raise
    except Exception as e:
        raise ApiError(400, f"malformed multipart body: {e}") from None
    if not state["ended"]:
        raise ApiError(400, "malformed multipart body: no closing boundary (truncated?)")
    return parts


def _text(part: _Part, body) -> str:
    return bytes(part.data(body)).decode("utf-8", "replace")


def parse_multipart(body, content_type_header: str) -> OneShot:
    parts = split_multipart(body, content_type_header)
    depth, grasps = parts.get("depth"), parts.get("grasps")
    if depth is None or depth.filename is None:
        raise ApiError(422, 'multipart body needs a file part "depth"')
    if grasps is None:
        raise ApiError(422, 'multipart body needs a part "grasps" (JSON text or float32 k x 7 file)')
    g = grasps.data(body)
    if grasps.content_type == OCTET:
        grasps_array = parse_binary(g)
    else:
        if len(g) == 0:
            raise ApiError(
                422, 'multipart part "grasps" is empty; expected JSON {"grasps": [[u, v, z, qw, qx, qy, qz], ...]}'
            )
        grasps_array = parse_json(g, syntax_status=422)  # a field's value, not the body's syntax
    fields = {
        name: _text(p, body) for name, p in parts.items() if p.filename is None and name not in ("depth", "grasps")
    }
    return OneShot(depth.data(body), depth.content_type, grasps_array, parse_all(ONE_SHOT_NUMBERS, fields))


def parse_npz(body, max_total_bytes: int, max_side: int, max_grasps: int) -> OneShot:
    members = read_npz(body, max_total_bytes)
    for need in ("depth", "grasps"):
        if need not in members:
            raise ApiError(422, f".npz body needs an array {need!r} (has {sorted(members)})")
    depth = parse_npy(members["depth"], "depth", max_side * max_side)
    if depth.ndim != 2 or not (32 <= depth.shape[0] <= max_side and 32 <= depth.shape[1] <= max_side):
        raise ApiError(422, f"depth has shape {depth.shape}; expected (H, W) with sides in [32, {max_side}]")
    depth = validate_depth(np.require(depth, np.float32, "CA"))  # a view of the body when aligned, else a copy
    grasps = parse_npy(members["grasps"], "grasps", max_grasps * GRASP_WIDTH + GRASP_WIDTH)
    if grasps.ndim != 2 or grasps.shape[1] != GRASP_WIDTH:
        raise ApiError(422, f"grasps has shape {grasps.shape}; expected (k, 7)")
    numbers = {n.name: None for n in ONE_SHOT_NUMBERS}
    if "center" in members:
        center = parse_npy(members["center"], "center", 2).reshape(-1)
        if center.shape != (2,):
            raise ApiError(422, "center must hold 2 values (u, v)")
        numbers["center_u"], numbers["center_v"] = CENTER_U.parse(center[0]), CENTER_V.parse(center[1])
    for name, fields, what in (
        ("intrinsics", INTRINSICS, "4 values (fx, fy, cx, cy) px"),
        ("up", UP, "3 values (the world's up direction in the camera frame)"),
    ):
        if name in members:
            values = parse_npy(members[name], name, len(fields)).reshape(-1)
            if values.shape != (len(fields),):
                raise ApiError(422, f"{name} must hold {what}")
            for number, value in zip(fields, values):
                numbers[number.name] = number.parse(value)
    return OneShot(members["depth"], NPY_TYPES[0], grasps.astype(np.float64), numbers, depth)
