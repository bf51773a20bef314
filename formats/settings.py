"""Typed settings from YAML: one strict base, one loader, one override rule, one error format.

Every settings class of the toolkit (model, rig, scene, simulation, calibration, fit) derives from
``Strict``: unknown keys are refused, values are frozen, defaults are validated. ``load_settings``
reads them all the same way:

1. the embedded defaults (the class's own, or a shipped YAML file given as ``default_path``);
2. a YAML file, if given, replacing the defaults' file;
3. ``overrides`` (command-line options), merged by the one rule, ``merge``: a mapping merges into a
   mapping key by key, at any depth; anything else replaces what was there.

A file that cannot be used raises the caller's error class (a ``SettingsError``) with the file and the
first bad key named, and one clause per problem: ``FILE: key.path: message (got value)``, the value cut
to a readable length.

Settings are small, and a file is data, not instructions: a file is read only up to
``MAX_SETTINGS_BYTES``; YAML's anchors and aliases are allowed, but the document they build may hold at
most ``MAX_SETTINGS_NODES`` values at most ``MAX_SETTINGS_DEPTH`` deep (an "alias bomb" of a few lines
stands for a billion values); and a number must be finite (``allow_inf_nan=False``: ``.inf`` and
``.nan`` are refused wherever a number is meant).
"""

from __future__ import annotations

import reprlib
from pathlib import Path
from typing import Annotated, Any, Mapping, TypeVar

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from .errors import SettingsError

__all__ = ["MAX_SETTINGS_BYTES", "MAX_SETTINGS_DEPTH", "MAX_SETTINGS_NODES", "PixelBox", "SettingsError", "Strict", "format_validation_error", "load_settings", "merge", "read_yaml_mapping", "validate_settings"]

S = TypeVar("S", bound=BaseModel)

#: The longest rejected value an error message shows (a whole rejected document is no help to read).
_SHOWN_VALUE_CHARS = 120
#: The largest settings file read (the biggest shipped one is under 10 kB).
MAX_SETTINGS_BYTES = 1 << 20
#: The most values, and the deepest nesting, a settings document may hold once its aliases are expanded.
MAX_SETTINGS_NODES = 100_000
MAX_SETTINGS_DEPTH = 32


class Strict(BaseModel):
    """Settings: unknown keys refused, frozen once made, defaults validated like given values, numbers finite."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, protected_namespaces=(), allow_inf_nan=False)


def _box(value: list[int]) -> list[int]:
    if not (0 <= value[0] < value[2] and 0 <= value[1] < value[3]):
        raise ValueError(f"must be [x0, y0, x1, y1] with 0 <= x0 < x1 and 0 <= y0 < y1, got {value}")
    return value


#: A half-open box of raw sensor pixels ``[x0, y0, x1, y1]`` (the gray card's region).
PixelBox = Annotated[list[int], Field(min_length=4, max_length=4), AfterValidator(_box)]


def read_yaml_mapping(path: str | Path, error: type[Exception] = SettingsError, what: str = "") -> dict:
    """The mapping at the top of a YAML file (loaded safely; empty file: ``{}``). Raises ``error`` naming
    the file and the problem: unreadable, not YAML, or not a mapping (``what``: "of settings", …)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_SETTINGS_BYTES + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > MAX_SETTINGS_BYTES:
        raise error(f"{path}: larger than {MAX_SETTINGS_BYTES >> 10} kB; a settings file is a few kB (is this the right file?)")
    try:
        data = yaml.safe_load(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML ({_shorten(' '.join(str(exc).split()))})") from None
    except RecursionError:  # the parser recurses once per level of nesting
        raise error(f"{path}: nested more than {MAX_SETTINGS_DEPTH} levels deep; refused") from None
    _check_size(data, path, error)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping {what + ' ' if what else ''}at the top level")
    return data


def _check_size(data: Any, path: Path, error: type[Exception]) -> None:
    """Refuse a document of more than ``MAX_SETTINGS_NODES`` values or ``MAX_SETTINGS_DEPTH`` levels,
    counting every use of an alias (safe_load shares aliased objects, so the count stops the walk of an
    alias bomb long before it would expand)."""
    budget = MAX_SETTINGS_NODES
    stack = [(data, 1)]
    while stack:
        value, depth = stack.pop()
        budget -= 1
        if budget < 0:
            raise error(f"{path}: holds more than {MAX_SETTINGS_NODES} values once its aliases are expanded; refused")
        if depth > MAX_SETTINGS_DEPTH:
            raise error(f"{path}: nested more than {MAX_SETTINGS_DEPTH} levels deep; refused")
        if isinstance(value, dict):
            stack.extend((v, depth + 1) for v in value.values())
        elif isinstance(value, (list, tuple)):
            stack.extend((v, depth + 1) for v in value)


def merge(base: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict:
    """``base`` with ``overrides`` merged in: mappings key by key at any depth, anything else replaced."""
    out = dict(base)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def validate_settings(cls: type[S], data: Mapping[str, Any], error: type[Exception] = SettingsError, source: str = "settings") -> S:
    """``cls`` validated from ``data``; ``error`` names ``source`` (a file or what the settings are), the
    first bad key and every problem."""
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        failure = error(f"{source}: {format_validation_error(exc)}")
        failure.key = _key(exc.errors()[0]) if exc.errors() else None
        raise failure from None


def load_settings(
    cls: type[S],
    path: str | Path | None = None,
    error: type[Exception] = SettingsError,
    name: str = "settings",
    overrides: Mapping[str, Any] | None = None,
    *,
    default_path: str | Path | None = None,
) -> S:
    """Settings of class ``cls``: defaults, then the YAML file ``path`` (or ``default_path``, a shipped
    file, when ``path`` is None), then ``overrides`` by ``merge``. Errors name the file, or ``name``."""
    source = path if path is not None else default_path
    data = read_yaml_mapping(source, error, "of settings") if source is not None else {}
    data = merge(data, overrides or {})
    return validate_settings(cls, data, error, str(source) if source is not None else name)


def _key(err: dict) -> str:
    return ".".join(str(p) for p in err["loc"]) or "(top level)"


def format_validation_error(exc: ValidationError) -> str:
    """One clause per problem, ``key.path: message (got value)``, joined by "; "."""
    clauses = []
    for err in exc.errors():
        msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        got = err.get("input")
        shown = err["type"] != "extra_forbidden" and not isinstance(got, dict)
        clauses.append(f"{_key(err)}: {msg}" + (f" (got {_shown(got)})" if shown else ""))
    return "; ".join(clauses)


_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = _SHOWN_VALUE_CHARS
_REPR.maxlist = _REPR.maxtuple = 16


def _shown(value: Any) -> str:
    """``repr(value)``, bounded: reprlib stops at depth and length, so a huge value costs no memory."""
    return _shorten(_REPR.repr(value))


def _shorten(text: str) -> str:
    return text if len(text) <= _SHOWN_VALUE_CHARS else text[: _SHOWN_VALUE_CHARS - 3] + "..."
