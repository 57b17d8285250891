"""The simulated disk: a power cut keeps what the last sync of each file
covered, whatever the file was called when it was synced; and a dead
robot's folder is found when it would restore less than the robot held."""

from __future__ import annotations

import os
from pathlib import Path

from support import ONTOLOGIES

from coapkb.kb.durable import Keeper, open_live
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.store import KnowledgeBase
from coapkb.sim.disk import SimDisk, restore_differences


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


LOC = "http://www.tcs.org/2018/Location#"


def _folder_with_writes(tmp_path: Path) -> tuple[LiveKB, Keeper, Path]:
    folder = tmp_path / "Robot1"
    live, keeper = open_live(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "Robot1", 1, folder,
                             background=False, wall_ms=wall_ms)
    assert keeper is not None
    for label in ("w0", "w1"):
        live.update(f'PREFIX loc: <{LOC}> INSERT DATA {{ loc:{label} loc:written "{label}" }}')
    return live, keeper, folder


def test_a_folder_restores_what_its_robot_held(tmp_path: Path) -> None:
    live, keeper, folder = _folder_with_writes(tmp_path)
    keeper.journal.close()
    assert restore_differences("Robot1", live, folder) == []
    assert sorted(p.name for p in folder.iterdir()) == [".gitignore", "journal.0", "lock"]  # read from a copy


def test_a_folder_that_lost_its_last_record_is_found(tmp_path: Path) -> None:
    live, keeper, folder = _folder_with_writes(tmp_path)
    keeper.journal.close()
    journal = folder / "journal.0"
    data = journal.read_bytes()
    journal.write_bytes(data[:-1])  # the last record torn: its write is gone
    found = restore_differences("Robot1", live, folder)
    assert found and found[0].startswith("Robot1's data folder restores Location with 1 written triples")
