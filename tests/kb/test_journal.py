"""The data folder: a writable KB's changes on disk (coapkb.kb.journal and
coapkb.kb.durable): appended and read back, a torn tail cut, corruption
refused, compaction into a snapshot, and a restarted KB that writes on
above its old dots."""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

import pytest
from rdflib import Literal, URIRef
from support import ONTOLOGIES

from coapkb.kb.durable import Keeper, open_live
from coapkb.kb.journal import JOURNAL_MAGIC, DataDirError, Journal, encode_record, read_records
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.store import KnowledgeBase
from coapkb.model.deltas import Dot

LOC = "http://www.tcs.org/2018/Location#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
WRITTEN = URIRef(LOC + "written")


@pytest.fixture(scope="module")
def base() -> KnowledgeBase:
    return KnowledgeBase.load([ONTOLOGIES / "Location.owl"])


def _open(base: KnowledgeBase, folder: Path, boot: int = 1) -> tuple[LiveKB, Keeper]:
    live, keeper = open_live(base, "Robot1", boot, folder, wall_ms=wall_ms)
    assert keeper is not None
    keeper.background = False
    keeper.on_failure = lambda message: None
    return live, keeper


def _insert(live: LiveKB, label: str) -> None:
    live.update(PREFIX + f'INSERT DATA {{ loc:{label} loc:written "{label}" }}')


def _labels(live: LiveKB) -> set[str]:
    rows = live.query(PREFIX + "SELECT ?v WHERE { ?s loc:written ?v }").rows  # type: ignore[union-attr]
    return {str(row[0]) for row in rows}


def _journal(folder: Path) -> Path:
    return max(folder.glob("journal.*"), key=lambda p: int(p.suffix[1:]))


def test_writes_come_back_with_the_writer_and_its_count(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path, boot=7)
    for i in range(5):
        _insert(live, f"w{i}")
    live.update(PREFIX + 'DELETE DATA { loc:w2 loc:written "w2" }')
    version, writer = live.etag, live.writer
    keeper.close()

    again, keeper = _open(base, tmp_path, boot=8)
    assert again.writer == writer == "Robot1.7"  # the folder's writer, not this start's
    assert _labels(again) == {"w0", "w1", "w3", "w4"}
    assert again.etag == version
    top = again.replicas["Location"].context.vv[writer]
    written = again.update(PREFIX + 'INSERT DATA { loc:w5 loc:written "w5" }')
    assert written.deltas["Location"].dot == Dot(writer, top + 1)  # never a dot used before
    keeper.close()


def test_a_folder_without_data_dir_is_memory_only(base) -> None:
    live, keeper = open_live(base, "Robot1", 3, None, wall_ms=wall_ms)
    assert keeper is None and live.writer == "Robot1.3" and live.keeper is None


def test_peers_deltas_and_states_are_kept(base, tmp_path) -> None:
    peer = LiveKB(base, "Robot2.1", wall_ms=wall_ms)
    _insert(peer, "a")
    _insert(peer, "b")
    live, keeper = _open(base, tmp_path)
    deltas = list(peer.replicas["Location"].journal.values())
    live.apply("Location", deltas)
    live.apply("Location", deltas)  # again: nothing new, nothing appended
    size = _journal(tmp_path).stat().st_size
    other = LiveKB(base, "Robot3.1", wall_ms=wall_ms)
    _insert(other, "c")
    live.join("Location", other.replicas["Location"].state())
    assert _journal(tmp_path).stat().st_size > size
    keeper.close()
    again, keeper = _open(base, tmp_path)
    assert _labels(again) == {"a", "b", "c"}
    assert again.replicas["Location"].equal_to(live.replicas["Location"])
    keeper.close()


def test_a_torn_tail_is_cut_with_one_line(base, tmp_path, caplog) -> None:
    live, keeper = _open(base, tmp_path)
    for i in range(3):
        _insert(live, f"w{i}")
    keeper.close()
    journal = _journal(tmp_path)
    whole = journal.stat().st_size
    with open(journal, "ab") as out:
        out.write(encode_record(b"C" + b"x" * 100)[:60])  # a record cut short
    with caplog.at_level(logging.WARNING, "coapkb.kb.journal"):
        again, keeper = _open(base, tmp_path)
    assert [r.message for r in caplog.records if "torn tail" in r.message] == [
        f"{journal}: cut a torn tail at byte {whole} (a record cut short (48 of 101 bytes), 60 bytes)"
    ]
    assert journal.stat().st_size == whole
    assert _labels(again) == {"w0", "w1", "w2"}
    _insert(again, "w3")  # appended after the cut: read back whole
    keeper.close()
    third, keeper = _open(base, tmp_path)
    assert _labels(third) == {"w0", "w1", "w2", "w3"}
    keeper.close()


