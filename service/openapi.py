"""OpenAPI descriptions of the raw (non-pydantic) request and response bodies, with examples."""

from __future__ import annotations

from .depth_io import DEPTH_TYPES
from .numbers import ONE_SHOT_NUMBERS

_ERROR = {
    "type": "object",
    "required": ["error"],
    "properties": {
        "error": {
            "type": "object",
            "required": ["status", "message"],
            "properties": {
                "status": {"type": "integer"},
                "message": {"type": "string"},
                "details": {
                    "type": "object",
                    "properties": {
                        "grasps": {"type": "array", "items": {"type": "integer"}},
                        "field": {"type": "string", "description": "the input at fault"},
                    },
                },
            },
        }
    },
}
_WHAT = {
    400: "malformed request or body",
    401: "missing or wrong API key",
    404: "unknown or evicted image id",
    408: "request headers or body not received in time (the connection is closed)",
    413: "body over the size limit (the connection is closed)",
    414: "request target too long (the connection is closed)",
    415: "unsupported content type",
    422: "invalid parameter, depth image or grasps (the message names them)",
    431: "request headers too large or too many (the connection is closed)",
    503: "model not ready, or too many requests, body bytes or waiting plans in flight (Retry-After says when to retry)",
}
PROTOCOL = (400, 408, 414, 431)  # answered by the HTTP layer for any operation
BODY_ERRORS = PROTOCOL + (401, 404, 413, 415, 422, 503)


def errors(codes) -> dict:
    """OpenAPI ``responses`` entries (the JSON error shape) for these status codes."""
    return {code: {"description": _WHAT[code], "content": {"application/json": {"schema": _ERROR}}} for code in codes}


STATUS_RESPONSE = {
    "description": "status",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["status"],
                "properties": {"status": {"type": "string"}, "model_version": {"type": "string"}},
            }
        }
    },
}
NOT_READY = {
    "description": "model loading or failed",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["status"],
                "properties": {
                    "status": {"type": "string", "enum": ["loading", "failed"]},
                    "error": {"type": ["string", "null"]},
                },
            }
        }
    },
}
MODEL_RESPONSE = {
    "description": "the model card (no file-system paths) and the limits in force",
    "content": {
        "application/json": {
            "schema": {"type": "object", "required": ["model_card", "head_precision", "limits", "depth_content_types"]}
        }
    },
}
CACHE_RESPONSE = {
    "description": "cache statistics",
    "content": {
        "application/json": {
            "schema": {"type": "object", "required": ["backend", "entries", "bytes", "hits", "misses", "evictions"]}
        }
    },
}

_GRASP_ROW = {
    "type": "array",
    "items": {"type": "number"},
    "minItems": 7,
    "maxItems": 7,
    "description": "u (px, column), v (px, row), z (m, camera frame), qw, qx, qy, qz (camera frame)",
}
_GRASPS_JSON = {
    "type": "object",
    "required": ["grasps"],
    "properties": {"grasps": {"type": "array", "items": _GRASP_ROW}},
    "example": {"grasps": [[150.0, 148.5, 0.62, 0.0, 1.0, 0.0, 0.0], [140.0, 160.0, 0.61, 0.0, 0.7071, 0.7071, 0.0]]},
}
_BINARY = {"type": "string", "format": "binary"}

