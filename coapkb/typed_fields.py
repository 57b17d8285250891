"""A table of settings (as read from TOML) checked against a dataclass's
fields: every key a field, every value of its default's type (an int
stands for a float; a field whose default is None takes what its
annotation names beside None).  One check for a robot's configuration
sections and for a transport's tunables; pure, below every package that
uses it."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable, Collection, Iterable, Mapping
from typing import Any


def typed_fields(cls: type, table: Mapping[str, Any], settable: Collection[str] | None = None,
                 convert: Mapping[str, Callable[[Any], Any]] | None = None) -> dict[str, Any]:
    """``table``'s values for ``cls``'s fields (only those in ``settable``,
    when given); a field in ``convert`` is that function's result instead
    (for a type a table cannot hold: an endpoint, a path).  Raises
    ValueError naming the field: ``NAME: unknown field (known: ...)``,
    ``NAME: expected TYPE, got VALUE``, or ``NAME: `` and what ``convert``
    raised."""
    defaults = {f.name: f.default for f in dataclasses.fields(cls) if settable is None or f.name in settable}
    unknown = sorted(set(table) - set(defaults))
    if unknown:
        raise ValueError(f"{unknown[0]}: unknown field (known: {', '.join(sorted(defaults))})")
    values: dict[str, Any] = {}
    for name, value in table.items():
        if convert is not None and name in convert:
            try:
                values[name] = convert[name](value)
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
            continue
        kind = type(defaults[name]) if defaults[name] is not None else _optional_of(cls, name)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not kind:
            raise ValueError(f"{name}: expected {kind.__name__}, got {value!r}")
        values[name] = value
    return values


def _optional_of(cls: type, name: str) -> type:
    """``X`` for a field annotated ``X | None``."""
    hint = typing.get_type_hints(cls)[name]
    kinds = [k for k in typing.get_args(hint) if k is not type(None)]
    if not isinstance(hint, types.UnionType) or len(kinds) != 1 or not isinstance(kinds[0], type):
        raise TypeError(f"{cls.__name__}.{name}: a None default needs an `X | None` annotation")
    return kinds[0]


def require_at_least(record: object, names: Iterable[str], least: int = 1) -> None:
    """A ``ValueError`` naming the first of ``record``'s fields ``names``
    below ``least`` (a bound of a dataclass's ``__post_init__``)."""
    for name in names:
        if getattr(record, name) < least:
            raise ValueError(f"{name} must be at least {least}, got {getattr(record, name)}")
