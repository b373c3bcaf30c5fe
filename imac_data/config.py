"""Typed dataclasses from YAML/JSON mappings, strictly: the parser behind recipes
(:mod:`imac_data.recipes`) and the world model's run configs (:mod:`imac_model.config`).

Unknown keys, missing required fields and values of the wrong type are
:class:`~imac_data.errors.InputError` naming the field (``augment.height: expected an
integer, got '240'``). Supported hints: dataclasses (recursively), ``X | None`` and
unions, ``tuple[X, ...]`` (a YAML list), ``dict[str, X]``, ``Literal[...]``, ``Any``,
``bool``, ``int``, ``float`` (an integer is accepted) and ``str``.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Collection
from typing import Literal

from imac_data.errors import InputError

__all__ = ["parse_dataclass"]


def parse_dataclass(cls, value, where: str = "", *, root: str = "", skip: Collection[str] = ()):
    """Build dataclass ``cls`` from ``value``. ``where``: the field path of ``value``
    (messages); ``root``: the name messages use when ``where`` is empty; ``skip``: field
    names never read from a mapping, at any depth (set by the caller, like a recipe's file)."""
    label = where or root
    prefix = f"{label}: " if label else ""
    if not isinstance(value, dict):
        raise InputError(f"{prefix}expected a mapping, got {type(value).__name__}")
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.name not in skip]
    known = sorted(f.name for f in fields)
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise InputError(f"{prefix}unknown field(s) {unknown}; allowed: {known}")
    kwargs = {}
    for f in fields:
        if f.name not in value:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise InputError(f"{prefix}missing required field '{f.name}'")
            continue
        kwargs[f.name] = _coerce(hints[f.name], value[f.name], f"{where}.{f.name}" if where else f.name, skip)
    try:
        return cls(**kwargs)
    except InputError as e:  # a dataclass's own check: say where it sits unless it does
        raise InputError(f"{prefix}{e}" if where and not str(e).startswith(where) else str(e)) from None


def _coerce(hint, value, where: str, skip: Collection[str]):
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        last = None
        for arg in options:
            try:
                return _coerce(arg, value, where, skip)
            except InputError as e:
                last = e
        raise last if len(options) == 1 else InputError(f"{where}: invalid value {value!r}")
    if origin is Literal:
        if value not in args:
            raise InputError(f"{where}: must be one of {list(args)} (got {value!r})")
        return value
    if dataclasses.is_dataclass(hint):
        return parse_dataclass(hint, value, where, skip=skip)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"{where}: expected a list, got {type(value).__name__}")
        return tuple(_coerce(args[0], v, f"{where}[{i}]", skip) for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise InputError(f"{where}: expected a mapping, got {type(value).__name__}")
        return {str(k): _coerce(args[1], v, f"{where}.{k}", skip) if args else v for k, v in value.items()}
    if hint is typing.Any:
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {value!r}")
        return value
    raise InputError(f"{where}: unsupported value {value!r}")  # pragma: no cover
