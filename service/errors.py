"""The error type the service raises for client mistakes (an HTTP status + message), and the
redaction of file-system paths from anything it answers."""

from __future__ import annotations

import re

# an absolute POSIX or Windows path (at least two components): answers name files, never folders of this host;
# the service's own routes (/v1/...) are not paths of the host and stay whole
_ABS_PATH = re.compile(r"(?<![\w.~:/-])(?!/v\d+/)(?:[A-Za-z]:[\\/]|/)(?:[^\s'\"/\\:,;]+[\\/])+([^\s'\"/\\:,;]*)")


class ApiError(Exception):
    def __init__(self, status: int, message: str, details: dict | None = None, headers: dict | None = None):
        super().__init__(message)
        self.status = status
        self.message = message
        self.details = details or {}
        self.headers = headers or {}

    def to_dict(self) -> dict:
        d = {"status": self.status, "message": redact_paths(self.message)}
        if self.details:
            d["details"] = self.details
        return {"error": d}


#: fields whose values look like paths but are not files: ONNX node names (``/head/fc5/Gemm``)
NOT_PATHS = frozenset({"quantized_nodes"})


def redact_paths(obj):
    """``obj`` (str, or dicts / lists of them) with every absolute file-system path cut to its
    last part: ``/home/ci/data/crops`` -> ``crops``. URLs and the fields in NOT_PATHS are kept."""
    if isinstance(obj, str):
        return _ABS_PATH.sub(lambda m: m.group(1) or "<path>", obj)
    if isinstance(obj, dict):
        return {k: v if k in NOT_PATHS else redact_paths(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [redact_paths(v) for v in obj]
    return obj
