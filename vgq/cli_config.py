"""The one bridge from a configuration dataclass to command-line flags, environment
variables and JSON files, used by every CLI (training, service, datagen).

A dataclass stays the one place where settings are defined. :func:`add_options` adds one
flag per leaf field (``--batch-size``; a nested dataclass's fields as ``--section.field``),
and :func:`build` fills the dataclass with the precedence

    defaults < config file (JSON) < environment (``<PREFIX><NAME>``) < overrides < flags

where only given flags count. Values are coerced to the annotated types (:func:`coerce`
for JSON values, :func:`parse_text` for flag and environment text); a bad value, an
unknown key or a value the dataclass's own ``__post_init__`` refuses raises one
:class:`ConfigError` naming the field, which a CLI turns into exit 2 with one line.
Field metadata ``choices`` and ``help`` (``field(metadata={"choices": ...})``) reach the flags.
Standard library only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path

__all__ = [
    "ConfigError",
    "add_options",
    "build",
    "coerce",
    "from_dict",
    "leaf_fields",
    "load_json_object",
    "parse_override",
    "parse_text",
]

Check = Callable[[str, str, object], None]  # (dotted path, field name, coerced value); raises ConfigError


class ConfigError(ValueError):
    """A configuration value, key or file is invalid; the message names the field or file."""


def _is_dataclass_type(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


# ----------------------------------------------------------------------------- JSON values -> dataclass


def from_dict(cls, d, prefix: str = "", check: Check | None = None):
    """Instantiate dataclass ``cls`` from dict ``d`` (JSON values), recursing into nested
    dataclasses; missing keys keep their defaults, unknown keys are refused. ``check`` is
    called on every coerced non-dataclass leaf (extra, caller-specific validation)."""
    where = prefix.rstrip(".") or "config"
    if not isinstance(d, dict):
        raise ConfigError(f"{where} must be a JSON object, got {type(d).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(d) - names)
    if unknown:
        raise ConfigError(f"unknown config field '{prefix}{unknown[0]}' (known: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if not f.init or f.name not in d:
            continue
        tp = hints.get(f.name)
        kwargs[f.name] = coerce(tp, d[f.name], f"{prefix}{f.name}", check)
        if check is not None and not _is_dataclass_type(tp):
            check(f"{prefix}{f.name}", f.name, kwargs[f.name])
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}" if prefix else str(e)) from e


def coerce(tp, value, name: str, check: Check | None = None):
    """Convert a JSON value to the annotated type ``tp`` (dataclass, tuple, dict, int,
    float, bool, str, unions); ``name`` is the field's dotted path for the error message."""
    if tp is None:
        return value
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        last = None
        for a in args:
            if a is type(None):
                continue
            try:
                return coerce(a, value, name, check)
            except ConfigError as e:
                last = e
        raise last or ConfigError(f"{name}: bad value {value!r}")
    if _is_dataclass_type(tp):
        return from_dict(tp, value, name + ".", check)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(f"{name} must be an integer, got {value!r}")
        return int(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name} must be a string, got {value!r}")
        return value
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{name} must be a JSON object, got {value!r}")
        kt, vt = args or (None, None)
        return {coerce(kt, k, f"{name} key {k!r}"): coerce(vt, v, f"{name}.{k}") for k, v in value.items()}
    if origin is tuple or tp is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name} must be a list, got {value!r}")
        if args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{name} must have {len(args)} entries, got {len(value)}")
            return tuple(coerce(a, v, f"{name}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        inner = args[0] if args else None
        return tuple(coerce(inner, v, f"{name}[{i}]") for i, v in enumerate(value))
    return value


# ----------------------------------------------------------------------------- text -> values

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off", "")


def parse_text(tp, raw: str, name: str):
    """A flag's or environment variable's text as a value of type ``tp``: strings as they
    are, booleans from 1/true/yes/on and 0/false/no/off, numbers as Python writes them
    (``inf`` too), anything else (tuples, dicts, optional values) as JSON."""
    if tp is str:
        return raw
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and set(typing.get_args(tp)) == {str, type(None)}:
        return None if raw == "null" else raw
    if tp is bool:
        if raw.strip().lower() in _TRUE:
            return True
        if raw.strip().lower() in _FALSE:
            return False
        raise ConfigError(f"{name} must be true or false, got {raw!r}")
    if tp in (int, float):
        try:
            return tp(raw.strip())
        except ValueError:
            kind = "an integer" if tp is int else "a number"
            raise ConfigError(f"{name} must be {kind}, got {raw!r}") from None
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return coerce(tp, value, name)


def parse_override(text: str) -> tuple[str, object]:
    """``"camera.d_range=[0.5, 0.9]"`` -> ``("camera.d_range", [0.5, 0.9])`` (value as JSON, else the string)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like section.field=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key, value


def load_json_object(path: str | Path) -> dict:
    """The JSON object in file ``path``; errors name the file."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} does not exist")
    try:
        d = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"config file {p} is not valid JSON ({e})") from e
    if not isinstance(d, dict):
        raise ConfigError(f"config file {p} must hold a JSON object, got {type(d).__name__}")
    return d


