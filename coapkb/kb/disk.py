"""How a data folder makes what it wrote durable: the operating system's
fsync, behind a seam (:attr:`coapkb.host.Host.disk`).  The simulator's
disk notes what each sync covered, and its power cut loses the rest, as a
machine's page cache is lost (:mod:`coapkb.sim.disk`).  Kept apart from
the journal's format so that a host names it without loading the journal."""

from __future__ import annotations

import os

__all__ = ["Disk"]


class Disk:
    """The operating system's fsync."""

    def sync(self, fd: int, *, data_only: bool = False) -> None:
        """What was written to ``fd`` on the disk (``data_only``: its data,
        not its metadata, as ``fdatasync``) when this returns."""
        (os.fdatasync if data_only else os.fsync)(fd)
