"""Write concern: how far a write must have reached before it is answered,
and how its answer says how far it reached (``docs/knowledge.md``, "Write
concern").

The writer asks with the URI query ``ack`` of PATCH/iPATCH ``/kb``:

* ``local``: written at the robot written to (on its disk when it has a
  data folder, else in its memory only); answered at once, the pushes go on;
* ``2`` (the default, and a request without ``ack``): also on a second
  holder of every module the write changed (that holder answered its push);
* ``all``: on every holder of those modules this robot pushes to (its
  cluster's and its replicas in the next cluster), within the ack wait.

The answer is text (content-format 0), one line:

* 2.04: ``removed N, added M; ack LEVEL (H of K holders[, in memory])``,
  LEVEL the strongest level reached (at least the one asked); to a writer
  that accepts CBOR (60), the array ``[N, M, LEVEL]`` instead
  (:func:`encode_changed`);
* 5.04: ``ack LEVEL (H of K holders[, in memory]), asked ASKED: written
  here, version HEX, ...``: fewer holders confirmed it than asked within
  the wait.  The write is not undone and spreads when they answer.

This module holds the levels, the parsing of the option and both
answers' text, for the robot and its clients alike.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Mapping
from dataclasses import dataclass

import cbor2

__all__ = [
    "ACK_PARAM", "DEFAULT_ACK", "Ack", "Answer", "Reached", "ack_of_query", "changed_line", "decode_changed",
    "encode_changed", "parse_ack", "parse_answer", "short_line",
]

#: The URI query parameter of a write naming its concern.
ACK_PARAM = "ack"


class Ack(enum.StrEnum):
    """A write concern, weakest first."""

    LOCAL = "local"
    TWO = "2"
    ALL = "all"

    @property
    def rank(self) -> int:
        return _RANKS[self]

    def covers(self, other: Ack) -> bool:
        """Whether reaching ``self`` meets a request for ``other``."""
        return self.rank >= other.rank


_RANKS = {Ack.LOCAL: 0, Ack.TWO: 1, Ack.ALL: 2}
#: What a request without ``ack`` asks: as before there was a choice.
DEFAULT_ACK = Ack.TWO
_CHOICES = "local, 2 or all"


def parse_ack(text: str) -> Ack:
    """The level ``text`` names (exactly ``local``, ``2`` or ``all``);
    ValueError with a one-line reason otherwise."""
    try:
        return Ack(text)
    except ValueError:
        raise ValueError(f"ack takes {_CHOICES}, not {text[:40]!r}") from None


def ack_of_query(query: Mapping[str, str], also: Mapping[str, str] | None = None) -> Ack:
    """The concern a write's URI query asks (:data:`DEFAULT_ACK` without
    ``ack``).  A write takes no other parameter than those ``also`` names
    (name -> what its value is, for the message): a misspelt one would
    silently ask the default.  ValueError with a one-line reason."""
    taken = {ACK_PARAM: "|".join(a.value for a in Ack), **(also or {})}
    others = sorted(k for k in query if k not in taken)
    if others:
        names = " and ".join(f"{k}={v}" for k, v in taken.items())
        counted = "one query parameter" if len(taken) == 1 else "the query parameters"
        raise ValueError(f"a write takes {counted} {names}; not {others[0][:40]!r}")
    text = query.get(ACK_PARAM)
    return DEFAULT_ACK if text is None else parse_ack(text)


@dataclass(frozen=True)
class Reached:
    """How far a write had reached when it was answered."""

    level: Ack
    #: Robots holding it: this one and the other holders that confirmed it.
    holders: int = 1
    #: Robots known to hold the modules it changed, this one included.
    of: int = 1
    #: The holders whose push was still unanswered, by name.
    waiting: tuple[str, ...] = ()
    #: The holders whose push failed (unreachable, or refused), by name.
    failed: tuple[str, ...] = ()
    #: False: the write changed nothing, so there was nothing to pass on.
    changed: bool = True
    #: True: a repeat of a write made before this robot restarted (its
    #: data folder kept the write and its id, not how far it had reached).
    before_restart: bool = False
    #: A repeat of a write another holder made and pushed here: that holder.
    made_by: str | None = None

    def describe(self, *, durable: bool) -> str:
        """``ack LEVEL (H of K holders[, in memory])``; ``durable``: this
        robot keeps its writes in a data folder."""
        if not self.changed:
            return f"ack {self.level} (nothing changed)"
        if self.made_by is not None:
            return f"ack {self.level} (made by {self.made_by}, which passed it on here)"
        if self.before_restart:
            return f"ack {self.level} (written before this robot restarted)"
        where = "" if durable else ", in memory"
        return f"ack {self.level} ({self.holders} of {self.of} holder{'s' if self.of != 1 else ''}{where})"


def changed_line(removed: int, added: int, reached: Reached, *, durable: bool) -> str:
    """A 2.04's payload."""
    return f"removed {removed}, added {added}; {reached.describe(durable=durable)}"


