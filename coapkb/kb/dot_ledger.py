"""The dots a replica knows of: its causal context (every write it has
received) and its tombstones (dots removed before their write came), and
the bound on how many of them may wait for the deltas before them.

Kept apart from the triples because it answers other questions: whether a
delta is new or a repeat, whether taking it would grow the waiting dots
past the bound (a flood of far dots must not fill a robot's memory), and
which sequence numbers a local write may not take.
"""

from __future__ import annotations

from collections.abc import Iterable

from ..model.deltas import CausalContext, Delta, Dot

__all__ = ["DotLedger"]


class DotLedger:
    """A replica's causal context and tombstones (see :mod:`.replica`)."""

    def __init__(self, waiting_max: int) -> None:
        self.context = CausalContext()
        self.tombstones: set[Dot] = set()
        #: Dots past a gap and tombstones, together, at most.
        self.waiting_max = waiting_max

    def waiting(self) -> int:
        """Dots waiting: past a gap, or removed before their write came."""
        return len(self.context.cloud) + len(self.tombstones)

    def admits(self, delta: Delta) -> bool:
        """Taking ``delta`` keeps the waiting dots within the bound (or
        adds none): else it is not taken and comes again, in order, at
        catch-up."""
        growth = sum(1 for d in delta.removed if d not in self.context and d not in self.tombstones)
        if delta.dot not in self.context and delta.dot.seq > self.context.vv.get(delta.dot.writer, 0) + 1:
            growth += len(delta.dots)
        return not growth or self.waiting() + growth <= self.waiting_max

    def knows(self, dot: Dot) -> bool:
        """``dot`` was received, or is known removed."""
        return dot in self.context or dot in self.tombstones

    def buried(self, dot: Dot) -> bool:
        """``dot`` was removed before its write came: it never shows."""
        return dot in self.tombstones

    def bury(self, dot: Dot) -> None:
        """A removed dot whose write has not come: a tombstone until it does."""
        if dot not in self.context:
            self.tombstones.add(dot)

    def receive(self, dots: Iterable[Dot]) -> None:
        """A write's dots arrived: into the context, their tombstones gone."""
        for dot in dots:
            self.context.add(dot)
            self.tombstones.discard(dot)

    def merge(self, context: CausalContext, tombstones: Iterable[Dot]) -> None:
        """A whole state's context and tombstones (a tombstone whose write
        either side received is dropped: the write is gone with it)."""
        self.context.merge(context)
        self.tombstones = {d for d in self.tombstones | set(tombstones) if d not in self.context}

    def highest(self, writer: str) -> int:
        """The highest sequence number of ``writer``'s known here: received,
        past a gap, or removed before its write came (0: none)."""
        return max((self.context.vv.get(writer, 0),
                    *(d.seq for d in self.context.cloud if d.writer == writer),
                    *(d.seq for d in self.tombstones if d.writer == writer)))

    def seqs_taken(self, writer: str, from_seq: int) -> set[int]:
        """The sequence numbers from ``from_seq`` on that are already dots
        of ``writer``'s here: past a gap, or tombstones."""
        taken = {d.seq for d in self.context.cloud if d.writer == writer and d.seq >= from_seq}
        taken.update(d.seq for d in self.tombstones if d.writer == writer and d.seq >= from_seq)
        return taken
