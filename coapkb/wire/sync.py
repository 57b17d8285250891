"""The replication message: a holder's context and the changes it sends
(pure; specified in ``docs/knowledge.cddl``).

::

    sync     = [module: tstr, context, changes / null,
                ? (forward: bool, ? (made-under / null, ? (life / null, ? lives)))]
    context  = [* [writer: tstr, top: uint, ? [+ seq: uint]]]   ; vv, then dots past a gap
    changes  = deltas / state
    deltas   = [triples: graph-item, [* delta]]
    delta    = [writer: tstr, seq: uint, ms: uint, counter: uint,
                removed: [* [writer: tstr, [+ seq: uint]]],
                removed-base: uint, added: uint]
    state    = {1: context, 2: graph-item, 3: [* [+ dot-stamp]], 4: graph-item,
                ? 5: [* [writer: tstr, [+ seq: uint]]]}
    dot-stamp = [writer: tstr, seq: uint, ms: uint, counter: uint]
    graph-item = #6.24(bstr .cbor graph)   ; a compact-results graph
    made-under = [writer: tstr, write: tstr, digest: bstr .size 8, removed: uint, added: uint,
                  ? peer: tstr / null]
    life     = [robot: tstr, number: uint]
    lives    = {* tstr => uint}

The triples of all the deltas travel in one compact graph, so their
prefixes and repeated names are sent once: each delta takes, in order, its
``removed-base`` count of them (the files' triples it removed), then its
``added`` count.  ``forward`` asks the receiver to pass deltas new to it on to the holders
it knows (a push from another cluster).  ``made-under`` is the id of the
client's write a push of one delta comes from; without ``peer``, its
sender is the name before the writer's first dot (``Robot2`` of
``Robot2.7f3a``).  ``life`` is the sender's life, when it writes under the
one name of its lives kept in memory, and ``lives`` (in an answer to a
question) the highest life the answering robot knows of each holder of
the module (``docs/knowledge.md``, section 6).  In a state, key 2 is the
written triples, key 3 the dots (and stamps) of each in the same order,
key 4 the files' triples removed, key 5 the tombstones (dots removed
before their write arrived).  Decoders raise
:class:`~coapkb.wire.codec.CodecError` and nothing else on malformed input.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cbor2

from ..model.deltas import CausalContext, Delta, Dot, MadeUnder, Stamp, WrittenState
from ..model.results import Triple
from . import codec
from .codec import CodecError, decode_graph_item

__all__ = ["Life", "SyncMessage", "decode_sync", "encode_sync"]

#: Bounds a decoder holds garbage to before building anything from it.
MAX_WRITERS = 4096
MAX_DELTAS = 100_000


@dataclass(frozen=True)
class Life:
    """One life (process) of a robot kept in memory that writes under the
    name of all its lives: ``number`` orders them."""

    robot: str
    number: int


@dataclass(frozen=True)
class SyncMessage:
    module: str
    context: CausalContext
    #: Deltas, a whole written state, or None (only the context: "what do I lack?").
    changes: Sequence[Delta] | WrittenState | None = None
    #: Pass the deltas new to the receiver on to the holders it knows.
    forward: bool = False
    #: The id of the client's write the one delta pushed comes from.
    made: MadeUnder | None = None
    #: The sender's life, when it writes under its lives' one name.
    life: Life | None = None
    #: In an answer to a question: the highest life of each robot the answerer knows.
    lives: Mapping[str, int] = field(default_factory=dict)


def _context(context: CausalContext) -> list[list[object]]:
    cloud: dict[str, list[int]] = {}
    for dot in sorted(context.cloud):
        cloud.setdefault(dot.writer, []).append(dot.seq)
    items: list[list[object]] = []
    for writer in sorted(set(context.vv) | set(cloud)):
        item: list[object] = [writer, context.vv.get(writer, 0)]
        if writer in cloud:
            item.append(cloud[writer])
        items.append(item)
    return items


def _dots(dots: Sequence[Dot]) -> list[list[object]]:
    grouped: dict[str, list[int]] = {}
    for dot in dots:
        grouped.setdefault(dot.writer, []).append(dot.seq)
    return [[writer, seqs] for writer, seqs in grouped.items()]


def _deltas(deltas: Sequence[Delta]) -> list[object]:
    triples = [t for d in deltas for t in (*d.removed_base, *d.added)]
    return [
        codec.graph_item(triples),
        [[d.dot.writer, d.dot.seq, d.stamp.ms, d.stamp.counter, _dots(d.removed), len(d.removed_base), len(d.added)]
         for d in deltas],
    ]


def _state(state: WrittenState) -> dict[int, object]:
    triples = list(state.entries)
    encoded: dict[int, object] = {
        1: _context(state.context),
        2: codec.graph_item(triples),
        3: [[[d.writer, d.seq, s.ms, s.counter] for d, s in sorted(state.entries[t].items())] for t in triples],
        4: codec.graph_item(sorted(state.removed_base, key=repr)),
    }
    if state.tombstones:
        encoded[5] = _dots(sorted(state.tombstones))
    return encoded


def encode_sync(message: SyncMessage) -> bytes:
    changes: object = None
    if isinstance(message.changes, WrittenState):
        changes = _state(message.changes)
    elif message.changes is not None:
        changes = _deltas(message.changes)
    fields: list[object] = [
        message.module, _context(message.context), changes, message.forward,
        None if message.made is None else _made(message.made),
        None if message.life is None else [message.life.robot, message.life.number],
        dict(sorted(message.lives.items())),
    ]
    # The optional tail is sent only as far as its last field that says something.
    while len(fields) > 3 and fields[-1] in (None, False, {}):
        fields.pop()
    return cbor2.dumps(fields)


def _made(made: MadeUnder) -> list[object]:
    fields: list[object] = [made.writer, made.write, made.digest, made.removed, made.added]
    if made.peer != _sender_named(made.writer):
        fields.append(made.peer)
    return fields


def _sender_named(writer: str) -> str:
    """The sender a made-under without ``peer`` stands for."""
    return writer.split(".", 1)[0]


# ------------------------------------------------------------------ decoding


def _uint(item: object, what: str) -> int:
    if not isinstance(item, int) or isinstance(item, bool) or item < 0:
        raise CodecError(f"{what}: expected an unsigned integer")
    return item


def _text(item: object, what: str) -> str:
    if not isinstance(item, str) or not item or len(item) > 200:
        raise CodecError(f"{what}: expected a name")
    return item


def _list(item: object, what: str, limit: int = MAX_DELTAS) -> list[object]:
    if not isinstance(item, list) or len(item) > limit:
        raise CodecError(f"{what}: expected an array of at most {limit}")
    return item


def _decode_context(item: object) -> CausalContext:
    vv: dict[str, int] = {}
    cloud: list[Dot] = []
    for entry in _list(item, "context", MAX_WRITERS):
        entry = _list(entry, "context entry", 3)
        if len(entry) < 2:
            raise CodecError("context entry: expected [writer, top, ?seqs]")
        writer = _text(entry[0], "context writer")
        vv[writer] = _uint(entry[1], "context top")
        if len(entry) == 3:
            cloud += [Dot(writer, _uint(s, "context seq")) for s in _list(entry[2], "context seqs")]
    return CausalContext({w: s for w, s in vv.items() if s}, cloud)


def _decode_dots(item: object, what: str) -> list[Dot]:
    dots: list[Dot] = []
    for group in _list(item, what, MAX_WRITERS):
        group = _list(group, f"{what} entry", 2)
        if len(group) != 2:
            raise CodecError(f"{what} entry: expected [writer, seqs]")
        dots += [Dot(_text(group[0], f"{what} writer"), _uint(s, f"{what} seq")) for s in _list(group[1], "seqs")]
    return dots


def _decode_deltas(item: list[object]) -> list[Delta]:
    if len(item) != 2:
        raise CodecError("deltas: expected [triples, [delta...]]")
    triples = decode_graph_item(item[0], "delta triples")
    at = 0
    deltas = []
    for raw in _list(item[1], "deltas"):
        fields = _list(raw, "delta", 7)
        if len(fields) != 7:
            raise CodecError("delta: expected 7 fields")
        writer = _text(fields[0], "delta writer")
        seq = _uint(fields[1], "delta seq")
        if seq == 0:
            raise CodecError("delta seq: counts from 1")
        removed_base, added = _uint(fields[5], "removed-base count"), _uint(fields[6], "added count")
        if at + removed_base + added > len(triples):
            raise CodecError("deltas: more triples counted than sent")
        deltas.append(Delta(
            Dot(writer, seq),
            Stamp(_uint(fields[2], "delta ms"), _uint(fields[3], "delta counter"), writer),
            added=triples[at + removed_base:at + removed_base + added],
            removed=tuple(_decode_dots(fields[4], "removed dots")),
            removed_base=triples[at:at + removed_base],
        ))
        at += removed_base + added
    if at != len(triples):
        raise CodecError("deltas: triples sent that no delta counts")
    return deltas


def _decode_state(item: dict[object, object]) -> WrittenState:
    if not {1, 2, 3, 4} <= set(item) <= {1, 2, 3, 4, 5}:
        raise CodecError("state: expected keys 1-4 and maybe 5")
    triples = decode_graph_item(item[2], "state triples")
    dots = _list(item[3], "state dots")
    if len(dots) != len(triples):
        raise CodecError("state: a dot list per triple")
    entries: dict[Triple, dict[Dot, Stamp]] = {}
    for triple, tags in zip(triples, dots):
        tagged: dict[Dot, Stamp] = {}
        for tag in _list(tags, "state dot list", MAX_WRITERS):
            tag = _list(tag, "state dot", 4)
            if len(tag) != 4:
                raise CodecError("state dot: expected [writer, seq, ms, counter]")
            writer = _text(tag[0], "state writer")
            tagged[Dot(writer, _uint(tag[1], "state seq"))] = Stamp(
                _uint(tag[2], "state ms"), _uint(tag[3], "state counter"), writer
            )
        if not tagged:
            raise CodecError("state: a written triple has at least one dot")
        entries[triple] = tagged
    tombstones = _decode_dots(item.get(5, []), "tombstones")
    return WrittenState(_decode_context(item[1]), entries, frozenset(decode_graph_item(item[4], "removed base")),
                        frozenset(tombstones))


def _decode_made(item: object) -> MadeUnder:
    fields = _list(item, "made-under", 6)
    if len(fields) not in (5, 6):
        raise CodecError("made-under: expected [writer, write, digest, removed, added, ?peer]")
    writer, write = _text(fields[0], "made-under writer"), _text(fields[1], "made-under write")
    digest = fields[2]
    if not isinstance(digest, bytes) or len(digest) != 8:
        raise CodecError("made-under digest: expected 8 bytes")
    peer = fields[5] if len(fields) == 6 else _sender_named(writer)
    if peer is not None:
        peer = _text(peer, "made-under peer")
    return MadeUnder(peer, writer, write, digest, _uint(fields[3], "made-under removed"),
                     _uint(fields[4], "made-under added"))


def _decode_life(item: object) -> Life:
    fields = _list(item, "life", 2)
    if len(fields) != 2:
        raise CodecError("life: expected [robot, number]")
    return Life(_text(fields[0], "life robot"), _uint(fields[1], "life number"))


def _decode_lives(item: object) -> dict[str, int]:
    if not isinstance(item, dict) or len(item) > MAX_WRITERS:
        raise CodecError(f"lives: expected a map of at most {MAX_WRITERS} robots")
    return {_text(robot, "lives robot"): _uint(number, "lives number") for robot, number in item.items()}


def decode_sync(data: bytes) -> SyncMessage:
    item = codec.load_cbor(data)
    fields = _list(item, "sync", 7)
    if len(fields) < 3 or (len(fields) > 3 and not isinstance(fields[3], bool)):
        raise CodecError("sync: expected [module, context, changes, ?forward, ?made-under, ?life, ?lives]")
    module = _text(fields[0], "module")
    context = _decode_context(fields[1])
    raw = fields[2]
    changes: Sequence[Delta] | WrittenState | None
    if raw is None:
        changes = None
    elif isinstance(raw, dict):
        changes = _decode_state(raw)
    else:
        changes = _decode_deltas(_list(raw, "changes", 2))
    made = _decode_made(fields[4]) if len(fields) > 4 and fields[4] is not None else None
    life = _decode_life(fields[5]) if len(fields) > 5 and fields[5] is not None else None
    lives = _decode_lives(fields[6]) if len(fields) > 6 else {}
    return SyncMessage(module, context, changes, forward=len(fields) > 3 and fields[3] is True, made=made,
                       life=life, lives=lives)
