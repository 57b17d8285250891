"""Block-wise transfer (RFC 7959) on the server: aiocoap's spool and cache,
with their pitfalls handled.

* aiocoap's Block2 cache keys on the request's options but not its body, so
  two FETCHes with different queries could get each other's blocks.
* aiocoap's and libcoap's clients send the Block2 follow-ups of a FETCH or
  POST without the body (the standard leaves this open: core-wg/corrclar#27;
  libcoap had the same bug, #793).  A follow-up therefore names its transfer
  only by the client endpoint, the resource and the options.
* a gap in Block1 blocks is the client's error (4.08), not a 5.00 with a
  logged traceback.

How :class:`BodyAwareBlock2Cache` matches a follow-up to its answer:

1. The key is aiocoap's: client endpoint, method and every cache-key option
   (path, query, Accept, Content-Format, ETag, and Request-Tag (RFC 9175,
   option 292), which is safe-to-forward and not NoCacheKey).  A client that
   sends a Request-Tag, or coapkb's ``qh=`` body hash, thus has a key per
   transfer.
2. A follow-up that repeats the body is served from the answer to that body
   (answered afresh if that answer expired: the request is complete).
3. A body-less follow-up is served from the most recent multi-block transfer
   under its key: a client that asks one large question after another moves
   on to the new answer.  Only if the requested block lies beyond that answer
   does an older one come into question, and only if exactly one older answer
   has that block; otherwise the request really is ambiguous: 4.08.
4. Every multi-block answer carries an ETag (the service's, or a hash of the
   answer): every block of one answer has the same ETag and two different
   answers have different ones, so a client checking ETags (RFC 7959 section
   2.4; aiocoap's does) can never assemble blocks of two answers, even when
   concurrent body-less transfers from one endpoint make rule 3 pick the
   newer one.

Both kinds of state are bounded (:class:`~coapkb.transport.expiring.ExpiringMap`):
a server shares one spool and one cache among its resources, each holding at most
the bytes and entries its :class:`.StateBounds` allow, and none unused for
``transfer_idle_s``.  A
flood of large answers therefore costs a few MiB for a minute and a half,
not memory that grows with the flood (docs/flood.md); a follow-up whose
transfer was evicted gets 4.08, as after any expiry, or is answered afresh
if it carries its body.
"""

from __future__ import annotations

import hashlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import aiocoap
from aiocoap.numbers.codes import Code
from aiocoap.optiontypes import BlockOption

from ..expiring import ExpiringMap
from .aiocoap_adapter import (
    Block1Spool,
    Block2Cache,
    ContinueException,
    IncompleteException,
    block_key,
    extract_block,
)
from .bounds import MESSAGE_OVERHEAD, StateBounds


class GapSafeBlock1Spool(Block1Spool):
    """aiocoap's Block1 spool, bounded (:class:`.StateBounds`'s ``block1_*``
    and ``transfer_idle_s``); a gap in the blocks, which aiocoap answers with
    a 5.00 and a logged traceback, is the client's error: 4.08 Incomplete."""

    def __init__(self, bounds: StateBounds = StateBounds()) -> None:
        super().__init__()
        self._assemblies: ExpiringMap[Any, aiocoap.Message] = ExpiringMap(
            bounds.transfer_idle_s, bounds.block1_assemblies, bounds.block1_bytes,
            lambda m: len(m.payload) + MESSAGE_OVERHEAD)

    def purge(self) -> int:
        """Forget the assemblies idle for ``transfer_idle_s``; returns the bytes forgotten."""
        return self._assemblies.purge()

    def feed_and_take(self, req: aiocoap.Message) -> aiocoap.Message:
        block1 = req.opt.block1
        if block1 is None:
            return req
        key = block_key(req)
        if block1.block_number == 0:
            assembly = req  # any older incomplete request under this key is dropped
        else:
            try:
                assembly = self._assemblies[key]
                assembly._append_request_block(req)
            except (KeyError, ValueError):  # never started, evicted, or a gap
                raise IncompleteException from None
        self._assemblies[key] = assembly  # stored again: its size changed
        if block1.more:
            raise ContinueException(block1)
        return assembly


@dataclass(frozen=True)
class _Transfer:
    """One multi-block answer and the body of the request it answers."""

    body: bytes  # digest of the request body (b"" for none)
    answer: aiocoap.Message


