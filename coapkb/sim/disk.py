"""The simulated machine's disk: what each sync covered, and a power cut
that loses the rest.

A robot process that is killed loses nothing it wrote: the operating
system holds its writes in the page cache and writes them out later.  A
power cut loses the page cache: a file keeps what its last sync covered.
The data folder syncs through :class:`~coapkb.kb.journal.Disk`; this disk
notes, per file (by inode: the journal writes a file under a temporary
name, syncs it, then renames it), its size at its last sync, and a power
cut truncates each file of a folder to it.  A directory's entries are
taken as synced (the journal syncs its folder after every rename); a
file never synced is left whole.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..kb.journal import Disk


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
