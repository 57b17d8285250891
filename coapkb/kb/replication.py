"""Keeps every holder of a module in step: pushes each write, and walks
the holders for what anyone missed (anti-entropy).

It speaks only the transport interface (a request to ``/kb/sync`` on a
peer), so it runs over every transport and under its security.

* **Push.**  A local write's delta goes to every holder of the module this
  robot knows (its cluster's holders and its peers in other clusters) at
  once.  The write is answered once one of them has it: an acknowledged
  write then lives on two robots.  A holder in another cluster passes a
  delta new to it on to the holders it knows (its cluster, and the next
  cluster), so a write crosses the team cluster by cluster, each robot
  sending it at most once to each holder it knows.
* **Anti-entropy.**  Every ``sync_every_s`` (with jitter) the robot sends
  one holder its causal context, round robin; the holder answers with the
  deltas the context lacks (from its journal) or, when its journal no
  longer has them, its whole written state, and with its own context.  The
  exchange goes both ways: what the holder lacks of this robot's is pushed
  right after.  What it costs grows with what was missed, not with the KB.
* **Compaction.**  A delta every peer's last known context holds leaves the
  journal.

Messages: :mod:`coapkb.wire.sync`.  Model: :mod:`.replica`.
"""

from __future__ import annotations

import asyncio
import logging
import random
from collections.abc import Coroutine, Sequence
from dataclasses import dataclass
from typing import Any

from ..transport.base import ClientTransport, Endpoint, ResourceInfo, TransportError
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.router import Router
from ..wire.codec import CodecError
from ..wire.sync import SyncMessage, decode_sync, encode_sync
from .live import LiveKB, Written
from .replica import CausalContext, Delta, WrittenState

__all__ = ["SYNC_PATH", "Holder", "Replicator", "ReplicationSettings"]

SYNC_PATH = "/kb/sync"
#: Exchanges one catch-up may chain while the holder has more to send.
MAX_FOLLOW_UPS = 1000

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Holder:
    """Another robot holding some of this robot's modules."""

    name: str
    endpoint: Endpoint
    modules: tuple[str, ...]
    #: In another cluster: a write pushed to it is passed on there.
    remote: bool = False


