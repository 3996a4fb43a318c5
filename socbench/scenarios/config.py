"""Checked construction of the scenario dataclasses from TOML tables.

Each dataclass validates its own values in ``__post_init__`` and raises :class:`FieldError` naming the field;
:func:`build` checks for unknown keys and wrong types and turns every problem into one :class:`ConfigError` line
``"<file>: key '<section>.<field>': <what is wrong>"``.
"""

from __future__ import annotations

import types
import typing
from dataclasses import MISSING, fields

from ..errors import ConfigError


class FieldError(ConfigError):
    """An impossible value of one field (the builder adds the file and the section)."""

    def __init__(self, key: str, message: str):
        self.key = key
        self.message = message
        super().__init__(f"key '{key}': {message}")


def require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise FieldError(key, message)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_type(value, annotation, key: str):
    """Coerce ``value`` to the field's annotated type (ints to floats), or raise FieldError."""
    if isinstance(annotation, str):
        annotation = {"float": float, "int": int, "bool": bool, "str": str}.get(annotation.split("|")[0].strip(),
                                                                                 object)
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        annotation = args[0] if len(args) == 1 else object
    if annotation is float:
        if not _is_number(value):
            raise FieldError(key, f"must be a number, got {value!r}")
        return float(value)
    if annotation is int:
        if not (_is_number(value) and float(value).is_integer()):
            raise FieldError(key, f"must be an integer, got {value!r}")
        return int(value)
    if annotation is bool:
        if not isinstance(value, bool):
            raise FieldError(key, f"must be true or false, got {value!r}")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise FieldError(key, f"must be a string, got {value!r}")
        return value
    return value


def build(cls, table: dict, section: str, where: str, skip: tuple = (), **extra):
    """``cls(**table, **extra)`` with unknown-key, type and value checks reported as one ConfigError line."""
    prefix = f"{section}." if section else ""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: key '{section}': must be a table")
    known = {f.name: f for f in fields(cls) if f.name not in skip}
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for key, value in table.items():
        if key not in known:
            raise ConfigError(f"{where}: unknown key '{prefix}{key}' (known: {', '.join(sorted(known))})")
        try:
            kwargs[key] = _check_type(value, hints.get(key, object), key)
        except FieldError as exc:
            raise ConfigError(f"{where}: key '{prefix}{exc.key}': {exc.message}") from None
    try:
        return cls(**kwargs, **extra)
    except FieldError as exc:
        raise ConfigError(f"{where}: key '{prefix}{exc.key}': {exc.message}") from None


def defaults(cls) -> dict:
    """Field defaults of a dataclass (for listings)."""
    out = {}
    for f in fields(cls):
        if f.default is not MISSING:
            out[f.name] = f.default
    return out