UPLOAD_BODY = {
    "required": True,
    "description": "Depth image in metres (camera frame z; 0 = no reading).",
    "content": {
        "application/x-npy": {"schema": _BINARY, "description": ".npy float32 (H, W) metres"},
        "image/png": {"schema": _BINARY, "description": "16-bit grayscale PNG, millimetres"},
        "application/octet-stream": {
            "schema": _BINARY,
            "description": "raw little-endian float32, needs width and height",
        },
    },
}
_INTR = {"type": "object", "properties": {k: {"type": "number"} for k in ("fx", "fy", "cx", "cy")}}
_CAMERA = {
    "intrinsics": {**_INTR, "description": "the camera's intrinsics (px) as used: given, or assumed"},
    "intrinsics_assumed": {
        "type": "array",
        "items": {"type": "string", "enum": ["fx", "fy", "cx", "cy"]},
        "description": "intrinsics not sent: fx, fy the model's, (cx, cy) the image centre",
    },
    "resampled": {
        "type": "object",
        "description": "the image at the model's focal length (what is cropped)",
        "properties": {
            "image_shape": {"type": "array", "items": {"type": "integer"}},
            "scale": {"type": "array", "items": {"type": "number"}},
            "intrinsics": _INTR,
        },
    },
    "level": {
        "type": "object",
        "description": "the world's up direction as sent (up_x, up_y, up_z) or read from the table plane "
        "(level=table; null: neither, the camera taken as level), the roll (deg) the image was turned about the "
        "optical axis to make its rows level as the training cameras' were (0 under 0.5 deg or looking straight "
        "down; a quarter or half turn within 0.5 deg is that turn), the camera's tilt from straight down (deg; the "
        "training cameras': 0 to 70), and where the up came from",
        "properties": {
            "up": {"type": ["array", "null"], "items": {"type": "number"}},
            "roll_deg": {"type": "number"},
            "tilt_deg": {"type": ["number", "null"]},
            "from": {"type": ["string", "null"], "enum": ["client", "table", None]},
        },
    },
}
_PLACEMENT_FOUND = {
    "table_found": {
        "type": "boolean",
        "description": "the image as uploaded shows a table plane (RANSAC, planning.placement)",
    },
}
_UPLOAD_PLACEMENT = {
    "type": "object",
    "required": ["table_found", "objects"],
    "description": "only for a model whose head reads placement rows (GET /v1/model: model_card.placement_columns): "
    "what the image as uploaded says about where grasps sit on their objects (vgq.placement); without a table, "
    "every grasp's placement row is unknown (all 0) and the model scores on its window and pose alone",
    "properties": {
        **_PLACEMENT_FOUND,
        "objects": {"type": "integer", "minimum": 0, "description": "object regions found above the table"},
    },
}
_SCORE_PLACEMENT = {
    "type": "object",
    "required": ["table_found", "known"],
    "description": "only for a model whose head reads placement rows: each grasp's placement row (where it sits on "
    "its object, from the image as uploaded, vgq.placement) was passed to the head after its pose",
    "properties": {
        **_PLACEMENT_FOUND,
        "known": {
            "type": "array",
            "items": {"type": "boolean"},
            "description": "per grasp: its placement row is known (a table and an object region at the grasp); "
            "false: the row was all 0 (unknown)",
        },
    },
}
_NOT_LEVELLED = {"up": None, "roll_deg": 0.0, "tilt_deg": None, "from": None}
_CAMERA_EXAMPLE = {
    "intrinsics": {"fx": 615.0, "fy": 615.0, "cx": 319.5, "cy": 239.5},
    "intrinsics_assumed": [],
    "resampled": {
        "image_shape": [410, 546],
        "scale": [0.853125, 0.8541666666666666],
        "intrinsics": {"fx": 524.671875, "fy": 525.3125, "cx": 272.5, "cy": 204.5},
    },
    "level": _NOT_LEVELLED,
}
UPLOAD_RESPONSE = {
    "description": "The image's id (content-addressed), its camera, and how grasps get windows: `grid` (anywhere in "
    "the image) or `fixed` (within grasp_range, client px).",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["image_id", "cached", "model_version"],
                "properties": {
                    "image_id": {"type": "string"},
                    "cached": {"type": "boolean"},
                    "model_version": {"type": "string"},
                    "image_shape": {"type": "array", "items": {"type": "integer"}},
                    **_CAMERA,
                    "windows": {"type": "string", "enum": ["grid", "fixed"]},
                    "window_center": {
                        "type": "array",
                        "items": {"type": "number"},
                        "description": "fixed window only (client px)",
                    },
                    "missing_fraction": {
                        "type": "number",
                        "minimum": 0,
                        "maximum": 1,
                        "description": "share of pixels without a depth reading (0): of the fixed window, else of the image",
                    },
                    "grasp_range": {
                        "type": "object",
                        "properties": {
                            "u": {"type": "array", "items": {"type": "number"}},
                            "v": {"type": "array", "items": {"type": "number"}},
                        },
                    },
                    "placement": _UPLOAD_PLACEMENT,
                },
            },
            "examples": {
                "grid": {
                    "summary": "a 640 x 480 image of a 615 px camera: grasps anywhere",
                    "value": {
                        "image_id": "3f1c0e9a5b7d4c2e8f6a1b3c5d7e9f01",
                        "cached": False,
                        "model_version": "fast_vgqcnn-0123456789ab",
                        "image_shape": [480, 640],
                        "missing_fraction": 0.004,
                        **_CAMERA_EXAMPLE,
                        "windows": "grid",
                    },
                },
                "fixed": {
                    "summary": "center_u / center_v given, model intrinsics assumed",
                    "value": {
                        "image_id": "9a0b1c2d3e4f5061728394a5b6c7d8e9",
                        "cached": False,
                        "model_version": "fast_vgqcnn-0123456789ab",
                        "image_shape": [300, 300],
                        "missing_fraction": 0.012,
                        "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 149.5, "cy": 149.5},
                        "intrinsics_assumed": ["fx", "fy", "cx", "cy"],
                        "resampled": {
                            "image_shape": [300, 300],
                            "scale": [1.0, 1.0],
                            "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 149.5, "cy": 149.5},
                        },
                        "level": _NOT_LEVELLED,
                        "windows": "fixed",
                        "window_center": [149.5, 149.5],
                        "grasp_range": {"u": [113.5, 185.5], "v": [113.5, 185.5]},
                    },
                },
            },
        }
    },
}
SCORE_BODY = {
    "required": True,
    "content": {
        "application/json": {"schema": _GRASPS_JSON},
        "application/octet-stream": {"schema": _BINARY, "description": "little-endian float32, k x 7 row-major"},
    },
}
_PER_GRASP = {"type": "array", "items": {"type": "number", "minimum": 0, "maximum": 1}}
SCORE_RESPONSE = {
    "description": "Per grasp, in request order: `p_success`, the calibrated probability of success at the dataset's native "
    "positivity (= `raw_score` when `calibrated` is false: the model card has no calibration); `raw_score`, the "
    "network's output (trained on resampled, class-balanced data: rank by it, do not read it as a probability); "
    "`ood`, the reasons the score is not to be trusted, and `ood_mask`, the same as bits (1 approach away from "
    "the camera, 2 z outside the training range, 4 centre on missing depth, 8 window mostly missing).",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["image_id", "p_success", "raw_score", "ood", "ood_mask", "calibrated", "model_version"],
                "properties": {
                    "image_id": {"type": "string"},
                    "cached": {"type": "boolean"},
                    "model_version": {"type": "string"},
                    "p_success": _PER_GRASP,
                    "raw_score": _PER_GRASP,
                    "calibrated": {"type": "boolean"},
                    "ood": {
                        "type": "array",
                        "items": {
                            "type": "array",
                            "items": {
                                "type": "string",
                                "enum": [
                                    "approach_away_from_camera",
                                    "z_outside_training_range",
                                    "center_on_missing_depth",
                                    "window_mostly_missing",
                                    "camera_tilt_outside_training",
                                ],
                            },
                        },
                    },
                    "ood_mask": {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 31}},
                    "windows": {"type": "integer", "description": "crop windows the grasps fell in"},
                    "windows_encoded": {
                        "type": "integer",
                        "description": "of them, encoded by this request (the rest were cached)",
                    },
                    "missing_fraction": {
                        "type": "number",
                        "description": "largest share of missing depth among those windows",
                    },
                    **_CAMERA,
                    "placement": _SCORE_PLACEMENT,
                },
            },
            "example": {
                "image_id": "3f1c0e9a5b7d4c2e8f6a1b3c5d7e9f01",
                "model_version": "fast_vgqcnn-0123456789ab",
                "p_success": [0.81, 0.07, 0.4],
                "raw_score": [0.81, 0.07, 0.4],
                "calibrated": False,
                "ood": [[], ["approach_away_from_camera"], ["z_outside_training_range", "center_on_missing_depth"]],
                "ood_mask": [0, 1, 6],
                "windows": 2,
                "windows_encoded": 1,
                "missing_fraction": 0.01,
            },
        },
        "application/octet-stream": {
            "schema": _BINARY,
            "description": "little-endian float32 p_success (k,), with Accept: "
            "application/octet-stream; headers x-calibrated (true / false), x-ood-count (grasps with "
            "a flag: ask for JSON to see which), x-windows-encoded, x-image-id; for a model whose head reads "
            "placement rows also x-placement-known (grasps whose placement row is known)",
        },
    },
}
STRICT = {
    "name": "strict",
    "in": "query",
    "required": False,
    "schema": {"type": "boolean", "default": False},
    "description": "true: any grasp with an out-of-distribution flag makes the request a 422 listing grasps and reasons",
}
ONE_SHOT_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": ["depth", "grasps"],
                "properties": {
                    "depth": _BINARY,
                    "grasps": {
                        "type": "string",
                        "minLength": 1,
                        "description": 'JSON {"grasps": [[u, v, z, qw, qx, qy, qz], ...]}',
                    },
                    **{n.name: n.schema() for n in ONE_SHOT_NUMBERS},
                },
            },
            "encoding": {"depth": {"contentType": ", ".join(DEPTH_TYPES)}},
        },
        "application/x-npz": {
            "schema": _BINARY,
            "description": "arrays depth (H, W) float32 m, grasps (k, 7), optional "
            "intrinsics (4,) = fx, fy, cx, cy px and center (2,)",
        },
    },
}