# ----------------------------------------------------------------------------- dataclass -> flags


def leaf_fields(cls, skip=(), prefix: str = ""):
    """``(dotted path, annotated type, field)`` of every leaf field of ``cls``, nested
    dataclasses flattened to ``section.field``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        path = prefix + f.name
        if not f.init or path in skip:
            continue
        tp = hints.get(f.name)
        if _is_dataclass_type(tp):
            yield from leaf_fields(tp, skip, path + ".")
        else:
            yield path, tp, f


def _default_of(cls, path: str):
    obj = cls()
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _flag(path: str) -> str:
    return "--" + path.replace("_", "-")


def add_options(
    parser: argparse.ArgumentParser,
    cls,
    *,
    skip=(),
    choices: Mapping[str, tuple] | None = None,
    env_prefix: str | None = None,
) -> None:
    """One flag per leaf field of dataclass ``cls``: ``--field-name`` (nested:
    ``--section.field-name``), dest the dotted path, default ``None`` (so :func:`build`
    only overrides with given flags). Booleans get ``--x/--no-x``; other values are text
    parsed by :func:`parse_text` (tuples as JSON, e.g. ``--camera.d-range [0.5,0.9]``).
    Choices and help come from ``field(metadata=...)`` or the ``choices`` mapping."""
    choices = dict(choices or {})
    for path, tp, f in leaf_fields(cls, skip):
        try:
            default = _default_of(cls, path)
        except TypeError:  # a field without a default
            default = None
        help_ = f.metadata.get("help", "")
        env = f" env {env_prefix}{path.upper().replace('.', '_')};" if env_prefix else ""
        help_ = f"{help_}{'; ' if help_ else ''}{env.strip()} default {default!r}".strip()
        help_ = help_.replace("%", "%%")  # argparse formats help with %
        if tp is bool:
            parser.add_argument(_flag(path), dest=path, default=None, action=argparse.BooleanOptionalAction, help=help_)
            continue
        ch = f.metadata.get("choices", choices.get(path))
        name = getattr(tp, "__name__", "value")
        parser.add_argument(
            _flag(path),
            dest=path,
            default=None,
            choices=tuple(ch) if ch else None,
            metavar=None if ch else name.upper(),
            help=help_,
        )


def build(
    cls,
    args: argparse.Namespace | Mapping | None = None,
    *,
    environ: Mapping[str, str] | None = None,
    env_prefix: str | None = None,
    file: str | Path | None = None,
    base=None,
    overrides: Mapping[str, object] | None = None,
    check: Check | None = None,
):
    """Dataclass ``cls`` from defaults (or the instance ``base``) < ``file`` (JSON object) < environment
    (``<env_prefix><PATH>``, dots as underscores, upper case; only with ``env_prefix``)
    < ``overrides`` (``{"section.field": JSON value}``) < ``args`` (parsed flags or a
    mapping of dotted paths; ``None`` values are not given). Raises :class:`ConfigError`."""
    d: dict = dataclasses.asdict(base) if base is not None else {}
    if file is not None:
        _merge(d, load_json_object(file))
    leaves = {path: tp for path, tp, _ in leaf_fields(cls)}
    if env_prefix is not None:
        environ = os.environ if environ is None else environ
        for path, tp in leaves.items():
            key = env_prefix + path.upper().replace(".", "_")
            if key in environ:
                _set_path(d, path, _text_to_json(tp, environ[key], key))
    for key, value in (overrides or {}).items():
        _set_path(d, key, value)
    given = vars(args) if isinstance(args, argparse.Namespace) else dict(args or {})
    for path, tp in leaves.items():
        value = given.get(path)
        if value is None:
            continue
        _set_path(d, path, _text_to_json(tp, value, _flag(path)) if isinstance(value, str) else value)
    return from_dict(cls, d, check=check)


def _text_to_json(tp, raw: str, name: str):
    """Parse text now (so the error names the variable or flag); tuples stay lists for from_dict."""
    v = parse_text(tp, raw, name)
    return list(v) if isinstance(v, tuple) else v


def _merge(dst: dict, src: dict) -> None:
    """Deep-merge JSON object ``src`` into ``dst`` (sections merge, values replace)."""
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            _merge(dst[k], v)
        else:
            dst[k] = v


def _set_path(d: dict, key: str, value) -> None:
    parts = key.split(".")
    cur = d
    for i, part in enumerate(parts[:-1]):
        nxt = cur.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"config section {'.'.join(parts[: i + 1])!r} must be a JSON object")
        cur = nxt
    cur[parts[-1]] = value