def encode_changed(removed: int, added: int, reached: Reached) -> bytes:
    """A 2.04's payload in CBOR: ``[removed, added, level]``."""
    return cbor2.dumps([removed, added, reached.level.value])


def decode_changed(payload: bytes) -> tuple[int, int, Ack]:
    """The inverse of :func:`encode_changed`; ValueError if it is not one."""
    try:
        removed, added, level = cbor2.loads(payload)
    except (cbor2.CBORDecodeError, TypeError, ValueError) as exc:
        raise ValueError(f"not a write answer: {exc}") from None
    if type(removed) is not int or type(added) is not int or removed < 0 or added < 0 or not isinstance(level, str):
        raise ValueError("not a write answer: expected [removed, added, level]")
    return removed, added, parse_ack(level)


def short_line(reached: Reached, asked: Ack, version: bytes, *, durable: bool, wait_s: float) -> str:
    """A 5.04's payload: the write is here, fewer holders confirmed it than asked."""
    kept = "kept on disk" if durable else "in memory only (no data folder)"
    why = []
    if reached.made_by is not None:
        why.append(f"{reached.made_by} made it and passed it on here; which other holders have it is not known here")
    elif reached.before_restart:
        why.append("which holders it reached then is not known here")
    if reached.failed:
        why.append(f"{', '.join(reached.failed)} unreachable or refused it")
    if reached.waiting:
        why.append(f"{', '.join(reached.waiting)} did not answer within {wait_s:g} s")
    return (f"{reached.describe(durable=durable)}, asked {asked}: written here, version {version.hex()}, {kept}; "
            f"{'; '.join(why) or 'no other holder confirmed it'}; it spreads to them when they answer: "
            "do not send it again")


_LEVEL = r"(local|2|all)"
_CHANGED = re.compile(rf"^removed \d+, added \d+; ack {_LEVEL}\b")
_SHORT = re.compile(rf"^ack {_LEVEL} \([^)]*\), asked {_LEVEL}: written here, version ([0-9a-f]*),")


@dataclass(frozen=True)
class Answer:
    """What a write's answer says of its concern."""

    reached: Ack
    #: The level asked (a 5.04 names it; None in a 2.04, which met it).
    asked: Ack | None = None
    #: The KB's version after the write (a 5.04 names it in its text).
    version: bytes | None = None


def parse_answer(text: str, *, short: bool) -> Answer | None:
    """The concern a 2.04's (``short`` False) or a 5.04's payload reports;
    None if it is not such an answer (a robot before write concerns, or
    a 5.04 from elsewhere: a proxy)."""
    if not short:
        match = _CHANGED.match(text)
        return None if match is None else Answer(Ack(match[1]))
    match = _SHORT.match(text)
    if match is None:
        return None
    return Answer(Ack(match[1]), Ack(match[2]), bytes.fromhex(match[3]) if len(match[3]) % 2 == 0 else None)
