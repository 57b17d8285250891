"""The simulated disk: a power cut keeps what the last sync of each file
covered, whatever the file was called when it was synced."""

from __future__ import annotations

import os
from pathlib import Path

from coapkb.sim.disk import SimDisk


def test_a_power_cut_keeps_what_the_last_sync_covered(tmp_path: Path) -> None:
    disk = SimDisk()
    tmp = tmp_path / "journal.0.tmp"
    with open(tmp, "wb") as out:
        out.write(b"meta")
        out.flush()
        disk.sync(out.fileno())
    os.replace(tmp, tmp_path / "journal.0")  # synced under its temporary name
    with open(tmp_path / "journal.0", "ab") as out:
        out.write(b"+one")
        out.flush()
        disk.sync(out.fileno(), data_only=True)
        out.write(b"+two")  # written, never synced
    (tmp_path / "lock").write_bytes(b"")  # never synced: left whole
    assert disk.power_cut(tmp_path) == [("journal.0", 4)]
    assert (tmp_path / "journal.0").read_bytes() == b"meta+one"


def test_a_folder_synced_to_its_end_loses_nothing(tmp_path: Path) -> None:
    disk = SimDisk()
    with open(tmp_path / "journal.0", "wb") as out:
        out.write(b"meta+one")
        out.flush()
        disk.sync(out.fileno())
    assert disk.power_cut(tmp_path) == []
    assert (tmp_path / "journal.0").read_bytes() == b"meta+one"