@pytest.mark.parametrize("tail", [b"\0" * 4096, b"\0\0\0", "last-record-garbled"])
def test_other_torn_tails(base, tmp_path, tail) -> None:
    live, keeper = _open(base, tmp_path)
    _insert(live, "w0")
    _insert(live, "w1")
    keeper.close()
    journal = _journal(tmp_path)
    data = bytearray(journal.read_bytes())
    if tail == "last-record-garbled":
        data[-3] ^= 0xFF  # the last record's payload: never acknowledged
        expected = {"w0"}
    else:
        data += tail
        expected = {"w0", "w1"}
    journal.write_bytes(bytes(data))
    again, keeper = _open(base, tmp_path)
    assert _labels(again) == expected
    keeper.close()


def test_corruption_in_the_middle_refuses_to_start(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path)
    for i in range(3):
        _insert(live, f"w{i}")
    keeper.close()
    journal = _journal(tmp_path)
    data = bytearray(journal.read_bytes())
    scan = read_records(bytes(data), "j", JOURNAL_MAGIC, torn_ok=False)
    second = len(JOURNAL_MAGIC) + sum(12 + len(r) for r in scan.records[:2])  # meta, w0: w1 next
    data[second + 12 + 5] ^= 0x01
    journal.write_bytes(bytes(data))
    with pytest.raises(DataDirError, match=rf"^{journal}: corrupt at byte {second}: a record fails its checksum "
                                           "and records follow it$"):
        _open(base, tmp_path)
    data[second + 12 + 5] ^= 0x01
    data[second + 1] ^= 0x40  # the length: the header's own checksum tells
    journal.write_bytes(bytes(data))
    with pytest.raises(DataDirError, match=rf"corrupt at byte {second}: a record header fails its checksum"):
        _open(base, tmp_path)


def test_a_bad_header_refuses_to_start(base, tmp_path) -> None:
    _, keeper = _open(base, tmp_path)
    keeper.close()
    journal = _journal(tmp_path)
    journal.write_bytes(b"not a journal at all")
    with pytest.raises(DataDirError, match=r"journal.0: not a coapkb journal \(bad header"):
        _open(base, tmp_path)


def test_another_robots_folder_or_one_in_use(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path)
    with pytest.raises(DataDirError, match="is in use by another process"):
        Journal.open(tmp_path, "Robot1", "Robot1.9")
    keeper.close()
    with pytest.raises(DataDirError, match=r"journal.0 belongs to Robot1, not Robot2"):
        Journal.open(tmp_path, "Robot2", "Robot2.9")


def test_compaction_writes_a_snapshot_and_drops_the_old_journal(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path)
    keeper.compact_after_bytes = 2000
    for i in range(40):
        _insert(live, f"w{i}")
        if i % 3 == 0:
            live.update(PREFIX + f'DELETE DATA {{ loc:w{i} loc:written "w{i}" }}')
    assert keeper.stats.snapshots >= 2
    names = sorted(p.name for p in tmp_path.iterdir())
    generation = keeper.journal.generation
    assert names == [".gitignore", "journal." + str(generation), "lock", "snapshot." + str(generation)]
    expected = _labels(live)
    state = live.replicas["Location"]
    keeper.close()
    again, keeper = _open(base, tmp_path)
    assert _labels(again) == expected
    assert again.replicas["Location"].equal_to(state)
    keeper.close()


def test_a_compaction_cut_short_leaves_what_it_would_replace(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path)
    for i in range(4):
        _insert(live, f"w{i}")
    # The next journal was started, and the process died writing the snapshot.
    keeper.journal.rotate()
    _insert(live, "w4")
    (tmp_path / f"snapshot.{keeper.journal.generation}.tmp").write_bytes(b"coapkbS\x01half")
    keeper.close()
    again, keeper = _open(base, tmp_path)
    assert _labels(again) == {f"w{i}" for i in range(5)}
    assert not list(tmp_path.glob("*.tmp"))
    keeper.compact()
    keeper.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".gitignore", "journal.2", "lock", "snapshot.2"]
    third, keeper = _open(base, tmp_path)
    assert _labels(third) == {f"w{i}" for i in range(5)}
    keeper.close()


