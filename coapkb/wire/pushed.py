"""Answers a KB holder pushes before it is asked (pure; ``robot-facts`` in
``docs/robot-state.cddl``).

::

    robot-facts = [* pushed-answer]
    pushed-answer = [request: bstr .size 8, max-age: uint / null, result: bstr]

Each is a named query's answer (``/kb/q/NAME?params``) as the holder would
give it to that request now: ``request`` names the request by
:func:`request_key` (the asker computes the same key for the question it
is about to put, so the name and parameters do not travel), ``result`` is
the compact CBOR answer (content-format 60), ``max-age`` its Max-Age (null:
CoAP's default, 60 s).  Decoders raise :class:`~coapkb.wire.codec.CodecError`
and nothing else on malformed input.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cbor2

from .codec import CodecError

#: The most answers one representation carries (a task needs at most a handful).
MAX_PUSHED = 8
#: Bytes of a request key: two keys of the few hundred a robot remembers
#: collide with odds of about 2^-48.
KEY_BYTES = 8


def request_key(name: str, params: Mapping[str, str]) -> bytes:
    """The key of the named query ``name`` with ``params``: the same on every robot."""
    return hashlib.blake2s(cbor2.dumps([name, sorted(params.items())]), digest_size=KEY_BYTES).digest()


@dataclass(frozen=True)
class PushedAnswer:
    """A named query's answer, keyed by the request it answers."""

    key: bytes
    max_age: int | None
    result: bytes


def encode_pushed(answers: Sequence[PushedAnswer]) -> bytes:
    return cbor2.dumps([[a.key, a.max_age, a.result] for a in answers])


def decode_pushed(data: bytes) -> tuple[PushedAnswer, ...]:
    """The answers of a ``robot-facts`` representation."""
    try:
        raw = cbor2.loads(data)
    except (cbor2.CBORDecodeError, RecursionError, ValueError, TypeError) as exc:
        raise CodecError(f"pushed answers are not CBOR: {exc}") from None
    if type(raw) is not list or len(raw) > MAX_PUSHED:
        raise CodecError(f"pushed answers are an array of at most {MAX_PUSHED} answers")
    answers = []
    for item in raw:
        if type(item) is not list or len(item) != 3:
            raise CodecError("a pushed answer is [request, max-age, result]")
        key, max_age, result = item
        if type(key) is not bytes or len(key) != KEY_BYTES or type(result) is not bytes:
            raise CodecError(f"a pushed answer's request is {KEY_BYTES} bytes and its result bytes")
        if max_age is not None and (type(max_age) is not int or max_age < 0):
            raise CodecError("a pushed answer's max-age is a uint or null")
        answers.append(PushedAnswer(key, max_age, result))
    return tuple(answers)
