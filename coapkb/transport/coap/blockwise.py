"""Block-wise transfer (RFC 7959) on the server: aiocoap's spool and cache,
with two of their pitfalls handled.

* aiocoap's Block2 cache keys on the request's options but not its body, so
  two FETCHes with different queries could get each other's blocks.  This
  cache keys on the body too.
* a gap in Block1 blocks is the client's error (4.08), not a 5.00 with a
  logged traceback.
"""

from __future__ import annotations

import hashlib
from typing import Any, Callable

import aiocoap
from aiocoap.numbers.constants import TransportTuning
from aiocoap.optiontypes import BlockOption

from .aiocoap_adapter import Block1Spool, Block2Cache, IncompleteException, TimeoutDict, block_key, extract_block


class GapSafeBlock1Spool(Block1Spool):
    """aiocoap's Block1 spool answers a gap in the blocks (ValueError) with a
    5.00 and a logged traceback; it is the client's error: 4.08 Incomplete."""

    def feed_and_take(self, req: aiocoap.Message) -> aiocoap.Message:
        try:
            return super().feed_and_take(req)
        except ValueError:
            raise IncompleteException from None


class BodyAwareBlock2Cache(Block2Cache):
    """aiocoap's Block2 cache, keyed on the request body as well.

    Follow-up block requests without a body (as aiocoap's client sends them)
    are served only when exactly one cached answer matches; otherwise 4.08,
    so an answer never reaches the wrong query."""

    def __init__(self) -> None:
        super().__init__()
        lifetime = TransportTuning().MAX_TRANSMIT_WAIT
        self._completes = TimeoutDict(lifetime)
        self._bodies: TimeoutDict = TimeoutDict(lifetime)

    async def extract_or_insert(self, req: aiocoap.Message, response_builder: Callable[[], Any]) -> aiocoap.Message:
        base_key = block_key(req)
        body = hashlib.blake2s(req.payload, digest_size=8).digest() if req.payload else None
        if req.opt.block2 is None or req.opt.block2.block_number == 0:
            assembled = await response_builder()
            if body is None:
                body = b""
        else:
            if body is None:
                try:
                    candidates = self._bodies[base_key]
                except KeyError:
                    raise IncompleteException from None
                if len(candidates) != 1:
                    raise IncompleteException
                (body,) = candidates
            try:
                assembled = self._completes[(base_key, body)]
            except KeyError:
                raise IncompleteException from None
        too_big = len(assembled.payload) > req.remote.maximum_payload_size or (
            req.opt.block2 is not None and len(assembled.payload) > req.opt.block2.size
        )
        if not too_big:
            return assembled
        self._completes[(base_key, body)] = assembled
        try:
            bodies = self._bodies[base_key]
        except KeyError:
            bodies = set()
        bodies.add(body)
        self._bodies[base_key] = bodies
        block2 = req.opt.block2 or BlockOption.BlockwiseTuple(0, 0, req.remote.maximum_block_size_exp)
        return extract_block(assembled, block2.block_number, block2.size_exponent, req.remote.maximum_payload_size)
