"""The incoming side of replication: ``/kb/sync``, where the other holders
of this robot's modules push their changes and ask for what they lack.

A message is taken only from a sender :mod:`.sync_access` allows, and
not from a robot's life that has ended (:mod:`.life_fence`; else 4.03);
its changes go into the KB, a forwarded push's new deltas are passed on
to the holders this robot knows, and the answer carries this robot's
context and what the sender's lacks, up to the answer bound (and, to a
question, the lives of the module's holders).
Changes the replica does not take at its bound are answered 5.03 with
Max-Age, never 2.04.  Overview: :mod:`.replication`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

from ..model.deltas import CausalContext, Delta
from ..transport.base import ResourceInfo
from ..transport.messages import ContentFormat, Request, Response, Status
from ..transport.router import Router
from ..wire.codec import CodecError
from ..wire.sync import Life, SyncMessage, decode_sync, encode_sync
from .live import LiveKB
from .replication_settings import SYNC_PATH, Holder, ReplicationSettings, ReplicationStats
from .sync_access import SyncAccess
from .sync_client import SyncClient

__all__ = ["SyncHandler"]


class SyncHandler:
    """Answers the holders' sync messages (see the module docstring);
    ``holders``: module -> the holders a new delta is passed on to;
    ``catching_up``: whether the catch-up at start is still running."""

    def __init__(self, live: LiveKB, holders: dict[str, list[Holder]], access: SyncAccess,
                 outgoing: SyncClient, settings: ReplicationSettings, stats: ReplicationStats,
                 catching_up: Callable[[], bool]) -> None:
        self.live = live
        self.holders = holders
        self.access = access
        self.fence = outgoing.fence
        self.catching_up = catching_up
        self.outgoing = outgoing
        self.settings = settings
        self.stats = stats

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
            self.stats.malformed += 1
            return Response.error(Status.BAD_REQUEST, f"malformed sync message: {exc}")
        module = message.module
        if module not in self.live.replicas:
            return Response.error(Status.NOT_FOUND, f"this robot does not hold the {module} module")
        refusal = self.access.refusal(message, request.peer)
        if refusal is not None:
            self.stats.forbidden += 1
            self.outgoing.log_once(request.peer or "an unprotected sender", module, Status.FORBIDDEN,
                                   "refused a sync of %s from %s: %s", module, request.peer, refusal)
            return Response.error(Status.FORBIDDEN, refusal)
        if message.life is not None:
            not_taken = self._refuse_life(message.life, message, request.peer)
            if not_taken is not None:
                return not_taken
            # Raised before the answer is made: the life that asks reads
            # every dot of its robot's earlier lives this robot will take.
            self.fence.raise_to(message.life)
        replica = self.live.replicas[module]
        refused = replica.refused
        new = self._new(message)
        self.outgoing.take(message)
        # Passed on only once taken here: a delta refused at the bound comes again at catch-up.
        fresh = [d for d in new if d.dot in replica.context]
        if fresh:
            for holder in self.holders[module]:
                self.outgoing.spawn(self.outgoing.push(holder, module, fresh, message.made))
        if request.peer is not None and self.access.holds(request.peer, module):
            self.outgoing.known[(module, request.peer)] = message.context
        if replica.refused > refused:
            # Not 2.04: a push's sender would count the write as held here.
            # The gap fills at the next exchanges; the rest may come then.
            self.stats.not_taken += replica.refused - refused
            return Response.error(
                Status.SERVICE_UNAVAILABLE,
                f"{replica.refused - refused} of the changes not taken: this robot waits for "
                f"{replica.gaps()} missing writes (at most {replica.limits.cloud_max}); it catches up first",
                max_age=self._next_round_s(),
            )
        answer = self._answer_for(module, message.context)
        if message.changes is None:
            # The lives of the module's holders: the asker's own, and those
            # whose ended lives it must refuse once started again.
            answer = dataclasses.replace(answer, lives={
                robot: number for robot, number in self.fence.lives.items()
                if self.access.holds(robot, module) is not False})
        return Response(Status.CHANGED, encode_sync(answer), ContentFormat.CBOR)

    def _refuse_life(self, life: Life, message: SyncMessage, peer: str | None) -> Response | None:
        """The answer to ``message``, from ``life``, if it is not taken; None if it is."""
        refusal = self.fence.refusal(life)
        if peer is not None and life.robot != peer:
            refusal = f"{peer} sent a sync as a life of {life.robot}"
        if refusal is not None:
            self.stats.forbidden += 1
            self.outgoing.log_once(life.robot, message.module, Status.FORBIDDEN,
                                   "refused a sync of %s: %s", message.module, refusal)
            return Response.error(Status.FORBIDDEN, refusal)
        if message.changes is not None and message.module not in self.fence.told and self.catching_up():
            # Started again, this robot may not know the fence yet: the
            # catch-up's answers carry it, and the changes come again.  Not
            # once one answer told it: at a team's start every holder
            # catches up at once, and a write refused by all of them failed.
            return Response.error(
                Status.SERVICE_UNAVAILABLE, "this robot is catching up: it takes a robot's life's changes after",
                max_age=self._next_round_s())
        return None

    def _next_round_s(self) -> int:
        """Max-Age of changes refused for now: the anti-entropy period, when
        they come again by this robot's own exchanges."""
        return max(1, math.ceil(self.settings.sync_every_s))

    def _new(self, message: SyncMessage) -> list[Delta]:
        """The deltas of a forwarded push that are new here: to pass on (once taken)."""
        if not message.forward or not isinstance(message.changes, list):
            return []
        context = self.live.replicas[message.module].context
        return [d for d in message.changes if d.dot not in context]

    def _answer_for(self, module: str, peer: CausalContext) -> SyncMessage:
        replica = self.live.replicas[module]
        missing = replica.missing_for(peer)
        if isinstance(missing, list):
            missing = self.outgoing.fit(missing)
        return SyncMessage(module, replica.context.copy(), missing or None)
