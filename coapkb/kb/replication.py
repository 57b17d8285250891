"""Keeps every holder of a module in step: pushes each write, and walks
the holders for what anyone missed (anti-entropy).

It speaks only the transport interface (a request to ``/kb/sync`` on a
peer), so it runs over every transport and under its security.

* **Push.**  A local write's delta goes to every holder of the module this
  robot knows (its cluster's holders and its peers in other clusters) at
  once.  The write is answered once as many of them have it as the writer
  asked (its write concern, :mod:`.write_concern`): by default one, so an
  acknowledged write lives on two robots.  A holder in another cluster passes a
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
* **Who may replicate.**  A sync carrying changes of a module is taken only
  from a robot known to hold that module (the security layer authenticated
  it: :attr:`Request.peer`), and only if every writer it names is an
  incarnation of such a robot; else 4.03 and nothing changes.  A question
  (a context alone) is a read, answered to any robot not known to lack the
  module.  A writer ``Robot1.<boot>`` is robot ``Robot1``'s incarnation.
  Without ``team`` (every holder of each module) a robot knows the holders
  its configuration names (its cluster's, its replicas); a writer of another
  cluster is then taken on the word of the holder that sends it.  An
  unprotected sender (``peer`` None) is not checked: there is nobody to
  check; writers known not to hold the module are still refused.
  (``docs/knowledge.md`` section 7, ``docs/security.md``.)
* **Refused at the bound.**  A delta the replica does not take (its dots past
  a gap would pass ``cloud_max``) is answered 5.03 with Max-Age, never 2.04:
  the sender must not count it as held here; it comes again at catch-up.

Messages: :mod:`coapkb.wire.sync`.  Model: :mod:`.replica`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import random
from collections.abc import Collection, Coroutine, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .. import clock
from ..model.deltas import CausalContext, Delta, MadeUnder, WrittenState
from ..transport.base import ClientTransport, Endpoint, ResourceInfo, TransportError
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.router import Router
from ..wire.codec import CodecError
from ..wire.sync import SyncMessage, decode_sync, encode_sync
from .live import LiveKB, Written
from .sync_access import SyncAccess, writer_robot
from .write_concern import DEFAULT_ACK, Ack, Reached

__all__ = ["SYNC_PATH", "Holder", "Replicator", "ReplicationSettings", "writer_robot"]

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
    #: How long a read waits, after a start, for the catch-up with every
    #: holder before it is answered anyway: a holder that answered at once
    #: would answer without the writes it missed while it was down (the
    #: catch-up takes one exchange, a round trip, unless holders are down).
    read_after_catch_up_s: float = 3.0
    #: Bytes of changes one answer carries at most (four CoAP blocks: on a
    #: lossy link a short exchange that times out wastes little); the rest
    #: follows at once, in the next exchange.
    max_answer_bytes: int = 4096

    def __post_init__(self) -> None:
        for name in ("sync_every_s", "request_timeout_s", "ack_timeout_s", "read_after_catch_up_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass
class ReplicationStats:
    """What one robot's replication did, counted since it started."""

    #: Pushes of new writes sent to a holder, and those that failed.
    pushed: int = 0
    push_failed: int = 0
    #: Anti-entropy rounds run.
    rounds: int = 0
    #: Deltas and whole states taken from holders.
    deltas_in: int = 0
    states_in: int = 0
    #: Sync messages refused: not decodable, from a sender not allowed, or
    #: deltas not taken at the replica's bound (they come again at catch-up).
    malformed: int = 0
    forbidden: int = 0
    not_taken: int = 0


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
        team: Mapping[str, Collection[str]] | None = None,
    ) -> None:
        """``team``: every robot holding each module, across the team; a
        robot it does not list holds nothing.  None: the holders ``live``
        and ``holders`` name (see the module docstring)."""
        self.live = live
        self.client = client
        self.settings = settings or ReplicationSettings()
        # Seeded by the writer when not given: runs repeat, and robots' rounds still differ.
        self._rng = rng or random.Random(live.writer)
        self.holders: dict[str, list[Holder]] = {
            module: [h for h in holders if module in h.modules] for module in live.names
        }
        me = writer_robot(live.writer)
        #: Who may replicate which module (:mod:`.sync_access`).
        self.access = SyncAccess(
            me,
            {module: frozenset(team.get(module, ())) if team is not None
             else frozenset(live.holders.get(module, ())) | {h.name for h in self.holders[module]}
             for module in live.names},
            frozenset({me, *(h.name for h in holders), *(r for robots in live.holders.values() for r in robots)}),
            listed=team is not None,
        )
        #: (sender or holder, module, status) already logged at warning level.
        self._warned: set[tuple[str, str, int]] = set()
        #: (module, holder) -> the last context it told us
        self.known: dict[tuple[str, str], CausalContext] = {}
        #: :attr:`known` as it was at the last anti-entropy round (what compaction goes by).
        self._known_then: dict[tuple[str, str], CausalContext] = {}
        self._turn = 0
        #: Set once the catch-up at start has asked every holder (or there is none).
        self._caught_up = asyncio.Event()
        self._started_at: float | None = None
        self._task: asyncio.Task[None] | None = None
        #: The pushes in flight, in the order they started (a dict: a set's order
        #: follows id(), and aclose cancels them in this order).
        self._pushes: dict[asyncio.Task[bool], None] = {}
        self.stats = ReplicationStats()

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
            self.stats.malformed += 1
            return Response.error(Status.BAD_REQUEST, f"malformed sync message: {exc}")
        module = message.module
        if module not in self.live.replicas:
            return Response.error(Status.NOT_FOUND, f"this robot does not hold the {module} module")
        refusal = self.access.refusal(message, request.peer)
        if refusal is not None:
            self.stats.forbidden += 1
            self._log_once(request.peer or "an unprotected sender", module, Status.FORBIDDEN,
                           "refused a sync of %s from %s: %s", module, request.peer, refusal)
            return Response.error(Status.FORBIDDEN, refusal)
        replica = self.live.replicas[module]
        refused = replica.refused
        new = self._new(message)
        self._take(message)
        # Passed on only once taken here: a delta refused at the bound comes again at catch-up.
        fresh = [d for d in new if d.dot in replica.context]
        if fresh:
            for holder in self.holders[module]:
                self._spawn(self._push(holder, module, fresh, message.made))
        if request.peer is not None and self.access.holds(request.peer, module):
            self.known[(module, request.peer)] = message.context
        if replica.refused > refused:
            # Not 2.04: a push's sender would count the write as held here.
            # The gap fills at the next exchanges; the rest may come then.
            self.stats.not_taken += replica.refused - refused
            return Response.error(
                Status.SERVICE_UNAVAILABLE,
                f"{replica.refused - refused} of the changes not taken: this robot waits for "
                f"{replica.gaps()} missing writes (at most {replica.limits.cloud_max}); it catches up first",
                max_age=max(1, math.ceil(self.settings.sync_every_s)),
            )
        answer = self._answer_for(module, message.context)
        return Response(Status.CHANGED, encode_sync(answer), ContentFormat.CBOR)

    # ------------------------------------------------------- who replicates

    def _log_once(self, who: str, module: str, status: Status, text: str, *args: object) -> None:
        """A warning the first time, debug after: a misconfigured peer is
        said once, not at every round."""
        key = (who, module, int(status))
        level = logging.DEBUG if key in self._warned else logging.WARNING
        self._warned.add(key)
        log.log(level, text, *args)

    def _new(self, message: SyncMessage) -> list[Delta]:
        """The deltas of a forwarded push that are new here: to pass on (once taken)."""
        if not message.forward or not isinstance(message.changes, list):
            return []
        context = self.live.replicas[message.module].context
        return [d for d in message.changes if d.dot not in context]

    def _take(self, message: SyncMessage) -> None:
        if isinstance(message.changes, WrittenState):
            self.stats.states_in += 1
            self.live.join(message.module, message.changes)
        elif message.changes:
            self.stats.deltas_in += len(message.changes)
            # The holder that made a client's write is its delta's writer.
            made_by = writer_robot(message.changes[0].dot.writer)
            self.live.apply(message.module, message.changes, message.made, made_by)

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
        """Push a local write to the holders of its modules; how many other
        holders had it when it returned: at the first acknowledgement of
        every module, or at the ack timeout (:meth:`acknowledge` at ``2``)."""
        return (await self.acknowledge(written, Ack.TWO)).holders - 1

    async def acknowledge(self, written: Written, ack: Ack = DEFAULT_ACK) -> Reached:
        """Push a local write to every holder of the modules it changed, and
        wait until it reached ``ack`` (:mod:`.write_concern`), every push
        ended or the ack timeout passed; how far it reached then.

        ``local`` waits for nothing.  ``2`` is reached when one other holder
        of every module changed confirmed it (a module with no other holder
        needs none), ``all`` when every holder pushed to did.  The pushes
        not waited for go on."""
        wanted = {module: frozenset(h.name for h in self.holders[module]) for module in written.deltas}
        made = written.made
        pushes = {
            self._spawn(self._push(holder, module, [delta], made)): (module, holder.name)
            for module, delta in written.deltas.items()
            for holder in self.holders[module]
        }
        confirmed: dict[str, set[str]] = {module: set() for module in wanted}
        failed: set[str] = set()
        reached = _reached(wanted, confirmed, failed)
        pending = set(pushes)
        if ack == Ack.LOCAL:
            return reached
        try:
            async with asyncio.timeout(self.settings.ack_timeout_s):
                while pending and not reached.level.covers(ack):
                    done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                    for task in done:
                        module, name = pushes[task]
                        if not task.cancelled() and task.exception() is None and task.result():
                            confirmed[module].add(name)
                        else:
                            failed.add(name)
                    reached = _reached(wanted, confirmed, failed)
        except TimeoutError:
            pass
        return reached

    def _spawn(self, coro: Coroutine[Any, Any, bool]) -> asyncio.Task[bool]:
        task = asyncio.ensure_future(coro)
        self._pushes[task] = None
        task.add_done_callback(lambda done: self._pushes.pop(done, None))
        return task

    async def _push(self, holder: Holder, module: str, changes: Sequence[Delta] | WrittenState,
                    made: MadeUnder | None = None) -> bool:
        """Send ``changes`` to ``holder``; ``made``: the id of the client's
        write they come from, so that a try of it sent there next is a repeat."""
        replica = self.live.replicas[module]
        message = SyncMessage(module, replica.context.copy(), changes, forward=holder.remote, made=made)
        answer = await self._exchange(holder, message)
        if answer is None:
            self.stats.push_failed += 1
            return False
        self.stats.pushed += 1
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
            self._log_once(holder.name, message.module, response.status, "%s refused a sync of %s: %s %s",
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
            self._log_once(holder.name, message.module, Status.FORBIDDEN, "not taking %s's answer on %s: %s",
                           holder.name, message.module, refusal)
            return None
        self.known[(message.module, holder.name)] = answer.context
        self._take(answer)
        return answer

    def compact(self) -> None:
        """Forget the deltas every holder had a round ago (each anti-entropy
        round ends with this).  Not by the contexts just heard: a holder's
        message sent before its latest (a push overtaken by the next, a
        question held up by retransmissions) asks with an older context,
        and a delta forgotten meanwhile made the answer a whole state
        (100 kB and more, several a minute, found on a long shift)."""
        for module, holders in self.holders.items():
            contexts = [self._known_then.get((module, h.name)) for h in holders]
            if holders and all(c is not None for c in contexts):
                self.live.replicas[module].compact(c for c in contexts if c is not None)
        self._known_then = dict(self.known)

    # -------------------------------------------------------- anti-entropy

    def start(self) -> None:
        self._started_at = clock.monotonic()
        if any(self.holders.values()):
            self._task = asyncio.ensure_future(self._rounds())
        else:
            self._caught_up.set()

    async def caught_up(self) -> None:
        """Until the catch-up at start has asked every holder, at most
        :attr:`ReplicationSettings.read_after_catch_up_s` after it began."""
        if self._caught_up.is_set() or self._started_at is None:
            return
        left = self._started_at + self.settings.read_after_catch_up_s - clock.monotonic()
        if left > 0:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._caught_up.wait(), left)

    async def _rounds(self) -> None:
        # A robot that starts (again) has missed everything: it catches up
        # from every holder at once, not at its first round.
        try:
            await self.catch_up()
        finally:
            self._caught_up.set()
        period = self.settings.sync_every_s
        while True:
            await asyncio.sleep(period * self._rng.uniform(2 / 3, 4 / 3))
            await self.sync_once()
            self.compact()

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
        self.stats.rounds += 1
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



def _reached(wanted: Mapping[str, frozenset[str]], confirmed: Mapping[str, set[str]],
             failed: Collection[str] = ()) -> Reached:
    """How far a write reached: ``wanted`` the other holders of each module
    it changed, ``confirmed`` those whose push was answered 2.04, ``failed``
    those a push to failed."""
    if not wanted:
        return Reached(Ack.ALL, changed=False)
    if all(confirmed[m] >= holders for m, holders in wanted.items()):
        level = Ack.ALL
    elif all(confirmed[m] or not holders for m, holders in wanted.items()):
        level = Ack.TWO
    else:
        level = Ack.LOCAL
    robots = frozenset().union(*wanted.values())
    # A robot holding several of the modules has the write once it confirmed each.
    holding = {r for r in robots if all(r in confirmed[m] for m, holders in wanted.items() if r in holders)}
    lacking = robots - holding
    return Reached(level, 1 + len(holding), 1 + len(robots), tuple(sorted(lacking - set(failed))),
                   tuple(sorted(lacking & set(failed))))
