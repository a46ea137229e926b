"""OpenAPI descriptions of the raw (non-pydantic) request and response bodies, with examples."""

from __future__ import annotations

from .depth_io import DEPTH_TYPES
from .numbers import ONE_SHOT_NUMBERS

_ERROR = {
    "type": "object",
    "required": ["error"],
    "properties": {"error": {"type": "object", "required": ["status", "message"], "properties": {
        "status": {"type": "integer"}, "message": {"type": "string"},
        "details": {"type": "object", "properties": {"grasps": {"type": "array", "items": {"type": "integer"}},
                                                    "field": {"type": "string", "description": "the input at fault"}}}}}},
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

PLAN_ERRORS = PROTOCOL + (401, 413, 415, 422, 503)
PLAN_BODY = {
    "required": True,
    "description": "Depth image in metres (camera frame z; 0 = no reading), as for POST /v1/images.",
    "content": UPLOAD_BODY["content"],
}
_NUMBERS = {"type": "array", "items": {"type": "number"}}
_PLANNED_GRASP = {"type": "object", "required": ["row", "pose", "width", "contacts", "score", "ood_flags", "ood"], "properties": {
    "row": {**_GRASP_ROW, "description": "the grasp row u, v (px of the uploaded image), z (m), qw, qx, qy, qz (camera frame): "
                                         "what POST /v1/images/{id}/scores takes"},
    "u": {"type": "number"}, "v": {"type": "number"}, "z": {"type": "number"},
    "q": {**_NUMBERS, "minItems": 4, "maxItems": 4, "description": "qw, qx, qy, qz"},
    "pose": {"type": "array", "items": {**_NUMBERS, "minItems": 4, "maxItems": 4}, "minItems": 4, "maxItems": 4,
             "description": "4 x 4 grasp frame in the camera frame (metres): x = jaw axis, z = approach, origin = TCP"},
    "width": {"type": "number", "description": "distance between the contacts (m)"},
    "contacts": {"type": "array", "items": {**_NUMBERS, "minItems": 3, "maxItems": 3}, "minItems": 2, "maxItems": 2,
                 "description": "the two observed contact points, camera frame (m)"},
    "score": {"type": "number", "minimum": 0, "maximum": 1, "description": "Fast-VGQ-CNN's P(success)"},
    "ood_flags": {"type": "integer", "minimum": 0, "description": "vgq.ood bitmask (0: in distribution)"},
    "ood": {"type": "array", "items": {"type": "string"}, "description": "names of the set ood flags"}}}
PLAN_EXAMPLE = {  # vgq-plan examples/depth_example.npy --k 1 on the bundled model (rounded)
    "grasps": [{"u": 150.83, "v": 154.9, "z": 0.72562, "q": [0.86217, 0.49129, -0.08047, 0.09388],
                "row": [150.83, 154.9, 0.72562, 0.86217, 0.49129, -0.08047, 0.09388],
                "pose": [[0.96942, -0.24096, -0.04651, 0.00184], [0.08282, 0.49964, -0.86227, 0.00746],
                         [0.23101, 0.83205, 0.50432, 0.72562], [0.0, 0.0, 0.0, 1.0]],
                "width": 0.03075, "contacts": [[-0.01307, 0.00619, 0.72207], [0.01674, 0.00874, 0.72917]],
                "score": 0.931, "ood_flags": 0, "ood": []}],
    "reason": None,
    "counts": {"object_pixels": 507, "table": True, "pairs": 313, "approaches": 1519, "checked": 512, "collision_free": 256,
               "windows": 1},
    "seconds": {"resample": 0.0004, "scene": 0.0041, "sample": 0.0049, "encode": 0.0055, "score": 0.004, "select": 0.0004,
                "total": 0.025},
    "model_version": "fast_vgqcnn-60b272a5a797", "k": 1, "seed": 0, "cem": 0,
    "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 149.5, "cy": 149.5, "width": 300, "height": 300},
}
PLAN_RESPONSE = {
    "description": "The best k distinct grasps, best first; none (with a reason) when the image has nothing to grasp.",
    "content": {"application/json": {"schema": {
        "type": "object", "required": ["grasps", "reason", "counts", "seconds", "model_version", "k", "seed", "cem", "intrinsics"],
        "properties": {
            "grasps": {"type": "array", "items": _PLANNED_GRASP},
            "reason": {"type": ["string", "null"], "description": "why there are no grasps (null when there are)"},
            "counts": {"type": "object", "description": "candidates at each stage"},
            "seconds": {"type": "object", "additionalProperties": {"type": "number"}, "description": "time of each stage"},
            "model_version": {"type": "string"}, "k": {"type": "integer"}, "seed": {"type": "integer"},
            "cem": {"type": "integer"},
            "intrinsics": {"type": "object", "required": ["fx", "fy", "cx", "cy", "width", "height"],
                           "description": "the camera the image was planned with (px)"}}},
        "example": PLAN_EXAMPLE}},
}
