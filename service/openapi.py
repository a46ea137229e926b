"""OpenAPI descriptions of the raw (non-pydantic) request and response bodies, with examples."""

from __future__ import annotations

from .depth_io import DEPTH_TYPES
from .numbers import ONE_SHOT_NUMBERS

_ERROR = {
    "type": "object",
    "required": ["error"],
    "properties": {"error": {"type": "object", "required": ["status", "message"], "properties": {
        "status": {"type": "integer"}, "message": {"type": "string"},
        "details": {"type": "object", "properties": {"grasps": {"type": "array", "items": {"type": "integer"}}}}}}},
}
_WHAT = {400: "malformed request or body", 401: "missing or wrong API key", 404: "unknown or evicted image id",
         408: "request headers or body not received in time (the connection is closed)",
         413: "body over the size limit (the connection is closed)", 414: "request target too long (the connection is closed)",
         415: "unsupported content type", 422: "invalid parameter, depth image or grasps (the message names them)",
         431: "request headers too large or too many (the connection is closed)",
         503: "model not ready, or too many requests or body bytes in flight (Retry-After says when to retry)"}
PROTOCOL = (400, 408, 414, 431)  # answered by the HTTP layer for any operation
BODY_ERRORS = PROTOCOL + (401, 404, 413, 415, 422, 503)


def errors(codes) -> dict:
    """OpenAPI ``responses`` entries (the JSON error shape) for these status codes."""
    return {code: {"description": _WHAT[code], "content": {"application/json": {"schema": _ERROR}}} for code in codes}


STATUS_RESPONSE = {"description": "status", "content": {"application/json": {"schema": {
    "type": "object", "required": ["status"], "properties": {"status": {"type": "string"}, "model_version": {"type": "string"}}}}}}
NOT_READY = {"description": "model loading or failed", "content": {"application/json": {"schema": {
    "type": "object", "required": ["status"], "properties": {"status": {"type": "string", "enum": ["loading", "failed"]},
                                                              "error": {"type": ["string", "null"]}}}}}}
MODEL_RESPONSE = {"description": "the model card (no file-system paths) and the limits in force", "content": {"application/json": {
    "schema": {"type": "object", "required": ["model_card", "head_precision", "limits", "depth_content_types"]}}}}
CACHE_RESPONSE = {"description": "cache statistics", "content": {"application/json": {"schema": {
    "type": "object", "required": ["backend", "entries", "bytes", "hits", "misses", "evictions"]}}}}

_GRASP_ROW = {"type": "array", "items": {"type": "number"}, "minItems": 7, "maxItems": 7,
              "description": "u (px, column), v (px, row), z (m, camera frame), qw, qx, qy, qz (camera frame)"}
_GRASPS_JSON = {"type": "object", "required": ["grasps"], "properties": {"grasps": {"type": "array", "items": _GRASP_ROW}},
                "example": {"grasps": [[150.0, 148.5, 0.62, 0.0, 1.0, 0.0, 0.0], [140.0, 160.0, 0.61, 0.0, 0.7071, 0.7071, 0.0]]}}
_BINARY = {"type": "string", "format": "binary"}

UPLOAD_BODY = {
    "required": True,
    "description": "Depth image in metres (camera frame z; 0 = no reading).",
    "content": {
        "application/x-npy": {"schema": _BINARY, "description": ".npy float32 (H, W) metres"},
        "image/png": {"schema": _BINARY, "description": "16-bit grayscale PNG, millimetres"},
        "application/octet-stream": {"schema": _BINARY, "description": "raw little-endian float32, needs width and height"},
    },
}
UPLOAD_RESPONSE = {
    "description": "The image's id (content-addressed) and the window grasps must lie in.",
    "content": {"application/json": {"schema": {"type": "object", "required": ["image_id", "cached", "model_version"], "properties": {
        "image_id": {"type": "string"}, "cached": {"type": "boolean"}, "model_version": {"type": "string"},
        "image_shape": {"type": "array", "items": {"type": "integer"}},
        "window_center": {"type": "array", "items": {"type": "number"}},
        "missing_fraction": {"type": "number", "minimum": 0, "maximum": 1,
                             "description": "fraction of the crop window's pixels without a depth reading (0); filled before encoding"},
        "grasp_range": {"type": "object", "properties": {"u": {"type": "array", "items": {"type": "number"}},
                                                         "v": {"type": "array", "items": {"type": "number"}}}}}},
        "example": {"image_id": "3f1c0e9a5b7d4c2e8f6a1b3c5d7e9f01", "cached": False, "model_version": "fast_vgqcnn-0123456789ab",
                    "image_shape": [300, 300], "window_center": [149.5, 149.5], "missing_fraction": 0.012, "grasp_range": {"u": [113.5, 185.5], "v": [113.5, 185.5]}}}},
}
SCORE_BODY = {
    "required": True,
    "content": {
        "application/json": {"schema": _GRASPS_JSON},
        "application/octet-stream": {"schema": _BINARY, "description": "little-endian float32, k x 7 row-major"},
    },
}
SCORE_RESPONSE = {
    "description": "Success probabilities, one per grasp, in order.",
    "content": {
        "application/json": {"schema": {"type": "object", "required": ["image_id", "p_success", "model_version"], "properties": {
            "image_id": {"type": "string"}, "cached": {"type": "boolean"}, "model_version": {"type": "string"},
            "p_success": {"type": "array", "items": {"type": "number", "minimum": 0, "maximum": 1}}}},
            "example": {"image_id": "3f1c0e9a5b7d4c2e8f6a1b3c5d7e9f01", "model_version": "fast_vgqcnn-0123456789ab", "p_success": [0.81, 0.07]}},
        "application/octet-stream": {"schema": _BINARY, "description": "little-endian float32 (k,), with Accept: application/octet-stream"},
    },
}
ONE_SHOT_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {"schema": {"type": "object", "required": ["depth", "grasps"], "properties": {
            "depth": _BINARY, "grasps": {"type": "string", "minLength": 1,
                                         "description": 'JSON {"grasps": [[u, v, z, qw, qx, qy, qz], ...]}'},
            **{n.name: n.schema() for n in ONE_SHOT_NUMBERS}}},
            "encoding": {"depth": {"contentType": ", ".join(DEPTH_TYPES)}}},
        "application/x-npz": {"schema": _BINARY, "description": "arrays depth (H, W) float32 m, grasps (k, 7), optional center (2,)"},
    },
}
