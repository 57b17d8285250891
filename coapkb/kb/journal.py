"""A robot's data folder: its modules' written state on disk, as a journal
of the changes its replicas took and a snapshot of their whole state.

This module is the disk format and nothing else: what is written when is
:mod:`.durable`'s business, and the records' contents are the replication
messages of :mod:`coapkb.wire.sync` (pure codecs, no I/O).  The format
(docs/knowledge.md, "On disk"):

::

    DIR/lock            held (flock) while a process uses the folder
    DIR/.gitignore      "*": a folder made inside a repository stays out of it
    DIR/journal.G       journal of generation G: magic "coapkbJ\\x01", then records
    DIR/snapshot.G      the whole state before journal G: magic "coapkbS\\x01", then records
    record  = length: u32 | crc32(payload): u32 | crc32(the 8 bytes before): u32 | payload
    payload = kind: 1 byte, then
              "M" meta      CBOR {"format": 1, "robot": tstr, "writer": tstr, "generation": uint}
              "C" change    a sync message: one delta, or a whole state a peer sent
              "S" head      a sync message: a module's context, removed files' triples, tombstones
              "E" entries   a sync message: a module's written triples (about 10,000) as
                            deltas, one per run of a writer's consecutive dots with one stamp
              "W" write id  CBOR [peer, writer, write, digest, version, removed, added, ?made-by]:
                            a client's write's id (:mod:`.write_ids`), with the write
                            in a journal, the ids remembered then in a snapshot;
                            ``made-by``: the holder that made it and pushed it here
              "Z" end       CBOR uint: the snapshot's records before it, meta excluded

Format 2 added the write-id record; format 1 (without it) is read alike.
Every file starts with its magic and a meta record.  A journal's records
are appended and fsynced before the change they hold is answered; a
snapshot is written to ``snapshot.G.tmp``, fsynced, and renamed.

Recovery: the highest snapshot, then every journal of that generation or
later, in order.  A journal's torn tail (a record cut short, or nothing
but zeros after the last good record) is cut off; a bad checksum with
good data after it, a bad header, a snapshot that is not whole, or a
generation missing raise :class:`DataDirError`.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import struct
import zlib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cbor2

from ..errors import CoapkbError
from ..model.deltas import CausalContext, Delta, Dot, Stamp, WrittenState
from ..model.results import Triple
from ..wire.codec import CodecError
from ..wire.sync import SyncMessage, decode_sync, encode_sync
from .disk import Disk
from .write_ids import Remembered, WriteId

__all__ = ["Change", "DataDirError", "Journal", "Recovered", "encode_record", "read_records"]

log = logging.getLogger(__name__)

FORMAT = 2
#: The formats this coapkb reads: 1 has no write-id records.
READABLE = (1, 2)
JOURNAL_MAGIC = b"coapkbJ\x01"
SNAPSHOT_MAGIC = b"coapkbS\x01"
HEAD = struct.Struct(">III")
#: A record longer than this is garbage (a whole state of 100,000 triples is about 5 MB).
MAX_RECORD = 256 << 20
#: Written triples per snapshot record (about): well inside what the sync decoder takes.
ENTRIES_PER_RECORD = 10_000

META, CHANGE, HEAD_KIND, ENTRIES, WRITE_ID, END = b"M", b"C", b"S", b"E", b"W", b"Z"

#: What a replica took: deltas (one per journal record) or a peer's whole state.
Change = Sequence[Delta] | WrittenState

_NAME = re.compile(r"^(journal|snapshot)\.(\d{1,12})$")


class DataDirError(CoapkbError):
    """The data folder cannot be used: a corrupt file, another robot's
    folder, one in use by another process.  The message names the file."""


@dataclass
class Recovered:
    """What a data folder held when it was opened."""

    writer: str
    #: Module -> its state from the snapshot (joined first).
    states: dict[str, WrittenState] = field(default_factory=dict)
    #: (module, change) in the order they were taken, after the snapshot.
    changes: list[tuple[str, Change]] = field(default_factory=list)
    #: The local writes' ids, in the order they were made (the snapshot's first).
    write_ids: list[tuple[WriteId, Remembered]] = field(default_factory=list)
    #: Bytes cut off a torn tail (0: none).
    cut: int = 0
    #: Whether the folder was new.
    fresh: bool = False


# ---------------------------------------------------------------- records


def encode_record(payload: bytes) -> bytes:
    length = struct.pack(">I", len(payload))
    crc = struct.pack(">I", zlib.crc32(payload))
    return length + crc + struct.pack(">I", zlib.crc32(length + crc)) + payload


@dataclass(frozen=True)
class _Scan:
    records: list[bytes]
    #: Where the good records end.
    end: int
    #: Why the rest is a torn tail (None: the file ends with its last record).
    torn: str | None


def _zeros(data: bytes | memoryview) -> bool:
    return not any(data)


def read_records(data: bytes, name: str, magic: bytes, *, torn_ok: bool) -> _Scan:
    """The records of a file's bytes; raises :class:`DataDirError` naming
    ``name`` where it is corrupt (and, unless ``torn_ok``, where it ends
    short)."""
    if len(data) < len(magic) or data[: len(magic)] != magic:
        raise DataDirError(f"{name}: not a coapkb {'journal' if magic == JOURNAL_MAGIC else 'snapshot'} "
                           f"(bad header {bytes(data[:len(magic)])!r})")
    view = memoryview(data)
    at = len(magic)
    records: list[bytes] = []
    torn: str | None = None
    while at < len(data):
        rest = view[at:]
        if _zeros(rest):
            torn = f"{len(rest)} zero bytes"
        elif len(rest) < HEAD.size:
            torn = f"a record header cut short ({len(rest)} of {HEAD.size} bytes)"
        else:
            length, crc, head_crc = HEAD.unpack_from(rest)
            if zlib.crc32(rest[:8]) != head_crc or length > MAX_RECORD:
                raise DataDirError(f"{name}: corrupt at byte {at}: a record header fails its checksum")
            end = at + HEAD.size + length
            if end > len(data):
                torn = f"a record cut short ({len(data) - at - HEAD.size} of {length} bytes)"
            else:
                payload = bytes(view[at + HEAD.size : end])
                if zlib.crc32(payload) != crc:
                    if not _zeros(view[end:]):
                        raise DataDirError(f"{name}: corrupt at byte {at}: a record fails its checksum "
                                           "and records follow it")
                    torn = "a last record that fails its checksum"
                else:
                    records.append(payload)
                    at = end
                    continue
        break
    if torn is not None and not torn_ok:
        raise DataDirError(f"{name}: corrupt at byte {at}: {torn}")
    return _Scan(records, at, torn)


def _meta(robot: str, writer: str, generation: int) -> bytes:
    return META + cbor2.dumps({"format": FORMAT, "robot": robot, "writer": writer, "generation": generation})


def _read_meta(payload: bytes, name: str) -> tuple[str, str, int]:
    if payload[:1] != META:
        raise DataDirError(f"{name}: corrupt: its first record is not its meta record")
    try:
        meta = cbor2.loads(payload[1:])
    except (cbor2.CBORDecodeError, ValueError, TypeError, EOFError) as exc:
        raise DataDirError(f"{name}: corrupt meta record: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") not in READABLE:
        raise DataDirError(f"{name}: format {meta.get('format') if isinstance(meta, dict) else '?'}, "
                           f"this coapkb reads format {' and '.join(map(str, READABLE))}")
    robot, writer, generation = meta.get("robot"), meta.get("writer"), meta.get("generation")
    if not isinstance(robot, str) or not isinstance(writer, str) or not writer or not isinstance(generation, int):
        raise DataDirError(f"{name}: corrupt meta record {meta!r}")
    return robot, writer, generation


def _change_payload(module: str, change: Delta | WrittenState) -> bytes:
    changes: Sequence[Delta] | WrittenState = change if isinstance(change, WrittenState) else [change]
    return CHANGE + encode_sync(SyncMessage(module, CausalContext(), changes))


def _write_id_payload(wid: WriteId, remembered: Remembered) -> bytes:
    fields: list[object] = [wid.peer, wid.writer, wid.write, remembered.digest, remembered.version,
                            remembered.removed, remembered.added]
    if remembered.made_by is not None:
        fields.append(remembered.made_by)
    return WRITE_ID + cbor2.dumps(fields)


def _decode_write_id(payload: bytes, name: str) -> tuple[WriteId, Remembered]:
    try:
        fields = cbor2.loads(payload[1:])
        peer, writer, write, digest, version, removed, added = fields[:7]
        made_by = fields[7] if len(fields) == 8 else None
    except (cbor2.CBORDecodeError, ValueError, TypeError, EOFError, KeyError) as exc:
        raise DataDirError(f"{name}: corrupt write-id record: {exc}") from None
    if not (isinstance(fields, list) and len(fields) in (7, 8)
            and isinstance(peer, (str, type(None))) and isinstance(writer, str) and isinstance(write, str)
            and isinstance(digest, bytes) and isinstance(version, bytes)
            and isinstance(removed, int) and isinstance(added, int) and isinstance(made_by, (str, type(None)))):
        raise DataDirError(f"{name}: corrupt write-id record")
    return WriteId(peer, writer, write), Remembered(digest, version, removed, added, made_by=made_by)


def _decode(payload: bytes, name: str) -> SyncMessage:
    try:
        message = decode_sync(payload[1:])
    except CodecError as exc:
        raise DataDirError(f"{name}: corrupt record: {exc}") from None
    if message.changes is None:
        raise DataDirError(f"{name}: corrupt record: it holds no change")
    return message


def _runs(entries: Mapping[Triple, Mapping[Dot, Stamp]]) -> list[Delta]:
    """Written triples as the writes that added them: runs of one writer's
    consecutive dots with one stamp, each a delta adding its triples (as
    the write did, or its part still live).  Far smaller to encode and to
    read back than a dot list for each triple."""
    tagged = sorted((dot, stamp, triple) for triple, dots in entries.items() for dot, stamp in dots.items())
    runs: list[Delta] = []
    first: tuple[Dot, Stamp] | None = None
    added: list[Triple] = []
    for dot, stamp, triple in tagged:
        if first is not None and (dot.writer, stamp) == (first[0].writer, first[1]) \
                and dot.seq == first[0].seq + len(added):
            added.append(triple)
            continue
        if first is not None:
            runs.append(Delta(first[0], first[1], tuple(added)))
        first, added = (dot, stamp), [triple]
    if first is not None:
        runs.append(Delta(first[0], first[1], tuple(added)))
    return runs


def snapshot_payloads(states: Mapping[str, WrittenState],
                      write_ids: Sequence[tuple[WriteId, Remembered]] = ()) -> Iterator[bytes]:
    """A snapshot's records after its meta: per module a head and its
    written triples in parts, the write ids remembered, then the end."""
    count = 0
    for wid, remembered in write_ids:
        yield _write_id_payload(wid, remembered)
        count += 1
    for module, state in states.items():
        head = WrittenState(state.context, {}, state.removed_base, state.tombstones)
        yield HEAD_KIND + encode_sync(SyncMessage(module, CausalContext(), head))
        count += 1
        part: list[Delta] = []
        size = 0
        for run in _runs(state.entries):
            part.append(run)
            size += len(run.added)
            if size >= ENTRIES_PER_RECORD:
                yield ENTRIES + encode_sync(SyncMessage(module, CausalContext(), part))
                count += 1
                part, size = [], 0
        if part:
            yield ENTRIES + encode_sync(SyncMessage(module, CausalContext(), part))
            count += 1
    yield END + cbor2.dumps(count)


def _snapshot_states(records: list[bytes], name: str,
                     write_ids: list[tuple[WriteId, Remembered]]) -> dict[str, WrittenState]:
    """The modules' states a snapshot's records hold; its write ids go into ``write_ids``."""
    heads: dict[str, WrittenState] = {}
    entries: dict[str, dict[Triple, dict[Dot, Stamp]]] = {}
    if not records or records[-1][:1] != END:
        raise DataDirError(f"{name}: corrupt: the snapshot does not end with its end record")
    try:
        count = cbor2.loads(records[-1][1:])
    except (cbor2.CBORDecodeError, ValueError, TypeError, EOFError):
        count = None
    if count != len(records) - 1:
        raise DataDirError(f"{name}: corrupt: the end record counts {count} records, the file has {len(records) - 1}")
    for payload in records[:-1]:
        kind = payload[:1]
        if kind == WRITE_ID:
            write_ids.append(_decode_write_id(payload, name))
            continue
        message = _decode(payload, name)
        changes = message.changes
        if kind == HEAD_KIND and isinstance(changes, WrittenState):
            if message.module in heads:
                raise DataDirError(f"{name}: corrupt: two heads for {message.module}")
            heads[message.module] = changes
            entries[message.module] = {}
        elif kind == ENTRIES and isinstance(changes, list):
            if message.module not in heads:
                raise DataDirError(f"{name}: corrupt: written triples of {message.module} before its head")
            into = entries[message.module]
            for run in changes:
                for triple, dot in run.tagged():
                    into.setdefault(triple, {})[dot] = run.stamp
        else:
            raise DataDirError(f"{name}: corrupt: a record of kind {kind!r} in a snapshot")
    return {m: WrittenState(h.context, entries[m], h.removed_base, h.tombstones) for m, h in heads.items()}


# ---------------------------------------------------------------- the folder


def _fsync_dir(path: Path, disk: Disk) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        disk.sync(fd)
    finally:
        os.close(fd)


def _write_file(path: Path, chunks: Iterable[bytes], disk: Disk) -> int:
    """``chunks`` into ``path`` through ``path.tmp``: whole or not at all."""
    tmp = path.with_name(path.name + ".tmp")
    size = 0
    with open(tmp, "wb") as out:
        for chunk in chunks:
            out.write(chunk)
            size += len(chunk)
        out.flush()
        disk.sync(out.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent, disk)
    return size


class Journal:
    """An open data folder: appends to the current journal, writes
    snapshots, and recovers what the folder held (:meth:`open`)."""

    def __init__(self, path: Path, robot: str, writer: str, generation: int, lock: int, disk: Disk) -> None:
        self.path = path
        self.disk = disk
        self.robot = robot
        self.writer = writer
        #: The current journal's generation.
        self.generation = generation
        self._lock = lock
        self._file = open(self._journal(generation), "ab")  # open until close()
        #: Bytes in the current journal.
        self.journal_bytes = self._file.tell()
        #: Bytes of the last snapshot written or read.
        self.snapshot_bytes = 0

    def __repr__(self) -> str:
        return f"<Journal {self.path} generation {self.generation}>"

    def _journal(self, generation: int) -> Path:
        return self.path / f"journal.{generation}"

    def _snapshot(self, generation: int) -> Path:
        return self.path / f"snapshot.{generation}"

    # ------------------------------------------------------------ opening

    @classmethod
    def open(cls, path: str | Path, robot: str, new_writer: str,
             disk: Disk | None = None) -> tuple[Journal, Recovered]:
        """Lock the folder (made if missing) and read it; a new folder takes
        ``new_writer``, an old one keeps the writer it names.  ``disk``: how
        it syncs (None: the operating system's)."""
        disk = Disk() if disk is None else disk
        path = Path(path)
        try:
            path.mkdir(parents=True, exist_ok=True)
            lock = os.open(path / "lock", os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DataDirError(f"data folder {path}: {exc.strerror}") from None
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(lock)
            raise DataDirError(f"data folder {path} is in use by another process") from None
        try:
            recovered, generation = cls._recover(path, robot, new_writer, disk)
            journal = cls(path, robot, recovered.writer, generation, lock, disk)
        except BaseException:
            os.close(lock)
            raise
        with contextlib.suppress(OSError):
            journal.snapshot_bytes = journal._snapshot(generation).stat().st_size
        return journal, recovered

    @classmethod
    def _recover(cls, path: Path, robot: str, new_writer: str, disk: Disk) -> tuple[Recovered, int]:
        journals: dict[int, Path] = {}
        snapshots: dict[int, Path] = {}
        for entry in path.iterdir():
            if entry.name.endswith(".tmp"):
                entry.unlink()  # a snapshot or a journal whose writing did not finish
                continue
            named = _NAME.match(entry.name)
            if named:
                (journals if named[1] == "journal" else snapshots)[int(named[2])] = entry
        if not journals and not snapshots:
            # A folder made inside a repository (``data_dir = "data"`` beside
            # the TOML) is never committed by mistake.
            ignore = path / ".gitignore"
            if not ignore.exists():
                ignore.write_text("# coapkb's data folder: a robot's writes, never committed\n*\n", encoding="utf-8")
            _write_file(path / "journal.0", [JOURNAL_MAGIC, encode_record(_meta(robot, new_writer, 0))], disk)
            return Recovered(new_writer, fresh=True), 0
        base = max(snapshots, default=0)
        wanted = sorted(g for g in journals if g >= base)
        if not wanted or wanted[0] != base or wanted != list(range(base, wanted[-1] + 1)):
            have = ", ".join(p.name for p in sorted([*journals.values(), *snapshots.values()]))
            raise DataDirError(f"data folder {path}: journal.{base} is missing (it holds {have})")
        writer: str | None = None

        def check(name: str, payload: bytes, generation: int) -> None:
            nonlocal writer
            owner, named_writer, meta_generation = _read_meta(payload, name)
            if owner != robot:
                raise DataDirError(f"{name} belongs to {owner}, not {robot}")
            if meta_generation != generation:
                raise DataDirError(f"{name}: corrupt: its meta record says generation {meta_generation}")
            if writer is not None and named_writer != writer:
                raise DataDirError(f"{name}: written by {named_writer}, the folder's other files by {writer}")
            writer = named_writer

        recovered = Recovered("")
        if base in snapshots:
            name = str(snapshots[base])
            scan = read_records(snapshots[base].read_bytes(), name, SNAPSHOT_MAGIC, torn_ok=False)
            if not scan.records:
                raise DataDirError(f"{name}: corrupt: no meta record")
            check(name, scan.records[0], base)
            recovered.states = _snapshot_states(scan.records[1:], name, recovered.write_ids)
        for generation in wanted:
            file = journals[generation]
            name = str(file)
            data = file.read_bytes()
            scan = read_records(data, name, JOURNAL_MAGIC, torn_ok=True)
            if not scan.records:
                raise DataDirError(f"{name}: corrupt: no meta record")
            check(name, scan.records[0], generation)
            for payload in scan.records[1:]:
                if payload[:1] == WRITE_ID:
                    recovered.write_ids.append(_decode_write_id(payload, name))
                    continue
                if payload[:1] != CHANGE:
                    raise DataDirError(f"{name}: corrupt: a record of kind {payload[:1]!r} in a journal")
                message = _decode(payload, name)
                assert message.changes is not None
                recovered.changes.append((message.module, message.changes))
            if scan.torn is not None:
                # Appended but never answered: the write it held was not acknowledged.
                log.warning("%s: cut a torn tail at byte %d (%s, %d bytes)", name, scan.end, scan.torn,
                            len(data) - scan.end)
                with open(file, "r+b") as out:
                    out.truncate(scan.end)
                    out.flush()
                    disk.sync(out.fileno())
                recovered.cut += len(data) - scan.end
        # Compacted away before the last start: gone for good.
        for generation, stale in [*journals.items(), *snapshots.items()]:
            if generation < base:
                stale.unlink()
        assert writer is not None
        recovered.writer = writer
        return recovered, wanted[-1]

    # ------------------------------------------------------------ writing

    def append(self, changes: Iterable[tuple[str, Change]], made: tuple[WriteId, Remembered] | None = None) -> int:
        """Append one record per delta (or state), and the id of the write
        that ``made`` them if it has one, and fsync: on disk when this
        returns.  How many bytes it wrote."""
        records = b"".join(
            encode_record(_change_payload(module, item))
            for module, change in changes
            for item in ([change] if isinstance(change, WrittenState) else change)
        )
        if made is not None:
            records += encode_record(_write_id_payload(*made))
        if not records:
            return 0
        self._file.write(records)
        self._file.flush()
        self.disk.sync(self._file.fileno(), data_only=True)
        self.journal_bytes += len(records)
        return len(records)

    def rotate(self) -> int:
        """Start the next generation's journal (what is appended from now
        on goes there); the new generation, which :meth:`write_snapshot`
        then takes with the state as it is now."""
        generation = self.generation + 1
        _write_file(self._journal(generation), [JOURNAL_MAGIC, encode_record(_meta(self.robot, self.writer, generation))],
                    self.disk)
        self._file.close()
        self._file = open(self._journal(generation), "ab")  # open until close()
        self.generation = generation
        self.journal_bytes = self._file.tell()
        return generation

    def write_snapshot(self, generation: int, states: Mapping[str, WrittenState],
                       write_ids: Sequence[tuple[WriteId, Remembered]] = ()) -> int:
        """Write the snapshot of ``generation`` (the state when it was
        rotated to) and remove what it replaces; its size.  May run in a
        thread of its own while the journal is appended to."""
        chunks: Iterator[bytes] = (
            encode_record(p)
            for p in [_meta(self.robot, self.writer, generation), *snapshot_payloads(states, write_ids)]
        )
        size = _write_file(self._snapshot(generation), [SNAPSHOT_MAGIC, *chunks], self.disk)
        for old in range(generation - 1, -1, -1):
            gone = False
            for stale in (self._journal(old), self._snapshot(old)):
                with contextlib.suppress(FileNotFoundError):
                    stale.unlink()
                    gone = True
            if not gone:
                break
        _fsync_dir(self.path, self.disk)
        self.snapshot_bytes = size
        return size

    def close(self) -> None:
        if self._lock < 0:
            return
        self._file.close()
        os.close(self._lock)
        self._lock = -1
