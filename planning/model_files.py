"""What the planner keeps beside a model (its calibration, its ranker): one JSON file each in the
model folder, fitted on judged pools of planner candidates and read when the model loads."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from vgq import atomic

T = TypeVar("T")


def read(model_dir: str | Path, name: str, key: str | None, parse: Callable[[dict], T], what: str) -> T | None:
    """``parse(file[key])`` (``key`` None: the whole file) of the JSON file ``name`` in
    ``model_dir``, or None when the folder has none; ValueError naming the file when it is not
    ``what``."""
    p = Path(model_dir) / name
    if not p.is_file():
        return None
    try:
        data = json.loads(p.read_text())
        return parse(data if key is None else data[key])
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{p}: not {what} ({e})") from None


def check_model_folder(model_dir: str | Path) -> None:
    """ValueError unless ``model_dir`` is a model folder (holds a model card)."""
    if not (Path(model_dir) / "model_card.json").is_file():
        raise ValueError(f"{model_dir}: not a model folder (no model_card.json)")


def write(model_dir: str | Path, name: str, record: dict) -> Path:
    """Write ``record`` as ``name`` in the model folder, atomically; its path."""
    p = Path(model_dir) / name
    atomic.write_bytes(p, json.dumps(record, indent=1).encode())
    return p
