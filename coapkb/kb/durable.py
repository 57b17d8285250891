"""A writable knowledge base kept on disk: every change its replicas take
is in the data folder's journal (:mod:`.journal`) before anyone hears of
it, and a robot started again on the same folder comes back with every
write it had acknowledged or taken from a peer.

* **What goes to disk.**  A local write's deltas and its write id (with
  the version it made, not the answer), and the deltas and whole states a
  peer sent that were new here, one journal record each, fsynced before
  the write is answered, pushed, or a peer's sync is answered.  Nothing
  else: the view, the catch-up journal and the version are rebuilt from it.
* **The writer.**  A new folder takes the robot's writer of this start
  (``RobotN.<boot>``) and keeps it: a robot started again on its folder
  writes on as the same writer, above the highest dot under that name
  (its own writes are all on disk before they leave it, so none it sent
  can be above).  Without a folder each start is a new writer, as before.
* **Compaction.**  When the journal has grown past both a bound and the
  last snapshot, the next generation's journal is started and the state
  as it stands is written as a snapshot in a thread; the older files go
  once it is on disk.  Written so, a snapshot costs at most as much
  writing as the journal it replaces.
* **Failure.**  A journal that cannot be written (a full disk, an I/O
  error) stops the process at once: a change it could not keep may not
  reach anyone, and a half-written record may not be followed by others.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from .disk import Disk
from .journal import Change, DataDirError, Journal, Recovered
from .live import LiveKB
from .replica import Replica
from .store import KnowledgeBase
from .write_ids import Remembered, WriteId

__all__ = ["DataDirError", "Keeper", "open_live"]

log = logging.getLogger(__name__)

#: The journal's bound: past it (and past the last snapshot's size) it is compacted.
COMPACT_AFTER_BYTES = 1 << 20


def fail_stop(message: str) -> NoReturn:
    """Log ``message`` and end the process at once (no clean-up: nothing may
    leave it that the disk does not hold)."""
    log.critical("%s; stopping", message)
    logging.shutdown()
    os._exit(75)


@dataclass
class KeeperStats:
    """What one robot's data folder took, counted since it started."""

    #: Bytes of journal records written.
    records_bytes: int = 0
    #: Snapshots written, and the seconds they took together.
    snapshots: int = 0
    snapshot_s: float = 0.0


class Keeper:
    """Keeps one :class:`~.live.LiveKB`'s changes in a data folder (see the
    module docstring): installed as the LiveKB's ``keeper``."""

    def __init__(
        self,
        journal: Journal,
        live: LiveKB,
        *,
        compact_after_bytes: int = COMPACT_AFTER_BYTES,
        on_failure: Callable[[str], Any] = fail_stop,
        background: bool = True,
    ) -> None:
        self.journal = journal
        self.live = live
        self.compact_after_bytes = compact_after_bytes
        self.on_failure = on_failure
        #: Compact in a thread (False: at once, in the caller).
        self.background = background
        self._compacting: threading.Thread | None = None
        self.stats = KeeperStats()

    @property
    def path(self) -> Path:
        return self.journal.path

    def __call__(self, changes: Sequence[tuple[str, Change]], made: tuple[WriteId, Remembered] | None = None) -> None:
        """The LiveKB's hook: ``changes``, and the id of the write that
        ``made`` them, on disk before it returns."""
        try:
            self.stats.records_bytes += self.journal.append(changes, made)
        except OSError as exc:
            self.on_failure(f"cannot keep a change in {self.journal.path}: {exc}")
            raise
        if self.journal.journal_bytes > max(self.compact_after_bytes, self.journal.snapshot_bytes):
            self.compact()

    def compact(self) -> None:
        """Snapshot the whole state and drop the journal before it (at most
        one at a time: while one is being written, this does nothing)."""
        if self._compacting is not None and self._compacting.is_alive():
            return
        try:
            states = {name: replica.state() for name, replica in self.live.replicas.items()}
            write_ids = list(self.live.write_ids)
            generation = self.journal.rotate()
        except OSError as exc:
            self.on_failure(f"cannot start a new journal in {self.journal.path}: {exc}")
            raise
        if self.background:
            self._compacting = threading.Thread(
                target=self._snapshot, args=(generation, states, write_ids), name="coapkb-snapshot", daemon=True)
            self._compacting.start()
        else:
            self._snapshot(generation, states, write_ids)

    def _snapshot(self, generation: int, states: Mapping[str, Any],
                  write_ids: Sequence[tuple[WriteId, Remembered]]) -> None:
        started = time.perf_counter()
        try:
            size = self.journal.write_snapshot(generation, states, write_ids)
        except OSError as exc:
            # The journals it would replace stay: nothing is lost, the next
            # compaction tries again.
            log.warning("snapshot %d in %s not written: %s", generation, self.journal.path, exc)
            return
        took = time.perf_counter() - started
        self.stats.snapshots += 1
        self.stats.snapshot_s += took
        log.info("snapshot %d of %s written: %d bytes in %.2f s", generation, self.journal.path, size, took)

    def close(self) -> None:
        if self.live.keeper is self:
            self.live.keeper = None
        if self._compacting is not None:
            self._compacting.join()
        self.journal.close()


