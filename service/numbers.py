"""The one path every number taken from a request goes through: query parameters, multipart
fields and .npz members alike. A ``Number`` names its field, checks the value (finite, in
range, integral where it must be; booleans are not numbers) and describes itself for the
OpenAPI document, so the schema and the check cannot disagree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ApiError

MAX_INT = 2**31 - 1  # integer fields (image sides) are bounded before any arithmetic on them
MAX_TEXT = 64  # characters of a number given as text (a 400-digit number is refused by length)


@dataclass(frozen=True)
class Number:
    """A numeric request field. Bounds: ``minimum`` / ``maximum`` inclusive, ``exclusive_minimum``
    strict; ``integer`` fields must hold a whole number (``3`` or ``3.0``)."""

    name: str
    description: str
    integer: bool = False
    minimum: float | None = None
    exclusive_minimum: float | None = None
    maximum: float | None = None

    def parse(self, raw) -> float | int | None:
        """``raw``: None (absent) -> None; text (query, form field) or a number (array element) ->
        float / int. Raises ApiError 422 naming the field, also for an empty value (``?fx=``: the
        schema says number, and a client that sent one meant some value; taking the default
        would answer for a camera it did not name)."""
        if raw is None:
            return None
        if isinstance(raw, (bool, np.bool_)):
            self._fail(raw, "a number, not true / false")
        if isinstance(raw, (bytes, bytearray)):
            raw = raw.decode("latin-1")
        if isinstance(raw, str):
            if len(raw) > MAX_TEXT:
                self._fail(raw, f"a number of at most {MAX_TEXT} characters")
            try:
                v = float(raw.strip())
            except ValueError:
                self._fail(raw, "an integer" if self.integer else "a number")
        else:
            try:
                v = float(raw)
            except (TypeError, ValueError, OverflowError):
                self._fail(raw, "an integer" if self.integer else "a number")
        if not math.isfinite(v):
            self._fail(raw, "finite")
        if self.integer and v != math.floor(v):
            self._fail(raw, "an integer")
        if self.minimum is not None and v < self.minimum:
            self._fail(raw, f">= {self.minimum:g}")
        if self.exclusive_minimum is not None and v <= self.exclusive_minimum:
            self._fail(raw, f"> {self.exclusive_minimum:g}")
        maximum = self.maximum if self.maximum is not None else (MAX_INT if self.integer else None)
        if maximum is not None and v > maximum:
            self._fail(raw, f"<= {maximum:g}")
        return int(v) if self.integer else v

    def _fail(self, raw, what: str):
        shown = raw if not isinstance(raw, str) or len(raw) <= 24 else raw[:20] + "..."
        raise ApiError(422, f"field {self.name} must be {what}, got {shown!r}", {"field": self.name})

    def schema(self) -> dict:
        s: dict = {"type": "integer" if self.integer else "number", "description": self.description}
        if self.minimum is not None:
            s["minimum"] = int(self.minimum) if self.integer else self.minimum
        if self.exclusive_minimum is not None:
            s["exclusiveMinimum"] = self.exclusive_minimum
        maximum = self.maximum if self.maximum is not None else (MAX_INT if self.integer else None)
        if maximum is not None:
            s["maximum"] = int(maximum) if self.integer else maximum
        return s

    def query_parameter(self) -> dict:
        return {
            "name": self.name,
            "in": "query",
            "required": False,
            "schema": self.schema(),
            "description": self.description,
        }


CENTER_U = Number(
    "center_u",
    "crop window centre, column (image px, u); default: the image centre; must lie in the image",
    minimum=0.0,
)
CENTER_V = Number(
    "center_v", "crop window centre, row (image px, v); default: the image centre; must lie in the image", minimum=0.0
)
WIDTH = Number("width", "image width (px), raw float32 bodies only", integer=True, minimum=1)
HEIGHT = Number("height", "image height (px), raw float32 bodies only", integer=True, minimum=1)
FX = Number(
    "fx",
    "the camera's focal length along u (px); the image is resampled to the model's (range: GET /v1/model, "
    "camera.focal_range_px); default: the model's",
    exclusive_minimum=0.0,
)
FY = Number(
    "fy",
    "the camera's focal length along v (px); default: fx when fx is given, else the model's",
    exclusive_minimum=0.0,
)
CX = Number("cx", "the camera's principal point, column (image px); must lie in the image; default: the image centre")
CY = Number("cy", "the camera's principal point, row (image px); must lie in the image; default: the image centre")
INTRINSICS = (FX, FY, CX, CY)
_UP = (
    "component of the world's up direction (against gravity) in the camera frame (x right, y down, z along "
    "the principal ray; any length; all three or none): the image is turned about the optical axis so its rows "
    "are level, as the training cameras' were; default: the camera is taken as level"
)
UP_X = Number("up_x", f"x {_UP}")
UP_Y = Number("up_y", f"y {_UP}")
UP_Z = Number("up_z", f"z {_UP}")
UP = (UP_X, UP_Y, UP_Z)


@dataclass(frozen=True)
class Choice:
    """A text query parameter that takes one of ``values`` (absent -> None; empty: 422, as for a Number)."""

    name: str
    description: str
    values: tuple[str, ...]

    def parse(self, raw) -> str | None:
        if raw is None:
            return None
        text = str(raw).strip().lower()
        if text in self.values:
            return text
        shown = text if len(text) <= 24 else text[:20] + "..."
        allowed = " or ".join(repr(v) for v in self.values)
        raise ApiError(422, f"field {self.name} must be {allowed} (or absent), got {shown!r}", {"field": self.name})

    def query_parameter(self) -> dict:
        schema = {"type": "string", "enum": list(self.values), "description": self.description}
        return {"name": self.name, "in": "query", "required": False, "schema": schema, "description": self.description}


LEVEL = Choice(
    "level",
    "'table': the service reads the world's up direction from the image itself, as the normal of the table "
    "plane the objects stand on (RANSAC), and turns the image level with it, for a camera whose mounting is "
    "not known (the answer's level.up says what it read; 422 when the image shows no table); instead of "
    "up_x, up_y, up_z",
    ("table",),
)

#: the numeric query parameters of an upload, and the numeric fields of a multipart one-shot
UPLOAD_NUMBERS = (CENTER_U, CENTER_V, WIDTH, HEIGHT, *INTRINSICS, *UP)
ONE_SHOT_NUMBERS = UPLOAD_NUMBERS

TRUE, FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def parse_flag(name: str, raw) -> bool:
    """A boolean query parameter (true / false / 1 / 0; absent = false); 422 naming it otherwise,
    an empty value (``?strict=``) included: the schema types it boolean."""
    if raw is None:
        return False
    text = str(raw).strip().lower()
    if text in TRUE:
        return True
    if text in FALSE:
        return False
    shown = text if len(text) <= 24 else text[:20] + "..."
    raise ApiError(422, f"field {name} must be true or false, got {shown!r}", {"field": name})


def request_key(content_type: str, numbers: dict) -> str:
    """The parameters that, with the body, make an upload's cache id (content type, shape, window,
    camera, and ``level`` when given)."""
    key = [content_type, *(repr(numbers.get(n.name)) for n in UPLOAD_NUMBERS)]
    if numbers.get(LEVEL.name) is not None:
        key.append(f"{LEVEL.name}={numbers[LEVEL.name]}")
    return ";".join(key)


def parse_all(numbers, source) -> dict:
    """``{name: value or None}`` for each Number, read from a mapping (query params, form)."""
    return {n.name: n.parse(source.get(n.name)) for n in numbers}
