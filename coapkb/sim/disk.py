"""The simulated machine's disk: what each sync covered, and a power cut
that loses the rest.

A robot process that is killed loses nothing it wrote: the operating
system holds its writes in the page cache and writes them out later.  A
power cut loses the page cache: a file keeps what its last sync covered.
The data folder syncs through :class:`~coapkb.kb.disk.Disk`; this disk
notes, per file (by inode: the journal writes a file under a temporary
name, syncs it, then renames it), its size at its last sync, and a power
cut truncates each file of a folder to it.  A directory's entries are
taken as synced (the journal syncs its folder after every rename); a
file never synced is left whole.
"""

from __future__ import annotations

import logging
import os
import shutil
import stat
import tempfile
from pathlib import Path

from ..kb.disk import Disk
from ..kb.durable import open_live
from ..kb.journal import DataDirError
from ..kb.live import LiveKB


class SimDisk(Disk):
    """The operating system's sync, noting how much of each file it covered."""

    def __init__(self) -> None:
        #: (device, inode) -> the file's size at its last sync.
        self._synced: dict[tuple[int, int], int] = {}

    def sync(self, fd: int, *, data_only: bool = False) -> None:
        super().sync(fd, data_only=data_only)
        info = os.fstat(fd)
        if stat.S_ISREG(info.st_mode):
            self._synced[(info.st_dev, info.st_ino)] = info.st_size

    def power_cut(self, folder: Path) -> list[tuple[str, int]]:
        """What a power cut leaves of ``folder``: each file cut back to its
        last sync.  The files cut, with the bytes each lost."""
        lost = []
        for file in sorted(folder.iterdir()):
            info = file.stat()
            kept = self._synced.get((info.st_dev, info.st_ino))
            if stat.S_ISREG(info.st_mode) and kept is not None and info.st_size > kept:
                os.truncate(file, kept)
                lost.append((file.name, info.st_size - kept))
        return lost


def restore_differences(robot_id: str, live: LiveKB, folder: Path) -> list[str]:
    """What a start on ``folder`` as it is now would restore that differs
    from what ``live`` held (its robot just died): one line per module that
    differs, and one if the write ids or the writer do.  Every change a
    replica takes is on disk before anyone hears of it, so a folder that
    gives back less (or more) than its robot held at its death lost an
    acknowledged write, or a received one the robot may have answered.
    Read from a copy, so that the robot's own restart meets the folder as
    its death left it; the restore's log lines are held back (a torn tail
    cut is the restart's to tell)."""
    with tempfile.TemporaryDirectory(prefix="coapkb-sim-restore-", dir=folder.parent) as scratch:
        copy = Path(scratch) / folder.name
        shutil.copytree(folder, copy)
        was = logging.root.manager.disable
        logging.disable(logging.CRITICAL)
        try:
            restored, keeper = open_live(live.base, robot_id, 0, copy, background=False, wall_ms=lambda: 0)
        except DataDirError as exc:
            return [f"{robot_id}'s data folder does not restore: {exc}"]
        finally:
            logging.disable(was)
        assert keeper is not None
        try:
            return _differences(robot_id, live, restored)
        finally:
            keeper.close()


def _differences(robot_id: str, held: LiveKB, restored: LiveKB) -> list[str]:
    found = []
    for module, replica in sorted(held.replicas.items()):
        back = restored.replicas.get(module)
        if back is None or not replica.equal_to(back):
            had, got = replica.state(), back.state() if back is not None else None
            said = "nothing" if got is None else (
                f"{len(got.entries)} written triples, context {got.context.vv}, {len(got.tombstones)} tombstones")
            found.append(f"{robot_id}'s data folder restores {module} with {said}; it held {len(had.entries)} "
                         f"written triples, context {had.context.vv}, {len(had.tombstones)} tombstones at its death")
    held_ids, back_ids = {wid for wid, _ in held.write_ids}, {wid for wid, _ in restored.write_ids}
    if held_ids != back_ids:
        found.append(f"{robot_id}'s data folder restores {len(back_ids)} write ids; it held {len(held_ids)} "
                     f"({len(held_ids - back_ids)} lost)")
    if restored.writer != held.writer:
        found.append(f"{robot_id}'s data folder writes on as {restored.writer}, not {held.writer}")
    return found