def restore(live: LiveKB, recovered: Recovered) -> int:
    """Join what a data folder held into ``live`` (its keeper not yet
    installed: nothing is written again); how many written triples it holds then."""
    skipped: set[str] = set()
    for module, state in recovered.states.items():
        if module in live.replicas:
            live.join(module, state)
        else:
            skipped.add(module)
    for module, change in recovered.changes:
        if module not in live.replicas:
            skipped.add(module)
        elif isinstance(change, Sequence):
            live.apply(module, change)
        else:
            live.join(module, change)
    if skipped:
        log.warning("the data folder holds writes of %s, which this robot no longer holds: left out",
                    ", ".join(sorted(skipped)))
    for wid, remembered in recovered.write_ids:
        live.write_ids.remember(wid, remembered)
    for replica in live.replicas.values():
        resume_writer(replica)
    return sum(len(r.entries) for r in live.replicas.values())


def resume_writer(replica: Replica) -> None:
    """The replica's own writes go on above its writes on disk: every one
    of them was kept before the next was made, so they run without a gap
    from 1 to the context's count for its writer, and no dot is used twice."""
    # The replica's own count, restored from its own context.
    replica.clock.resume(replica.context.vv.get(replica.writer, 0))


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off while a folder is read back.

    Reading makes hundreds of thousands of objects that live on (terms,
    triples, dots), and the collector counts them as they come: it scanned
    them over and over, a sixth of a restart with 100,000 written triples.
    None of them is cyclic garbage; the collector runs again after."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def open_live(
    base: KnowledgeBase,
    robot_id: str,
    boot: int,
    data_dir: Path | None,
    *,
    background: bool = True,
    disk: Disk | None = None,
    **live_options: Any,
) -> tuple[LiveKB, Keeper | None]:
    """The writable KB of robot ``robot_id`` started as ``boot``: in memory
    only (``data_dir`` None, a new writer ``robot_id.boot``), or kept in
    ``data_dir`` and restored from it; ``background``: compact in a thread
    (False in the simulator, which runs no thread); ``disk``: how the folder
    syncs (None: the operating system's).  Raises :class:`DataDirError`."""
    writer = f"{robot_id}.{boot}"
    if data_dir is None:
        return LiveKB(base, writer, **live_options), None
    started = time.perf_counter()
    with _collector_paused():
        journal, recovered = Journal.open(data_dir, robot_id, writer, disk)
        try:
            live = LiveKB(base, recovered.writer, **live_options)
            written = restore(live, recovered)
        except BaseException:
            journal.close()
            raise
    keeper = Keeper(journal, live, background=background)
    live.keeper = keeper
    if recovered.fresh:
        log.info("data folder %s: new, writing as %s", data_dir, recovered.writer)
    else:
        log.info("data folder %s: %d written triples restored in %.2f s, writing on as %s", data_dir, written,
                 time.perf_counter() - started, recovered.writer)
    return live, keeper
