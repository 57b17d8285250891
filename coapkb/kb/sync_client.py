"""The outgoing side of replication: this robot's sync messages to the
other holders of its modules, and what their answers carry.

A message to ``/kb/sync`` carries this robot's causal context of one
module and, in a push, changes; the holder answers with its own context
and the changes this robot lacks, which are taken in here, as the changes
of a message received are (:mod:`.sync_handler`).  Every sender and
answer is checked by :mod:`.sync_access`.  Overview: :mod:`.replication`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Coroutine, Sequence
from typing import Any

from ..model.deltas import CausalContext, Delta, MadeUnder, WrittenState
from ..transport.base import ClientTransport, TransportError
from ..transport.messages import ContentFormat, Method, Request, Status
from ..wire.codec import CodecError
from ..wire.sync import SyncMessage, decode_sync, encode_sync
from .life_fence import LifeFence
from .live import LiveKB
from .replication_settings import SYNC_PATH, Holder, ReplicationSettings, ReplicationStats
from .sync_access import SyncAccess, writer_robot

__all__ = ["SyncClient"]

log = logging.getLogger(__name__)


class SyncClient:
    """Pushes and exchanges with holders, for every part of replication
    (see the module docstring); ``client``: the transport they go by."""

    def __init__(self, live: LiveKB, client: ClientTransport, access: SyncAccess, settings: ReplicationSettings,
                 stats: ReplicationStats, fence: LifeFence) -> None:
        self.live = live
        self.client = client
        self.access = access
        self.fence = fence
        self.settings = settings
        self.stats = stats
        #: (module, holder) -> the last context it told us
        self.known: dict[tuple[str, str], CausalContext] = {}
        #: (sender or holder, module, status) already logged at warning level.
        self._warned: set[tuple[str, str, int]] = set()
        #: The pushes in flight, in the order they started (a dict: a set's order
        #: follows id(), and the replicator cancels them in this order).
        self.pushes: dict[asyncio.Task[bool], None] = {}

    def log_once(self, who: str, module: str, status: Status, text: str, *args: object) -> None:
        """A warning the first time, debug after: a misconfigured peer is
        said once, not at every round."""
        key = (who, module, int(status))
        level = logging.DEBUG if key in self._warned else logging.WARNING
        self._warned.add(key)
        log.log(level, text, *args)

    def spawn(self, coro: Coroutine[Any, Any, bool]) -> asyncio.Task[bool]:
        """A push run on its own, kept in :attr:`pushes` until it ends."""
        task = asyncio.ensure_future(coro)
        self.pushes[task] = None
        task.add_done_callback(lambda done: self.pushes.pop(done, None))
        return task

    async def push(self, holder: Holder, module: str, changes: Sequence[Delta] | WrittenState,
                   made: MadeUnder | None = None) -> bool:
        """Send ``changes`` to ``holder``; ``made``: the id of the client's
        write they come from, so that a try of it sent there next is a repeat."""
        replica = self.live.replicas[module]
        message = SyncMessage(module, replica.context.copy(), changes, forward=holder.remote, made=made)
        answer = await self.exchange(holder, message)
        if answer is None:
            self.stats.push_failed += 1
            return False
        self.stats.pushed += 1
        return True

    async def exchange(self, holder: Holder, message: SyncMessage) -> SyncMessage | None:
        """Send ``message`` to ``holder`` and take in its answer; None if
        there is none to take (unreachable, refused, malformed, not allowed)."""
        if self.fence.own is not None:
            message = dataclasses.replace(message, life=self.fence.own)
        request = Request(
            Method.POST, SYNC_PATH, payload=encode_sync(message), content_format=ContentFormat.CBOR,
            accept=ContentFormat.CBOR,
        )
        try:
            response = await self.client.request(holder.endpoint, request, timeout=self.settings.request_timeout_s)
        except TransportError as exc:
            log.debug("sync with %s failed: %s", holder.name, exc)
            return None
        if response.status != Status.CHANGED:
            self.log_once(holder.name, message.module, response.status, "%s refused a sync of %s: %s %s",
                          holder.name, message.module, response.status.dotted, response.text())
            return None
        try:
            answer = decode_sync(response.payload)
        except CodecError as exc:
            log.warning("%s answered a malformed sync message: %s", holder.name, exc)
            return None
        if answer.module != message.module:
            return None
        # The answer comes from the holder asked (the client's security checks who answers).
        refusal = self.access.refusal(answer, holder.name)
        if refusal is not None:
            self.stats.forbidden += 1
            self.log_once(holder.name, message.module, Status.FORBIDDEN, "not taking %s's answer on %s: %s",
                          holder.name, message.module, refusal)
            return None
        self.known[(message.module, holder.name)] = answer.context
        self.fence.learn(message.module, answer.lives)
        self.take(answer)
        return answer

    def take(self, message: SyncMessage) -> None:
        """The changes a sync message carries (an answer's or a request's), into the KB."""
        if isinstance(message.changes, WrittenState):
            self.stats.states_in += 1
            self.live.join(message.module, message.changes)
        elif message.changes:
            self.stats.deltas_in += len(message.changes)
            # The holder that made a client's write is its delta's writer.
            made_by = writer_robot(message.changes[0].dot.writer)
            self.live.apply(message.module, message.changes, message.made, made_by)

    def fit(self, deltas: list[Delta]) -> list[Delta]:
        """The first deltas up to the answer bound (at least one): the rest
        follows at the next exchange, the join being order-free."""
        budget = self.settings.max_answer_bytes
        kept: list[Delta] = []
        for delta in deltas:
            budget -= 64 + 48 * delta.size  # a safe over-estimate of its encoding
            if kept and budget < 0:
                break
            kept.append(delta)
        return kept