def _body_digest(payload: bytes) -> bytes:
    return hashlib.blake2s(payload, digest_size=8).digest() if payload else b""


def answer_etag(answer: aiocoap.Message) -> bytes:
    """An ETag naming this answer's code, format and bytes."""
    digest = hashlib.blake2s(digest_size=8)
    digest.update(bytes([int(answer.code)]))
    digest.update(int(answer.opt.content_format or 0).to_bytes(2, "big"))
    digest.update(answer.payload)
    return digest.digest()


class BodyAwareBlock2Cache(Block2Cache):
    """aiocoap's Block2 cache, matching follow-ups to answers as the module
    docstring describes.

    ``max_per_key`` bounds the answers kept per client endpoint and request
    options; all of them together are bounded by :class:`.StateBounds`'s
    ``block2_bytes`` and ``block2_keys``, and forgotten ``transfer_idle_s``
    after their last use."""

    def __init__(self, max_per_key: int = 4, bounds: StateBounds = StateBounds()) -> None:
        super().__init__()
        if max_per_key < 1:
            raise ValueError(f"max_per_key must be at least 1, got {max_per_key}")
        self.max_per_key = max_per_key
        #: block key -> transfers under it, the most recent last.
        self._transfers: ExpiringMap[Any, list[_Transfer]] = ExpiringMap(
            bounds.transfer_idle_s, bounds.block2_keys, bounds.block2_bytes,
            lambda transfers: sum(len(t.answer.payload) + MESSAGE_OVERHEAD for t in transfers))

    def purge(self) -> int:
        """Forget the answers idle for ``transfer_idle_s``; returns the bytes forgotten."""
        return self._transfers.purge()

    async def extract_or_insert(
        self, req: aiocoap.Message, response_builder: Callable[[], Awaitable[aiocoap.Message]]
    ) -> aiocoap.Message:
        block2 = req.opt.block2
        key = block_key(req)
        if block2 is None or block2.block_number == 0:
            answer = await self._build(req, key, response_builder)
        else:
            answer = self._follow_up(req, key, block2)
            if answer is None:
                # A follow-up that carries its whole request (its body, or a
                # GET, which has none) can be answered afresh.
                if not req.payload and req.code != Code.GET:
                    raise IncompleteException
                answer = await self._build(req, key, response_builder)
        if answer.opt.block2 is not None or not self._needs_blocks(req, answer):
            return answer
        block2 = block2 or BlockOption.BlockwiseTuple(0, 0, req.remote.maximum_block_size_exp)
        return extract_block(answer, block2.block_number, block2.size_exponent, req.remote.maximum_payload_size)

    @staticmethod
    def _needs_blocks(req: aiocoap.Message, answer: aiocoap.Message) -> bool:
        size = len(answer.payload)
        return size > req.remote.maximum_payload_size or (req.opt.block2 is not None and size > req.opt.block2.size)

    async def _build(
        self, req: aiocoap.Message, key: Any, response_builder: Callable[[], Awaitable[aiocoap.Message]]
    ) -> aiocoap.Message:
        answer = await response_builder()
        if answer.opt.block2 is not None or not self._needs_blocks(req, answer):
            return answer  # one datagram (or blocks the resource made itself): nothing to remember
        if answer.opt.etag is None:
            answer.opt.etag = answer_etag(answer)
        body = _body_digest(req.payload)
        try:
            older = self._transfers[key]
        except KeyError:
            older = []
        # The same body again replaces its older answer; the newest goes last.
        kept = [t for t in older if t.body != body][-(self.max_per_key - 1):] if self.max_per_key > 1 else []
        self._transfers[key] = [*kept, _Transfer(body, answer)]
        return answer

    def _follow_up(self, req: aiocoap.Message, key: Any, block2: Any) -> aiocoap.Message | None:
        """The answer a follow-up block request belongs to, or None."""
        try:
            transfers: list[_Transfer] = self._transfers[key]
        except KeyError:
            return None
        if req.payload:
            body = _body_digest(req.payload)
            return next((t.answer for t in reversed(transfers) if t.body == body), None)
        start = block2.start
        newest = transfers[-1].answer
        if start < len(newest.payload):
            return newest
        covering = [t.answer for t in transfers[:-1] if start < len(t.answer.payload)]
        return covering[0] if len(covering) == 1 else None
