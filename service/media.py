"""Media types: the one parser of a Content-Type / Accept value, and the names used."""

from __future__ import annotations

JSON = "application/json"
OCTET = "application/octet-stream"
NPZ = "application/x-npz"
MULTIPART = "multipart/form-data"


def media_type(header: str | None) -> str:
    """``"Application/X-NPY; charset=binary"`` -> ``"application/x-npy"`` ("" when absent)."""
    return (header or "").split(";", 1)[0].strip().lower()


def accepts(header: str | None, media: str) -> bool:
    """Whether an Accept header names ``media`` (exactly; wildcards do not select binary answers)."""
    return any(media_type(item) == media for item in (header or "").split(","))