@dataclass(frozen=True)
class ReplicationSettings:
    #: Seconds between two anti-entropy rounds (each with one holder), jittered by a third.
    sync_every_s: float = 5.0
    #: How long a push or an exchange may take (the transport retransmits within it).
    request_timeout_s: float = 10.0
    #: How long a write waits for a second holder before it is answered anyway.
    ack_timeout_s: float = 10.0
    #: Bytes of changes one answer carries at most (four CoAP blocks: on a
    #: lossy link a short exchange that times out wastes little); the rest
    #: follows at once, in the next exchange.
    max_answer_bytes: int = 4096

    def __post_init__(self) -> None:
        for name in ("sync_every_s", "request_timeout_s", "ack_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


class Replicator:
    """One robot's side of replication (see the module docstring)."""

    def __init__(
        self,
        live: LiveKB,
        client: ClientTransport,
        holders: Sequence[Holder],
        *,
        settings: ReplicationSettings | None = None,
        rng: random.Random | None = None,
    ) -> None:
        self.live = live
        self.client = client
        self.settings = settings or ReplicationSettings()
        self._rng = rng or random.Random()
        self.holders: dict[str, list[Holder]] = {
            module: [h for h in holders if module in h.modules] for module in live.names
        }
        #: (module, holder) -> the last context it told us
        self.known: dict[tuple[str, str], CausalContext] = {}
        self._turn = 0
        self._task: asyncio.Task[None] | None = None
        self._pushes: set[asyncio.Task[bool]] = set()
        self.stats = {"pushed": 0, "push_failed": 0, "rounds": 0, "deltas_in": 0, "states_in": 0, "malformed": 0}

    # -------------------------------------------------------------- serving

    def mount(self, router: Router) -> None:
        router.add(
            ResourceInfo(SYNC_PATH, rt="coapkb.sync", ct=(int(ContentFormat.CBOR),), methods=("POST",),
                         title="replication between a module's holders"),
            self.handle_sync,
        )

    async def handle_sync(self, request: Request) -> Response:
        if request.content_format not in (None, ContentFormat.CBOR):
            return Response.error(Status.UNSUPPORTED_CONTENT_FORMAT, "a sync message is CBOR (content-format 60)")
        try:
            message = decode_sync(request.payload)
        except CodecError as exc:
            self.stats["malformed"] += 1
            return Response.error(Status.BAD_REQUEST, f"malformed sync message: {exc}")
        if message.module not in self.live.replicas:
            return Response.error(Status.NOT_FOUND, f"this robot does not hold the {message.module} module")
        fresh = self._fresh(message)
        self._take(message)
        if fresh:
            for holder in self.holders[message.module]:
                self._spawn(self._push(holder, message.module, fresh))
        if request.peer is not None:
            self.known[(message.module, request.peer)] = message.context
        answer = self._answer_for(message.module, message.context)
        return Response(Status.CHANGED, encode_sync(answer), ContentFormat.CBOR)

    def _fresh(self, message: SyncMessage) -> list[Delta]:
        """The deltas of a forwarded push that are new here: to pass on."""
        if not message.forward or not isinstance(message.changes, list):
            return []
        context = self.live.replicas[message.module].context
        return [d for d in message.changes if d.dot not in context]

    def _take(self, message: SyncMessage) -> None:
        if isinstance(message.changes, WrittenState):
            self.stats["states_in"] += 1
            self.live.join(message.module, message.changes)
        elif message.changes:
            self.stats["deltas_in"] += len(message.changes)
            self.live.apply(message.module, message.changes)

    def _answer_for(self, module: str, peer: CausalContext) -> SyncMessage:
        replica = self.live.replicas[module]
        missing = replica.missing_for(peer)
        if isinstance(missing, list):
            missing = self._fit(missing)
        return SyncMessage(module, replica.context.copy(), missing or None)

    def _fit(self, deltas: list[Delta]) -> list[Delta]:
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

    # -------------------------------------------------------------- writing

    async def replicate(self, written: Written) -> int:
        """Push a local write to the holders of its modules; how many had it
        before the ack timeout (the number of robots it lives on, minus one).

        Returns at the first acknowledgement; the other pushes go on."""
        pushes = [
            self._spawn(self._push(holder, module, [delta]))
            for module, delta in written.deltas.items()
            for holder in self.holders[module]
        ]
        if not pushes:
            return 0
        acked = 0
        try:
            async with asyncio.timeout(self.settings.ack_timeout_s):
                for done in asyncio.as_completed(pushes):
                    if await done:
                        acked += 1
                        break
        except TimeoutError:
            pass
        return acked

    def _spawn(self, coro: Coroutine[Any, Any, bool]) -> asyncio.Task[bool]:
        task = asyncio.ensure_future(coro)
        self._pushes.add(task)
        task.add_done_callback(self._pushes.discard)
        return task

    async def _push(self, holder: Holder, module: str, changes: Sequence[Delta] | WrittenState) -> bool:
        replica = self.live.replicas[module]
        message = SyncMessage(module, replica.context.copy(), changes, forward=holder.remote)
        answer = await self._exchange(holder, message)
        if answer is None:
            self.stats["push_failed"] += 1
            return False
        self.stats["pushed"] += 1
        return True

    async def _exchange(self, holder: Holder, message: SyncMessage) -> SyncMessage | None:
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
            log.warning("%s refused a sync of %s: %s %s", holder.name, message.module, response.status.dotted,
                        response.text())
            return None
        try:
            answer = decode_sync(response.payload)
        except CodecError as exc:
            log.warning("%s answered a malformed sync message: %s", holder.name, exc)
            return None
        if answer.module != message.module:
            return None
        self.known[(message.module, holder.name)] = answer.context
        self._take(answer)
        self._compact(message.module)
        return answer

    def _compact(self, module: str) -> None:
        holders = self.holders[module]
        contexts = [self.known.get((module, h.name)) for h in holders]
        if holders and all(c is not None for c in contexts):
            self.live.replicas[module].compact(c for c in contexts if c is not None)

    # -------------------------------------------------------- anti-entropy

    def start(self) -> None:
        if any(self.holders.values()):
            self._task = asyncio.ensure_future(self._rounds())

    async def _rounds(self) -> None:
        # A robot that starts (again) has missed everything: it catches up
        # from every holder at once, not at its first round.
        await self.catch_up()
        period = self.settings.sync_every_s
        while True:
            await asyncio.sleep(period * self._rng.uniform(2 / 3, 4 / 3))
            await self.sync_once()

    async def catch_up(self) -> None:
        """One exchange with every holder of every module: the modules at
        once, their holders one after another (the first sends what was
        missed, the next only what the first lacked: asked all at once,
        each sent it all)."""

        async def module(name: str, holders: list[Holder]) -> None:
            for holder in holders:
                await self._sync_with(holder, name)

        await asyncio.gather(*(module(name, holders) for name, holders in self.holders.items()))

    async def sync_once(self) -> None:
        """One anti-entropy exchange per module, with its next holder."""
        self.stats["rounds"] += 1
        self._turn += 1
        for module, holders in self.holders.items():
            if not holders:
                continue
            await self._sync_with(holders[self._turn % len(holders)], module)

    async def _sync_with(self, holder: Holder, module: str) -> None:
        replica = self.live.replicas[module]
        answer = await self._exchange(holder, SyncMessage(module, replica.context.copy()))
        # An answer holds at most max_answer_bytes of changes: ask again at
        # once while the holder has more (it said so with its context).
        for _ in range(MAX_FOLLOW_UPS):
            if answer is None or replica.context.covers(answer.context):
                break
            answer = await self._exchange(holder, SyncMessage(module, replica.context.copy()))
        if answer is None:
            return
        # Both ways: what the holder lacks of ours, pushed now.
        theirs = replica.missing_for(answer.context)
        if theirs:
            await self._push(holder, module, self._fit(theirs) if isinstance(theirs, list) else theirs)

    async def aclose(self) -> None:
        tasks = [t for t in (self._task, *self._pushes) if t is not None]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

