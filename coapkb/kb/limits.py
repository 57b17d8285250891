"""The limits every query runs under: a row limit and an optional time budget."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from .. import clock
from ..model.results import Term
from .errors import QueryTimeout


class Deadline:
    """Checks a monotonic deadline between results."""

    __slots__ = ("budget", "end")

    def __init__(self, budget_s: float | None) -> None:
        self.budget = budget_s
        self.end = None if budget_s is None else clock.monotonic() + budget_s

    def check(self, rows: int) -> None:
        if self.end is not None and clock.monotonic() > self.end:
            raise QueryTimeout(self.budget or 0.0, rows)


def take(items: Iterable[Term | tuple[Term | None, ...]], limit: int, deadline: Deadline) -> tuple[list[Any], bool]:
    """Up to ``limit`` items, and whether more existed; checks the deadline
    after every item (one ``next()`` on a lazy result = evaluating up to the
    next solution)."""
    out: list[Any] = []
    for item in items:
        if len(out) == limit:
            return out, True
        out.append(item)
        deadline.check(len(out))
    return out, False

