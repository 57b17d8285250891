"""What names a replica's own writes: the sequence numbers of their dots
and their hybrid-logical-clock stamps.

A dot under this writer's name that it did not make (a forged or replayed
delta, or one from a life it forgot) would otherwise take a real write's
place, so the next numbers step over every dot of its name already seen;
the stamps stay ahead of every stamp seen, so a later write's single value
wins over the one it replaces wherever the two meet.
"""

from __future__ import annotations

from ..model.deltas import BASE_STAMP, Dot, Stamp
from .dot_ledger import DotLedger

__all__ = ["WriterClock"]


class WriterClock:
    """One writer's count of dots and its hybrid logical clock."""

    def __init__(self, writer: str) -> None:
        self.writer = writer
        #: The last sequence number a local write took.
        self.seq = 0
        self._last = BASE_STAMP

    def stamp(self, now_ms: int) -> Stamp:
        """The next hybrid-logical-clock stamp of a local write."""
        last = self._last
        stamp = Stamp(now_ms, 0, self.writer) if now_ms > last.ms else Stamp(last.ms, last.counter + 1, self.writer)
        self._last = stamp
        return stamp

    def observe(self, stamp: Stamp) -> None:
        """A stamp seen in a peer's write: the next local one comes after it."""
        if (stamp.ms, stamp.counter) > (self._last.ms, self._last.counter):
            self._last = Stamp(stamp.ms, stamp.counter, self.writer)

    def first_seq(self, count: int, ledger: DotLedger) -> int:
        """The first of ``count`` sequence numbers for the next local write,
        none of them a dot under this writer's name already seen: past the
        context's version vector, and clear of its dots past a gap and of its
        tombstones.  A dot under this name that it did not make (a forged or
        replayed delta, or one from a life it forgot) would otherwise take a
        real write's place: the write would be dropped as a duplicate (or
        hidden by the tombstone) here and at every holder.  A far dot past a
        gap is stepped over, not jumped to: the writes fill the gap below it,
        so the others' contexts do not keep a gap that never closes."""
        seq = max(self.seq, ledger.context.vv.get(self.writer, 0)) + 1
        taken = ledger.seqs_taken(self.writer, seq)
        while taken:
            clash = [s for s in range(seq, seq + count) if s in taken]
            if not clash:
                break
            seq = clash[-1] + 1
        return seq

    def took(self, last: Dot) -> None:
        """A local write took the dots up to ``last``."""
        self.seq = last.seq

    def continue_as(self, writer: str) -> None:
        """Write from now on as ``writer``, the name of this robot's lives
        (:mod:`.life_fence`): its numbers go on above the dots of it seen;
        the stamps stay ahead of every stamp seen."""
        self.writer = writer
        self.seq = 0
        self._last = Stamp(self._last.ms, self._last.counter, writer)

    def resume(self, top: int) -> None:
        """The writer's dots up to ``top`` are already taken (read back from
        the data folder): the next write goes on above them."""
        self.seq = max(self.seq, top)