def test_a_snapshot_not_whole_or_a_generation_missing_refuses(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path)
    _insert(live, "w0")
    keeper.compact()
    keeper.close()
    snapshot = tmp_path / "snapshot.1"
    data = snapshot.read_bytes()
    snapshot.write_bytes(data[:-5])
    with pytest.raises(DataDirError, match=rf"^{snapshot}: corrupt at byte \d+: a record (header )?cut short"):
        _open(base, tmp_path)
    snapshot.write_bytes(data)
    (tmp_path / "journal.1").unlink()
    with pytest.raises(DataDirError, match=r"journal.1 is missing \(it holds snapshot.1\)"):
        _open(base, tmp_path)


def test_a_journal_that_cannot_be_written_stops_the_process(base, tmp_path, monkeypatch) -> None:
    live, keeper = _open(base, tmp_path)
    failures: list[str] = []
    keeper.on_failure = failures.append

    def full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fdatasync", full)
    with pytest.raises(OSError):
        _insert(live, "w0")
    assert failures == [f"cannot keep a change in {tmp_path}: [Errno 28] No space left on device"]
    monkeypatch.undo()
    keeper.close()


def test_record_framing() -> None:
    record = encode_record(b"C\x01\x02")
    length, crc, head = struct.unpack(">III", record[:12])
    assert length == 3 and record[12:] == b"C\x01\x02"
    scan = read_records(JOURNAL_MAGIC + record * 3, "j", JOURNAL_MAGIC, torn_ok=False)
    assert scan.records == [b"C\x01\x02"] * 3 and scan.torn is None


def test_many_written_triples_go_in_several_snapshot_records(base, tmp_path) -> None:
    live, keeper = _open(base, tmp_path)
    for batch in range(12):
        triples = " ".join(f'loc:t{batch}_{i} loc:written "{batch}_{i}" .' for i in range(1000))
        live.update(PREFIX + f"INSERT DATA {{ {triples} }}")
    keeper.compact()
    keeper.close()
    again, keeper = _open(base, tmp_path)
    assert len(again.replicas["Location"].entries) == 12_000
    assert again.replicas["Location"].equal_to(live.replicas["Location"])
    keeper.close()
    assert Literal("11_999") in {o for _, _, o in again.replicas["Location"].entries}


def test_a_snapshot_keeps_concurrent_adds_shadowed_values_and_tombstones(base, tmp_path) -> None:
    move = PREFIX + ("DELETE { loc:Robot1 loc:Robot_aisle_no ?a } INSERT { loc:Robot1 loc:Robot_aisle_no %d } "
                     "WHERE { loc:Robot1 loc:Robot_aisle_no ?a }")
    aisle = PREFIX + "SELECT ?a WHERE { loc:Robot1 loc:Robot_aisle_no ?a }"

    def deltas(kb: LiveKB) -> list:
        return list(kb.replicas["Location"].journal.values())

    peer, other = LiveKB(base, "Robot2.1", wall_ms=wall_ms), LiveKB(base, "Robot3.1", wall_ms=wall_ms)
    _insert(peer, "same")
    _insert(other, "same")  # one triple, two dots
    peer.update(move % 4)
    other.update(move % 6)  # concurrent: one value shows, the other is shadowed
    ghost, remover = LiveKB(base, "Robot4.1", wall_ms=wall_ms), LiveKB(base, "Robot5.1", wall_ms=wall_ms)
    _insert(ghost, "ghost")
    remover.apply("Location", deltas(ghost))
    removal = remover.update(PREFIX + 'DELETE DATA { loc:ghost loc:written "ghost" }').deltas["Location"]

    live, keeper = _open(base, tmp_path)
    live.apply("Location", deltas(peer) + deltas(other))
    live.apply("Location", [removal])  # before the write it removes: a tombstone
    _insert(live, "mine")
    state = live.replicas["Location"]
    assert state.tombstones and len(state.entries) > len({t for t in state.entries if len(state.entries[t]) == 1})
    assert len(live.query(aisle).rows) == 1  # type: ignore[union-attr]
    keeper.compact()
    keeper.close()
    again, keeper = _open(base, tmp_path)
    assert again.replicas["Location"].equal_to(state)
    assert again.query(aisle).rows == live.query(aisle).rows  # type: ignore[union-attr]
    assert _labels(again) == _labels(live) == {"same", "mine"}
    again.apply("Location", deltas(ghost))
    live.apply("Location", deltas(ghost))
    assert again.replicas["Location"].equal_to(live.replicas["Location"]) and "ghost" not in _labels(again)
    keeper.close()
