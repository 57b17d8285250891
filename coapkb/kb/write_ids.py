"""Write ids: a write tried again is applied once (docs/knowledge.md, "A
write tried again").

A PATCH is not idempotent, and a write is tried again without the holder
telling a repeat from a new write: the CoAP client's reliability layer
sends every try as a new exchange (a fresh token and message ID, so CoAP's
deduplication never sees it), a robot's knowledge writer tries a failed
write again, and a holder that answers late is asked again.  A repeat
that lands after another change (a delivery between a pick and its late
repeat) undoes that change.

So each write carries an id, the same for every try of it, as the URI
query ``wid=WRITER.N`` (an idempotency key: the part before the last dot
names the writer, the part after the write).  A holder remembers, per
writer and bounded, the ids of the writes it made with what it answered;
a repeat gets that answer again and changes nothing.  This module holds
the id, its parsing, and the memory (pure: no I/O).
"""

from __future__ import annotations

import hashlib
import re
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass

from ..transport.messages import Response

__all__ = ["WID_PARAM", "Remembered", "WriteId", "WriteIds", "WriteTag", "body_digest", "parse_wid", "writer_name"]

#: The URI query parameter of a write naming its id.
WID_PARAM = "wid"
#: The longest id taken (the writer's part and the write's together).
WID_MAX_CHARS = 64
#: The longest writer part :func:`writer_name` makes: room is left for the count.
WRITER_MAX_CHARS = 40
#: RFC 3986's unreserved characters; a dot parts the writer from the write.
_WID = re.compile(r"^([A-Za-z0-9._~-]+)\.([A-Za-z0-9_~-]+)$")
_NOT_UNRESERVED = re.compile(r"[^A-Za-z0-9._~-]")


@dataclass(frozen=True, order=True)
class WriteId:
    """A write's id as a holder keys it: the sender as the security layer
    authenticated it (None: unprotected), the writer the id names, and the
    write.  Two senders never share an id: one cannot answer for another."""

    peer: str | None
    writer: str
    write: str

    def __str__(self) -> str:
        return f"{self.writer}.{self.write}"


def writer_name(name: str) -> str:
    """``name`` (a robot's id and boot, say) as the writer part of an id:
    its characters outside the unreserved set as ``_``, and a long one cut
    and ended with a hash of it, so names that differ stay apart."""
    safe = _NOT_UNRESERVED.sub("_", name).strip(".") or "_"
    if len(safe) <= WRITER_MAX_CHARS and safe == name:
        return safe
    tail = hashlib.blake2s(name.encode(), digest_size=6).hexdigest()
    return f"{safe[:WRITER_MAX_CHARS - len(tail) - 1]}~{tail}"


def parse_wid(text: str, peer: str | None = None) -> WriteId:
    """The id ``text`` (``WRITER.N``) of a write from ``peer``; ValueError
    with a one-line reason if it is not one."""
    match = _WID.match(text) if len(text) <= WID_MAX_CHARS else None
    if match is None or not match[1].strip("."):
        raise ValueError(f"{WID_PARAM} takes WRITER.N, at most {WID_MAX_CHARS} letters, digits and ._~- "
                         f"(a writer's name, a dot, the write's count); not {text[:40]!r}")
    return WriteId(peer, match[1], match[2])


def body_digest(method: str, content_format: int | None, payload: bytes) -> bytes:
    """What a repeat must share with the first try of a write: its method,
    content-format and body (an id sent again with another update is a
    mistake, not a repeat)."""
    return hashlib.blake2s(f"{method} {content_format}\n".encode() + payload, digest_size=8).digest()


@dataclass(frozen=True)
class WriteTag:
    """A write's id and its body's digest, as the write is made with them."""

    wid: WriteId
    digest: bytes


@dataclass
class Remembered:
    """A write made under an id: what a repeat of it is answered from."""

    #: :func:`body_digest` of the write.
    digest: bytes
    #: The KB's version the write made (its ETag).
    version: bytes
    removed: int
    added: int
    #: The answer given (None until it is known, and after a restart: it is
    #: kept in memory only, the rest of the record on disk too).
    answer: Response | None = None
    #: The holder that made the write and pushed it here under its id
    #: (None: made here); ``version`` is then this robot's once it took it.
    made_by: str | None = None


class WriteIds:
    """The ids of the writes made lately, per writer, and what each was
    answered: at most ``per_writer`` ids of each of ``writers`` writers,
    the oldest id and the writer heard from least lately going first."""

    def __init__(self, per_writer: int, writers: int) -> None:
        if per_writer < 1 or writers < 1:
            raise ValueError(f"per_writer and writers must be at least 1, got {per_writer} and {writers}")
        self.per_writer = per_writer
        self.writers = writers
        self._by_writer: OrderedDict[tuple[str | None, str], OrderedDict[str, Remembered]] = OrderedDict()

    def __len__(self) -> int:
        return sum(len(ids) for ids in self._by_writer.values())

    def get(self, wid: WriteId) -> Remembered | None:
        ids = self._by_writer.get((wid.peer, wid.writer))
        return None if ids is None else ids.get(wid.write)

    def remember(self, wid: WriteId, remembered: Remembered) -> None:
        key = (wid.peer, wid.writer)
        ids = self._by_writer.get(key)
        if ids is None:
            ids = self._by_writer[key] = OrderedDict()
        self._by_writer.move_to_end(key)
        ids[wid.write] = remembered
        ids.move_to_end(wid.write)
        while len(ids) > self.per_writer:
            ids.popitem(last=False)
        while len(self._by_writer) > self.writers:
            self._by_writer.popitem(last=False)

    def __iter__(self) -> Iterator[tuple[WriteId, Remembered]]:
        """Every id remembered, in the order :meth:`remember` would put them back."""
        for (peer, writer), ids in self._by_writer.items():
            for write, remembered in ids.items():
                yield WriteId(peer, writer, write), remembered
