"""The deltas a replica keeps for catch-up, in the order they came.

Catch-up sends a peer the deltas its context lacks, so what it costs grows
with what the peer missed, not with the module.  The journal is bounded
(in triples and dots, :attr:`Delta.size`): past the bound the oldest go,
and the deltas every peer has received go at compaction; a peer that needs
one no longer kept gets the whole written state instead.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable

from ..model.deltas import CausalContext, Delta, Dot

__all__ = ["DeltaJournal"]


class DeltaJournal:
    """Deltas by their first dot, oldest first, at most ``size_max`` in size."""

    def __init__(self, size_max: int) -> None:
        self.deltas: OrderedDict[Dot, Delta] = OrderedDict()
        #: The sum of the kept deltas' sizes.
        self.size = 0
        self.size_max = size_max

    def __contains__(self, dot: Dot) -> bool:
        return dot in self.deltas

    def add(self, delta: Delta) -> None:
        """Keep ``delta`` (once), and forget the oldest past the bound (never
        the newest, even alone past it)."""
        if delta.dot in self.deltas:
            return
        self.deltas[delta.dot] = delta
        self.size += delta.size
        while self.size > self.size_max and len(self.deltas) > 1:
            self._forget(next(iter(self.deltas)))

    def compact(self, peers: Iterable[CausalContext]) -> int:
        """Forget the deltas every peer in ``peers`` has received; how many went."""
        contexts = list(peers)
        gone = [dot for dot in self.deltas if all(dot in c for c in contexts)]
        for dot in gone:
            self._forget(dot)
        return len(gone)

    def missing_from(self, context: CausalContext, peer: CausalContext) -> list[Delta] | None:
        """The deltas of ``context`` that ``peer`` lacks, in the order they
        came; None when one of them is no longer kept."""
        journaled = sum(len(d.dots) for d in self.deltas.values())
        # Counted before they are listed: a context claiming a huge count
        # must not make this enumerate it.
        if context.count_missing_from(peer) > journaled:
            return None
        missing = set(context.missing_from(peer))
        wanted = [d for d in self.deltas.values() if any(dot in missing for dot in d.dots)]
        if sum(1 for d in wanted for dot in d.dots if dot in missing) < len(missing):
            return None
        return wanted

    def _forget(self, dot: Dot) -> None:
        delta = self.deltas.pop(dot)
        self.size -= delta.size
