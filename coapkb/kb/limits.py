"""The limits every query runs under: a row limit and an optional time
budget, and a robot's limits on the requests it serves (:class:`QueryLimits`)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from .. import clock
from ..model.results import Term
from ..typed_fields import require_at_least
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


@dataclass(frozen=True)
class QueryLimits:
    """Per-query limits a robot enforces so one request cannot starve the rest."""

    row_limit: int = 1000
    time_budget_s: float = 2.0
    max_request_bytes: int = 8192
    #: Max-Age of query answers of a read-only KB: they stay fresh.
    max_age_s: int = 300
    #: Max-Age of a writable KB's answers: how stale a cached answer may get
    #: (an observer is told of a change at once).
    live_max_age_s: int = 2
    #: Bytes of an update (SPARQL Update text or a compact patch) taken at most.
    max_update_bytes: int = 8192
    #: Max-Age on a 5.03 when the time budget ran out: when to try again.
    retry_after_s: int = 5
    #: Queries evaluated at once (including ones still running past their
    #: budget); beyond this the robot answers 5.03 at once.
    max_concurrent: int = 8
    #: A named query whose every run so far took less than this runs inline
    #: on the event loop: starting a thread costs more than the query (an
    #: index lookup on pyoxigraph takes tens of microseconds).  0 disables.
    inline_below_s: float = 0.002

    def __post_init__(self) -> None:
        require_at_least(self, ("row_limit", "max_request_bytes", "max_age_s", "live_max_age_s",
                                "max_update_bytes", "retry_after_s", "max_concurrent"))
        if not self.time_budget_s > 0:
            raise ValueError(f"time_budget_s must be positive, got {self.time_budget_s}")
        if not 0 <= self.inline_below_s < self.time_budget_s:
            raise ValueError(f"inline_below_s must be in [0, time_budget_s), got {self.inline_below_s}")
