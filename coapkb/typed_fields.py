"""A table of settings (as read from TOML) checked against a dataclass's
defaults: every key a field, every value of its default's type (an int
stands for a float).  One check for a robot's configuration sections and
for a transport's tunables; pure, below every package that uses it."""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Mapping
from typing import Any


def typed_fields(cls: type, table: Mapping[str, Any], settable: Collection[str] | None = None) -> dict[str, Any]:
    """``table``'s values for ``cls``'s fields (only those in ``settable``,
    when given).  Raises ValueError naming the field: ``NAME: unknown field
    (known: ...)`` or ``NAME: expected TYPE, got VALUE``."""
    defaults = {f.name: f.default for f in dataclasses.fields(cls) if settable is None or f.name in settable}
    unknown = sorted(set(table) - set(defaults))
    if unknown:
        raise ValueError(f"{unknown[0]}: unknown field (known: {', '.join(sorted(defaults))})")
    values: dict[str, Any] = {}
    for name, value in table.items():
        default = defaults[name]
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not type(default):
            raise ValueError(f"{name}: expected {type(default).__name__}, got {value!r}")
        values[name] = value
    return values
