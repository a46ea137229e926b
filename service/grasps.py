"""Parse a batch of grasps from a request body into a (k, 7) float64 array.

JSON ``{"grasps": [[u, v, z, qw, qx, qy, qz], ...]}`` (or objects with u, v, z, q) or
little-endian float32 k x 7. Checking the rows and building network pose rows is the
contract's job (``vgq.grasps.pose_rows``); its GraspError maps to 422 at the HTTP edge.
"""

from __future__ import annotations

import numpy as np
import orjson

from vgq.grasps import GRASP_WIDTH

from .errors import ApiError

ROWS_MESSAGE = "every grasp must be a list of 7 numbers [u, v, z, qw, qx, qy, qz]"


def parse_json(body: bytes | bytearray | memoryview | str, syntax_status: int = 400) -> np.ndarray:
    """``{"grasps": [...]}`` -> (k, 7) float64. Syntax errors answer ``syntax_status`` (400 for a
    request body; 422 for a form field), anything else 422. JSON true / false are not numbers."""
    if isinstance(body, memoryview):
        body = bytes(body)  # a multipart part (small): `in` below needs a bytes-like sequence
    try:
        doc = orjson.loads(body)
    except orjson.JSONDecodeError as e:
        raise ApiError(syntax_status, f"grasps are not valid JSON: {e}") from None
    rows = doc.get("grasps") if isinstance(doc, dict) else None
    if not isinstance(rows, list):
        raise ApiError(422, 'body must be a JSON object with a "grasps" list of [u, v, z, qw, qx, qy, qz] rows')
    if rows and isinstance(rows[0], dict):
        try:
            rows = [[g["u"], g["v"], g["z"], *g["q"]] for g in rows]
        except (KeyError, TypeError):
            raise ApiError(422, 'grasp objects need keys "u", "v", "z" and "q" (a list of 4: w, x, y, z)') from None
    raw = body.encode() if isinstance(body, str) else body
    if (b"true" in raw or b"false" in raw) and any(
        type(x) is bool for row in rows if isinstance(row, list) for x in row
    ):
        raise ApiError(422, ROWS_MESSAGE + " (true / false are not numbers)")
    try:
        a = np.array(rows, dtype=np.float64)
    except (ValueError, TypeError, OverflowError):
        raise ApiError(422, ROWS_MESSAGE) from None
    if a.size == 0:
        a = a.reshape(0, GRASP_WIDTH)
    if a.ndim != 2 or a.shape[1] != GRASP_WIDTH:
        raise ApiError(422, ROWS_MESSAGE)
    return a


def parse_binary(body: bytes) -> np.ndarray:
    """Little-endian float32, k x 7 row-major -> (k, 7) float64."""
    if len(body) % (GRASP_WIDTH * 4):
        raise ApiError(422, f"binary grasps must be k x 7 float32 (a multiple of 28 bytes), got {len(body)} bytes")
    return np.frombuffer(body, dtype="<f4").reshape(-1, GRASP_WIDTH).astype(np.float64)
