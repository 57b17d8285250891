"""The cluster's claims: each object its cluster assigned, to whom and at
which task, so a repeat of it is skipped alike on every robot before the
pick is written, or even made (docs/knowledge.md, section 9)."""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Sequence

from ..transport.base import TransportError
from .decisions import Claim
from .robot_state import Decision

log = logging.getLogger(__name__)

#: Asks a teammate for the claims it hands a restarted robot.
AskClaims = Callable[[str], Awaitable[dict[str, Claim]]]


class ClusterClaims(OrderedDict[str, Claim]):
    """Object -> the cluster's assignment of it, from the decisions this
    robot applied, the latest last; at most ``kept`` (older picks are in
    the KB by then, in a writable team).  ``ask``: how a restarted robot
    asks a teammate for them (None: it takes none)."""

    def __init__(self, kept: int, handed: int, ask: AskClaims | None = None) -> None:
        super().__init__()
        self._kept = kept
        self._handed = handed
        self._ask = ask

    def record(self, decision: Decision) -> None:
        """The cluster assigned ``decision``'s object (if to anyone)."""
        if decision.assigned_to is None:
            return
        self[decision.object] = Claim(decision.assigned_to, decision.seq)
        self.move_to_end(decision.object)
        while len(self) > self._kept:
            self.popitem(last=False)

    def handed(self) -> dict[str, Claim]:
        """The claims a restarted teammate takes: the latest ``handed``."""
        return dict(list(self.items())[-self._handed:])

    async def take(self, seq: int, mates: Sequence[str]) -> None:
        """A restarted robot joining at task ``seq`` takes the claims of
        the tasks before from the first of ``mates`` to hand them over."""
        if self._ask is None:
            return
        for mate in mates:
            try:
                claims = await self._ask(mate)
            except TransportError as exc:
                log.warning("task %d: no claims from %s: %s", seq, mate, exc)
                continue
            # A teammate that saw this robot's plan may have decided this
            # task already: its claim of it is not one of the tasks before.
            earlier = sorted(((o, c) for o, c in claims.items() if c.seq < seq), key=lambda item: item[1].seq)
            self.clear()
            self.update(earlier)
            log.info("task %d: took %d claims from %s", seq, len(claims), mate)
            return
        log.warning("task %d: no teammate handed its claims over: a repeat of an earlier object may be decided "
                    "differently here", seq)