PLAN_ERRORS = PROTOCOL + (401, 404, 413, 415, 422, 503)  # 404: a JSON body's image id is unknown or evicted
IMAGE_PLAN_ERRORS = PROTOCOL + (401, 404, 413, 422, 503)
PLAN_IMAGE_ID_BODY = {
    "type": "object",
    "required": ["image_id"],
    "additionalProperties": False,
    "properties": {"image_id": {"type": "string", "description": "the id POST /v1/images answered"}},
}
PLAN_BODY = {
    "required": True,
    "description": "Depth image in metres (camera frame z; 0 = no reading), as for POST /v1/images; or JSON "
    '{"image_id": ...} naming an uploaded image (planned as POST /v1/images/{image_id}/plan: with the '
    "camera given at upload, its encoded windows reused).",
    "content": {**UPLOAD_BODY["content"], "application/json": {"schema": PLAN_IMAGE_ID_BODY}},
}
_NUMBERS = {"type": "array", "items": {"type": "number"}}
_PLANNED_GRASP = {
    "type": "object",
    "required": ["row", "pose", "width", "contacts", "score", "ood_flags", "ood"],
    "properties": {
        "row": {
            **_GRASP_ROW,
            "description": "the grasp row u, v (px of the uploaded image), z (m), qw, qx, qy, qz (camera frame): "
            "what POST /v1/images/{id}/scores takes",
        },
        "u": {"type": "number"},
        "v": {"type": "number"},
        "z": {"type": "number"},
        "q": {**_NUMBERS, "minItems": 4, "maxItems": 4, "description": "qw, qx, qy, qz"},
        "pose": {
            "type": "array",
            "items": {**_NUMBERS, "minItems": 4, "maxItems": 4},
            "minItems": 4,
            "maxItems": 4,
            "description": "4 x 4 grasp frame in the camera frame (metres): x = jaw axis, z = approach, origin = TCP",
        },
        "width": {"type": "number", "description": "distance between the contacts (m)"},
        "contacts": {
            "type": "array",
            "items": {**_NUMBERS, "minItems": 3, "maxItems": 3},
            "minItems": 2,
            "maxItems": 2,
            "description": "the two observed contact points, camera frame (m)",
        },
        "score": {"type": "number", "minimum": 0, "maximum": 1, "description": "Fast-VGQ-CNN's P(success)"},
        "ood_flags": {"type": "integer", "minimum": 0, "description": "vgq.ood bitmask (0: in distribution)"},
        "ood": {"type": "array", "items": {"type": "string"}, "description": "names of the set ood flags"},
        "p_hold": {
            "type": ["number", "null"],
            "minimum": 0,
            "maximum": 1,
            "description": "probability that the grasp holds through the physics oracle's lift and shake, from the "
            "model's planner calibration (planner_calibration.json); null when the model has none",
        },
    },
}
PLAN_EXAMPLE = {  # vgq-plan examples/depth_example.npy --k 1 on the bundled model (rounded)
    "grasps": [
        {
            "u": 150.83,
            "v": 154.9,
            "z": 0.72562,
            "q": [0.86217, 0.49129, -0.08047, 0.09388],
            "row": [150.83, 154.9, 0.72562, 0.86217, 0.49129, -0.08047, 0.09388],
            "pose": [
                [0.96942, -0.24096, -0.04651, 0.00184],
                [0.08282, 0.49964, -0.86227, 0.00746],
                [0.23101, 0.83205, 0.50432, 0.72562],
                [0.0, 0.0, 0.0, 1.0],
            ],
            "width": 0.03075,
            "contacts": [[-0.01307, 0.00619, 0.72207], [0.01674, 0.00874, 0.72917]],
            "score": 0.931,
            "ood_flags": 0,
            "ood": [],
            "p_hold": 0.356,
        }
    ],
    "reason": None,
    "counts": {
        "object_pixels": 507,
        "table": True,
        "pairs": 313,
        "approaches": 1519,
        "checked": 512,
        "collision_free": 256,
        "table_collisions": 41,
        "point_collisions": 215,
        "windows": 1,
    },
    "seconds": {
        "resample": 0.0004,
        "scene": 0.0041,
        "sample": 0.0049,
        "encode": 0.0055,
        "score": 0.004,
        "select": 0.0004,
        "total": 0.025,
    },
    "model_version": "fast_vgqcnn-60b272a5a797",
    "ranked_by": "ranker",
    "k": 1,
    "seed": 0,
    "cem": 0,
    "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 149.5, "cy": 149.5, "width": 300, "height": 300},
    "level": _NOT_LEVELLED,
}
PLAN_RESPONSE = {
    "description": "The best k distinct grasps, best first; none (with a reason) when the image has nothing to grasp.",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": [
                    "grasps",
                    "reason",
                    "counts",
                    "seconds",
                    "model_version",
                    "ranked_by",
                    "k",
                    "seed",
                    "cem",
                    "intrinsics",
                ],
                "properties": {
                    "grasps": {"type": "array", "items": _PLANNED_GRASP},
                    "reason": {
                        "type": ["string", "null"],
                        "description": "why there are no grasps (null when there are)",
                    },
                    "counts": {"type": "object", "description": "candidates at each stage"},
                    "seconds": {
                        "type": "object",
                        "additionalProperties": {"type": "number"},
                        "description": "time of each stage",
                    },
                    "model_version": {"type": "string"},
                    "ranked_by": {
                        "type": "string",
                        "enum": ["ranker", "score"],
                        "description": "what ordered the grasps: the model's planner ranker (planner_ranker.json: "
                        "the score with the jaw width and the gripper's pose against the estimated table) or, for a "
                        "model without one, the score alone",
                    },
                    "k": {"type": "integer"},
                    "seed": {"type": "integer"},
                    "cem": {"type": "integer"},
                    "intrinsics": {
                        "type": "object",
                        "required": ["fx", "fy", "cx", "cy", "width", "height"],
                        "description": "the camera the image was planned with (px)",
                    },
                    "image_id": {"type": "string", "description": "the image planned on (a JSON body only)"},
                    "level": _CAMERA["level"],
                    "intrinsics_assumed": {
                        **_CAMERA["intrinsics_assumed"],
                        "description": "intrinsics not sent at upload (a JSON body only)",
                    },
                },
            },
            "example": PLAN_EXAMPLE,
        }
    },
}
IMAGE_PLAN_RESPONSE = {
    "description": "As POST /v1/plan, for the uploaded image: `intrinsics` is the camera given (or assumed) at "
    "upload, `intrinsics_assumed` the values that were not sent, `counts.windows_reused` the crop windows taken "
    "from the cache rather than encoded.",
    "content": {
        "application/json": {
            "schema": {
                **PLAN_RESPONSE["content"]["application/json"]["schema"],
                "required": [*PLAN_RESPONSE["content"]["application/json"]["schema"]["required"], "image_id"],
                "properties": {
                    **PLAN_RESPONSE["content"]["application/json"]["schema"]["properties"],
                    "image_id": {"type": "string"},
                    "intrinsics_assumed": _CAMERA["intrinsics_assumed"],
                },
            },
            "example": {
                **PLAN_EXAMPLE,
                "counts": {**PLAN_EXAMPLE["counts"], "windows_reused": 1},
                "image_id": "3f2a9c0d4e5b6a7f8091a2b3c4d5e6f7",
                "intrinsics_assumed": ["fx", "fy", "cx", "cy"],
            },
        }
    },
}
