"""One running robot: its KB, server, client and the workflow modules, wired.

Resources (besides the KB's ``/kb``, ``/kb/sparql``, ``/kb/q/*``):

=================  ======  ==================================================
``/robot/state``   GET     live and planned state, last decision; observable (RFC 7641)
``/robot/plan``    GET     planned state only, for teammates; observable
``/robot/plan``    POST    ``?of=X&at=S``: compare notes on teammate X's plan after task S
``/robot/outcome`` GET     what the feeder acts on: decisions, jobs done or dropped, idle; observable
``/tasks``         POST    a new task ``{"seq": n, "object": name}`` (CBOR/JSON; :mod:`coapkb.feeder.tasks`)
``/tasks``         GET     the decisions taken so far
``/decisions``     POST    the leader's decision ("compute and communicate")
``/robot/stats``   GET     traffic counters and query statistics
``/robot/lease``   GET     ``?r=X[&check]``: does this robot grant teammate X a lease (the fence)
=================  ======  ==================================================
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, replace
from typing import TYPE_CHECKING, Any

import cbor2

from .. import clock
from ..config import KB_MODULES, ConfigError, RobotConfig
from ..errors import CoapkbError
from ..host import Host, operating_system
from ..kb.client import KBClient, QueryFailed, WriteShort
from ..kb.durable import Keeper, open_live
from ..kb.live import LiveKB
from ..kb.named_updates import NamedUpdate, named_updates_sparql
from ..kb.replication import Holder, Replicator
from ..kb.resources import KBResources
from ..kb.store import KnowledgeBase, named_rows
from ..security import AccessPolicy, TeamIdentity, load_identity, mechanism_for, server_security
from ..transport import ClientSecurity, reliability_for
from ..transport.base import ClientTransport, ResourceInfo, ServerTransport, TransportError
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.router import Router
from ..world import Position, layout_from_row
from ..world.service import WorldClient
from .controller import Controller
from .decisions import CLAIMS_PATH, Claim, DecisionMessage, Task, decode_claims, encode_claims
from .knowledge_writer import KnowledgeWriter
from .lease import LEASE_PATH, Lease
from .local_health import LoopHealth
from .progress import ProgressPacing, acted_on
from .query_handler import QueryError, QueryHandler
from .robot_state import LiveState, PlannedState, RobotState
from .stats import RobotStats
from .task_assigner import robot_sort_key
from .task_executor import TaskExecutor
from .team_view import OUTCOME_PATH, PLAN_PATH, STATE_PATH, TeamView

if TYPE_CHECKING:  # discovery is imported only when a robot uses it
    from ..discovery.client import DirectoryClient

OBJECT_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,127}$")


def _decode_body(request: Request) -> Any:
    """A CBOR (default) or JSON request body."""
    if request.content_format == ContentFormat.JSON:
        return json.loads(request.payload)
    return cbor2.loads(request.payload)


def _encode(value: Any, accept: int | None) -> Response:
    if accept == ContentFormat.JSON:
        return Response(Status.CONTENT, json.dumps(value).encode(), ContentFormat.JSON)
    if accept not in (None, ContentFormat.CBOR):
        return Response.error(Status.NOT_ACCEPTABLE, "use content-format 60 (cbor) or 50 (json)")
    return Response(Status.CONTENT, cbor2.dumps(value), ContentFormat.CBOR)


def _cbor_state(payload: bytes, accept: int | None) -> Response:
    if accept not in (None, ContentFormat.CBOR):
        return Response.error(Status.NOT_ACCEPTABLE, "use content-format 60 (cbor) or 50 (json)")
    return Response(Status.CONTENT, payload, ContentFormat.CBOR)


def check_start(config: RobotConfig, kb: KnowledgeBase | None) -> None:
    """Refuse a start position outside the warehouse, checked against the
    Location KB's geometry when this robot holds that KB (without it the
    geometry is a teammate's to tell, at the first task; configuration
    loading already refuses aisle 0 and negative racks)."""
    if kb is None:
        return
    rows = named_rows(kb, "warehouse-layout")
    if not rows:
        return  # not the Location KB
    layout = layout_from_row(rows[0])
    start = Position(config.start.aisle, config.start.rack)
    if not layout.contains(start):
        raise ConfigError(
            f"start: aisle {start.aisle}, rack {start.rack} is outside the warehouse "
            f"(aisles 1..{layout.aisles}, racks 0..{layout.racks_per_aisle + 1} in the Location KB)"
        )


async def write_knowledge(
    config: RobotConfig, served: KnowledgeBase | LiveKB | None, replicator: Replicator | None, kb_client: KBClient,
    module: str, update: Sequence[NamedUpdate], alive: Callable[[str], bool], write_id: str | None = None,
) -> None:
    """Write ``update`` (facts of KB ``module``): into this robot's own
    module if it holds it, passed on to the other holders; else to the first
    live holder in robot-id order (another if it fails), under ``write_id``
    (each try of one write the same id: a holder makes it once).  A holder
    that answers 5.04 has made the write, which spreads from it: not sent to
    another (it would be written twice)."""
    if isinstance(served, LiveKB) and module in served.names:
        written = served.update(named_updates_sparql(update))
        if replicator is not None and written.deltas:
            await replicator.replicate(written)
        return
    holders = sorted((m for m in config.holders_of(module) if m.robot_id != config.robot_id),
                     key=lambda m: (not alive(m.robot_id), robot_sort_key(m.robot_id)))
    if not holders:
        raise QueryError(f"no teammate holds the {module} KB")
    failure: CoapkbError | None = None
    for holder in holders:
        try:
            await kb_client.update(holder.endpoint, update, timeout=config.query_timeout_s, write_id=write_id)
            return
        except WriteShort:
            return
        except (QueryFailed, TransportError) as exc:
            failure = exc
    assert failure is not None
    raise failure


def module_holders(config: RobotConfig, modules: Iterable[str]) -> list[Holder]:
    """The other robots holding any of ``modules``: teammates, then the
    holders in other clusters (``replicas``)."""
    held = set(modules)
    mates = [(m, False) for m in config.team.values() if m.robot_id != config.robot_id]
    mates += [(m, True) for m in config.replicas.values()]
    return [Holder(m.robot_id, m.endpoint, tuple(k for k in m.kbs if k in held), remote)
            for m, remote in mates if held & set(m.kbs)]


#: How long one snapshot of a robot's statistics is served (``/robot/stats``).
STATS_SNAPSHOT_S = 5.0
#: Tries to deliver the leader's decision to a follower ("compute and communicate"),
#: each within the query timeout: together under the follower's patience (4 of them).
DECISION_SENDS = 3
#: Task posts whose repeat a robot recognises (sequence numbers are consecutive).
POSTS_REMEMBERED = 64


class FinalOutcome:
    """Which ``/robot/outcome`` is final: the robot went idle with nothing
    queued, and has decided nothing since.  Its notification goes confirmed
    (``Response.confirm``): the feeder waits for it at the end of a run, and
    no later change would make up for its loss; the others go unconfirmed,
    each awaited by a feeder that asks again when one is late."""

    def __init__(self) -> None:
        #: (jobs done, last task decided) when the robot last went idle.
        self._at: tuple[int, int] | None = None

    @staticmethod
    def _key(state: RobotState) -> tuple[int, int]:
        return state.live.done, state.last.seq if state.last is not None else 0

    def on_live(self, before: LiveState, state: RobotState) -> None:
        live = state.live
        if before.activity != "idle" and live.activity == "idle" and not live.queued:
            self._at = self._key(state)

    def __call__(self, state: RobotState) -> bool:
        return self._at is not None and self._at == self._key(state) and state.live.activity == "idle"


class Robot:
    def __init__(
        self,
        config: RobotConfig,
        kb: KnowledgeBase | None,
        client: ClientTransport,
        router: Router,
        controller: Controller,
        team: TeamView,
        executor: TaskExecutor,
        queries: QueryHandler,
    ) -> None:
        self.config = config
        self.kb = kb
        self.server: ServerTransport | None = None
        #: Content format -> (when taken, the stats answer): see _get_stats.
        self._stats_snapshots: dict[int | None, tuple[float, Response]] = {}
        self.client = client
        self.router = router
        self.controller = controller
        self.team = team
        self.executor = executor
        self.queries = queries
        #: Paces the notifications of /robot/state and /robot/outcome (set at start).
        self.progress: tuple[ProgressPacing, ...] = ()
        self.final_outcome = FinalOutcome()
        self._next_seq = 1
        #: Object of the last ``POSTS_REMEMBERED`` tasks taken, by sequence number
        #: (a repeated post is recognised: the feeder repeats only its latest).
        self._accepted: dict[int, str] = {}
        #: Its registration in the team's Resource Directory (``[discovery] method = "rd"``).
        self.directory: DirectoryClient | None = None
        #: How late its own event loop runs (set at start).
        self.health: LoopHealth | None = None
        #: Spreads its KB's writes to the other holders (``kb_writable``).
        self.replicator: Replicator | None = None
        #: Writes what the executor did into the Location KB (a writable team).
        self.knowledge: KnowledgeWriter | None = None
        #: Keeps its KB's writes in its data folder (``data_dir``).
        self.keeper: Keeper | None = None

    @classmethod
    async def start(cls, config: RobotConfig, *, query_wire: str = "compact", host: Host | None = None) -> Robot:
        """Start the robot ``config`` describes on ``host`` (the operating
        system unless a simulator gives one)."""
        host = host or operating_system()
        directory = None
        if config.discovery.method == "rd":
            # The teammates come from the directory; the rest of the robot is
            # wired from the configuration they complete (and its security
            # expects each of them at the endpoint it registered).  Imported
            # here: it needs aiocoap, which a ZeroMQ robot never loads.
            from ..discovery import discover

            config, directory = await discover(config)
        try:
            robot = await cls._start(config, query_wire, host)
        except BaseException:
            if directory is not None:
                await directory.aclose()
            raise
        robot.directory = directory
        return robot

    @classmethod
    async def _start(cls, config: RobotConfig, query_wire: str, host: Host) -> Robot:
        secured = robot_security(config)  # first: a bad key stops the robot before the KB loads
        client_security = None if secured is None else secured[1]
        kb = host.load_kb(config.kb_files, config.kb_index) if config.kb_files else None
        check_start(config, kb)
        router = Router()
        # One reliability layer for the client and the server's notifications.
        # The [transport.SCHEME] table: CoAP's layer takes it; another transport its options.
        table = config.transport_options.get(config.transport, {})
        reliability = reliability_for(config.transport, link_kbps=config.link_kbps, options=table)
        client = await host.network.open_client(config.transport, reliability=reliability, security=client_security,
                                                options=table)
        # Nonzero, so it is always sent: teammates tell a restart by it.
        boot = host.rng.randrange(1, 2**32)
        replicator = None
        keeper: Keeper | None = None
        served: KnowledgeBase | LiveKB | None = kb
        if kb is not None:
            served = kb
            if config.kb_writable:
                # In memory, each incarnation writes as a writer of its own (its
                # counts start again at 1); with a data folder, it restores what
                # the folder holds and writes on as the folder's writer.
                known = {m: [t.robot_id for t in config.holders_of(m)] for m in KB_MODULES}
                try:
                    served, keeper = open_live(kb, config.robot_id, boot, config.data_dir, wall_ms=host.wall_ms,
                                               holders=known, background=host.threads)
                except BaseException:
                    await client.aclose()
                    raise
                replicator = Replicator(served, client, module_holders(config, served.names), rng=host.rng)
            KBResources(served, threads=host.threads, replicator=replicator,
                        read_only=f"{config.robot_id}'s knowledge base is read-only (kb_writable = false in its TOML, "
                                  "or coapkb team --read-only): leave kb_writable out or set it true, "
                                  "and start the robot again").mount(router)
        start = config.start
        own = RobotState(
            robot_id=config.robot_id,
            plan=PlannedState(start.aisle, start.rack, start.battery_wh, 0.0, start.payload_kg, seq=0),
            live=LiveState(float(start.aisle), float(start.rack)),
            boot=boot,
        )
        teammates = {r: m.endpoint for r, m in config.team.items() if r != config.robot_id}
        # Local health: this robot's own loop lateness, so its failure
        # detector does not blame teammates for its own busy CPU.
        health = LoopHealth()
        team = TeamView(own, teammates, client, link_kbps=config.link_kbps, health=health)
        # The compact wire caches answers for their Max-Age (the KBs are
        # read-only); the seed's wire reproduces the paper: no cache.
        kb_client = KBClient(client, timeout=config.query_timeout_s, cache=query_wire == "compact",
                             writer=f"{config.robot_id}.{boot}")
        queries = QueryHandler(
            config, served, kb_client, wire=query_wire, down=lambda r: team.down.get(r),
            on_failure=team.request_failed
        )

        state_changed = ProgressPacing(lambda: router.notify(STATE_PATH))
        # Never progress alone: only what the feeder acts on, the changes of
        # one loop turn as one notification.
        outcome_changed = ProgressPacing(lambda: router.notify(OUTCOME_PATH))

        final = FinalOutcome()

        def publish_live(live: LiveState) -> None:
            before = team.own.live
            team.set_own(replace(team.own, live=live))
            final.on_live(before, team.own)
            if acted_on(before, live):
                state_changed.now()
                outcome_changed.now()
            else:
                state_changed.progress()

        def publish_decision(state: RobotState) -> None:
            router.notify(PLAN_PATH)
            state_changed.now()
            outcome_changed.now()

        async def send_decision(message: DecisionMessage) -> None:
            # Not to teammates known down: each would hold the decision up by a timeout.
            members = [r for r in team.membership.members if r != config.robot_id and team.is_up(r)]
            await broadcast_decision(client, config, message, members, team.is_up)

        fence = None
        if config.lease_s > 0:
            lease = Lease(
                config.robot_id, teammates, client, config.lease_s,
                request_timeout_s=lambda: team.request_timeout_s, down=lambda: team.down,
                on_failure=team.request_failed,
            )
            fence = lease.hold
        knowledge = None
        if config.kb_writable:
            knowledge = KnowledgeWriter(
                lambda module, update, write_id: write_knowledge(config, served, replicator, kb_client, module,
                                                                 update, team.is_up, write_id),
                config.robot_id, host.wall_ms, new_write_id=kb_client.new_write_id)
        world = host.world if host.world is not None else (
            WorldClient(config.world) if config.world is not None else None)
        executor = TaskExecutor(config.execution, own.live, publish_live, lease=fence, robot_id=config.robot_id,
                                world=world, knowledge=knowledge)
        async def ask_decision(robot_id: str, seq: int) -> DecisionMessage | None:
            request = Request(Method.GET, "/decisions", {"seq": str(seq)}, accept=ContentFormat.CBOR)
            response = await client.request(config.team[robot_id].endpoint, request, timeout=team.request_timeout_s)
            if response.status != Status.CONTENT:
                return None
            try:
                return DecisionMessage.from_dict(cbor2.loads(response.payload))
            except (ValueError, KeyError, TypeError, cbor2.CBORDecodeError):
                return None

        async def ask_claims(robot_id: str) -> dict[str, Claim]:
            request = Request(Method.GET, CLAIMS_PATH, accept=ContentFormat.CBOR)
            response = await client.request(config.team[robot_id].endpoint, request,
                                            timeout=config.query_timeout_s)
            if response.status != Status.CONTENT:
                raise TransportError(f"{robot_id} answered {response.status.dotted} for its claims")
            try:
                return decode_claims(response.payload)
            except ValueError as exc:
                raise TransportError(f"{robot_id}'s claims: {exc}") from None

        controller = Controller(
            config, queries, team, executor, publish_decision, send_decision, ask_decision, ask_claims
        )
        robot = cls(config, kb, client, router, controller, team, executor, queries)
        robot.progress = (state_changed, outcome_changed)
        robot.final_outcome = final
        robot.health = health
        robot.replicator = replicator
        robot.keeper = keeper
        robot.knowledge = knowledge
        robot._mount()  # before serving: the transport publishes the resource list
        try:
            server_side = None
            if secured is not None:
                # Decisions only from whom this robot's Controller waits for.
                deciders = (lambda: {controller.leader}) if config.strategy == "compute-and-communicate" else (lambda: ())
                server_side = server_security(config.transport, secured[0], AccessPolicy(deciders))
            robot.server = await host.network.serve(router, config.bind, reliability=reliability, security=server_side,
                                                    options=table)
        except BaseException:
            await client.aclose()
            if keeper is not None:
                keeper.close()
            raise
        health.start()
        if replicator is not None:
            replicator.start()
        if knowledge is not None:
            knowledge.start()
        team.start()
        executor.start()
        controller.start()
        return robot

    def _mount(self) -> None:
        add = self.router.add
        add(ResourceInfo(STATE_PATH, rt="coapkb.state", ct=(60, 50), obs=True, title="robot state"), self._get_state)
        add(ResourceInfo(PLAN_PATH, rt="coapkb.plan", ct=(60,), obs=True, title="planned state",
                         methods=("GET", "POST")), self._plan)
        add(ResourceInfo(OUTCOME_PATH, rt="coapkb.outcome", ct=(60,), obs=True, title="decisions and jobs"),
            self._get_outcome)
        add(
            ResourceInfo("/tasks", rt="coapkb.tasks", ct=(60, 50), title="task feed", methods=("GET", "POST")),
            self._tasks,
        )
        add(ResourceInfo("/decisions", rt="coapkb.decisions", methods=("GET", "POST")), self._decisions)
        add(ResourceInfo("/robot/stats", rt="coapkb.stats", ct=(60, 50), title="traffic and query stats"),
            self._get_stats)
        add(ResourceInfo(CLAIMS_PATH, rt="coapkb.claims", ct=(60,), title="objects the cluster assigned"),
            self._get_claims)
        add(ResourceInfo(LEASE_PATH, rt="coapkb.lease", title="lease grants (the fence)"), self._get_lease)

    async def join_team(self) -> tuple[int, int]:
        """Wait, a bounded time, until every teammate has been heard from
        (:meth:`TeamView.heard_from`): the security handshake and the first
        round trip with each are then behind, not in the first task's
        queries.  Returns (teammates heard from, teammates)."""
        heard = await self.team.heard_from(self.team.join_wait_s)
        return len(heard), sum(1 for r in self.config.team if r != self.config.robot_id)

    async def aclose(self) -> None:
        if self.directory is not None:
            await self.directory.aclose()
        await self.controller.aclose()
        if self.knowledge is not None:
            await self.knowledge.aclose()
        await self.executor.aclose()
        for pacing in self.progress:
            pacing.cancel()
        await self.team.aclose()
        if self.replicator is not None:
            await self.replicator.aclose()
        if self.health is not None:
            await self.health.aclose()
        if self.server is not None:
            await self.server.aclose()
        await self.client.aclose()
        if self.keeper is not None:
            self.keeper.close()

    # ---------------------------------------------------------------- resources

    async def _get_state(self, request: Request) -> Response:
        if request.accept == ContentFormat.JSON:
            return _encode(self.team.own.to_dict(), request.accept)
        return _cbor_state(self.team.own.encode(), request.accept)

    async def _get_outcome(self, request: Request) -> Response:
        own = self.team.own
        response = _cbor_state(own.encode_outcome(), request.accept)
        return replace(response, confirm=self.final_outcome(own)) if response.status.is_success else response

    async def _plan(self, request: Request) -> Response:
        if request.method == Method.POST:
            return await self._compare_notes(request)
        return await self._get_plan(request)

    async def _compare_notes(self, request: Request) -> Response:
        """``POST ?of=X&at=S``: a teammate goes on without X's plan after
        task S unless this robot has it (TeamView._plan_from_survivors).
        Answered with that plan (2.04), or 4.04, and then this robot goes on
        without it too: a change of state, so not a GET, which must be safe
        (RFC 7252 §5.8.1).  Only the cluster's robots may ask."""
        about, at = request.query.get("of"), request.query.get("at")
        if about is None or at is None:
            return Response.error(Status.BAD_REQUEST, "give the robot and the task: /robot/plan?of=ROBOT&at=SEQ")
        try:
            seq = int(at)
        except ValueError:
            return Response.error(Status.BAD_REQUEST, "at must be a task number")
        if request.peer is not None and not self.team.in_cluster(request.peer):
            return Response.error(Status.FORBIDDEN, f"{request.peer} is not of {self.config.robot_id}'s cluster")
        state = self.team.state_of(about)
        if state is None or state.plan_at(seq) is None:
            await self.team.forgo(about, seq)
            return Response.error(Status.NOT_FOUND, f"no plan of {about} after task {seq}")
        return Response(Status.CHANGED, state.encode_plan(), ContentFormat.CBOR)

    async def _get_plan(self, request: Request) -> Response:
        probed = request.query.get("probe")
        if probed is not None:
            # A teammate finds ``probed`` silent: does this robot reach it?
            if await self.team.reaches(probed):
                return _cbor_state(self.team.own.encode_plan(), request.accept)
            return Response.error(Status.GATEWAY_TIMEOUT, f"{probed} does not answer {self.config.robot_id} either")
        about = request.query.get("of")
        if about is None or about == self.config.robot_id:
            return _cbor_state(self.team.own.encode_plan(), request.accept)
        # A teammate's plan as this robot observed it: survivors compare notes
        # on a robot that died (TeamView._plan_from_survivors).
        state = self.team.state_of(about)
        at = request.query.get("at")
        if at is not None:
            try:
                seq = int(at)
            except ValueError:
                return Response.error(Status.BAD_REQUEST, "at must be a task number")
            if state is None or state.plan_at(seq) is None:
                return Response.error(Status.NOT_FOUND, f"no plan of {about} after task {seq}")
        if state is None:
            return Response.error(Status.NOT_FOUND, f"no state of {about}")
        return _cbor_state(state.encode_plan(), request.accept)

    async def _get_lease(self, request: Request) -> Response:
        """``?r=X``: does this robot grant teammate X a lease (2.05) or not
        (4.03, why)?  ``&check``: probe X first, so a robot that stopped
        answering is found down now (the feeder asks before re-assigning
        X's tasks).  The requester must be X or the feeder, when known."""
        about = request.query.get("r", "")
        if request.peer is not None and request.peer not in (about, "feeder"):
            return Response.error(Status.FORBIDDEN, f"{request.peer} may not ask about {about}'s lease")
        if "check" in request.query:
            await self.team.probe(about)
        else:
            self.team.asked_by(about)  # alive: if down here, perhaps this robot was the one cut off
        why = self.team.grant(about)
        if why is not None:
            return Response.error(Status.FORBIDDEN, why)
        return Response(Status.CONTENT)

    async def _tasks(self, request: Request) -> Response:
        if request.method == Method.GET:
            return _encode([asdict(d) for d in self.controller.log], request.accept)
        try:
            body = _decode_body(request)
            seq, name = body["seq"], body["object"]
            join = body.get("join", [])
            again = body.get("again")
            restocked = body.get("restocked", False)
        except (ValueError, KeyError, TypeError, AttributeError, cbor2.CBORDecodeError):
            return Response.error(
                Status.BAD_REQUEST,
                'expected {"seq": int, "object": name[, "join": [robot, ...]][, "again": int][, "restocked": true]} '
                'in CBOR or JSON',
            )
        if not isinstance(seq, int) or not isinstance(name, str) or not OBJECT_NAME.match(name):
            return Response.error(Status.BAD_REQUEST, "seq must be an integer and object a local name")
        if again is not None and (type(again) is not int or not 0 < again < seq):
            return Response.error(Status.BAD_REQUEST, "again must name an earlier task")
        if type(restocked) is not bool:
            return Response.error(Status.BAD_REQUEST, "restocked must be true or false")
        if not isinstance(join, list) or not all(isinstance(r, str) and r in self.config.team for r in join):
            return Response.error(Status.BAD_REQUEST, "join must list robots of the team")
        if seq < self._next_seq and self._accepted.get(seq) == name:
            # A repeat of a post already taken (its answer was lost and the
            # feeder asked again as a new exchange): same answer, no new task.
            return Response(Status.CHANGED)
        if self.config.robot_id in join and not self._accepted and seq > 0:
            # Restarted: this robot joins the team at this task (its first).
            self._next_seq = seq
        if seq != self._next_seq:
            return Response.error(Status.CONFLICT, f"expected task {self._next_seq}, got {seq}")
        self._next_seq += 1
        self._accepted[seq] = name
        self._accepted.pop(seq - POSTS_REMEMBERED, None)
        self.controller.submit(Task(seq, name, tuple(join), again, restocked))
        return Response(Status.CHANGED)

    async def _get_claims(self, request: Request) -> Response:
        """``/robot/claims``: the objects the cluster assigned lately, for a restarted teammate."""
        return Response(Status.CONTENT, encode_claims(self.controller.claims_handed()), ContentFormat.CBOR)

    async def _decisions(self, request: Request) -> Response:
        if request.method == Method.GET:
            return self._get_decision(request)
        return await self._post_decision(request)

    def _get_decision(self, request: Request) -> Response:
        """``?seq=N``: this robot's decision on task N, whole (a teammate whose
        knowledge did not arrive takes it instead of deciding alone)."""
        try:
            seq = int(request.query.get("seq", ""))
        except ValueError:
            return Response.error(Status.BAD_REQUEST, "give the task: /decisions?seq=N")
        message = self.controller.recent.get(seq)
        if message is None:
            return Response.error(Status.NOT_FOUND, f"no decision on task {seq} here (yet)")
        return _cbor_state(cbor2.dumps(message.to_dict()), request.accept)

    async def _post_decision(self, request: Request) -> Response:
        try:
            message = DecisionMessage.from_dict(cbor2.loads(request.payload))
        except (ValueError, KeyError, TypeError, cbor2.CBORDecodeError) as exc:
            return Response.error(Status.BAD_REQUEST, f"not a decision: {exc}")
        self.controller.receive_decision(message)
        return Response(Status.CHANGED)

    async def _get_stats(self, request: Request) -> Response:
        # Serving the stats counts traffic, so every fresh snapshot differs: a
        # retried first block of a block-wise transfer on a lossy link would
        # start a new answer each time.  One snapshot serves for a few seconds.
        now = clock.monotonic()
        snapshot = self._stats_snapshots.get(request.accept)
        if snapshot is None or now - snapshot[0] > STATS_SNAPSHOT_S:
            snapshot = (now, _encode(self.stats().to_dict(), request.accept))
            self._stats_snapshots[request.accept] = snapshot
        return snapshot[1]

    def stats(self) -> RobotStats:
        """A snapshot: copies of the live counters, so later traffic does not change it."""
        queries = self.queries.stats
        return RobotStats(
            robot_id=self.config.robot_id,
            transport=self.config.transport,
            strategy=self.config.strategy,
            query_wire=self.queries.wire,
            retransmission=getattr(self.client, "describe", lambda: None)(),
            server_retransmission=getattr(self.server, "describe", lambda: None)(),
            server=replace(self.server.counters) if self.server else None,
            client=replace(self.client.counters),
            queries=replace(queries, remote_latencies=[round(x, 6) for x in queries.remote_latencies]),
            executed=self.executor.live.done,
            idle=self.executor.live.activity == "idle" and self.executor.live.queued == 0,
            fenced=list(self.executor.live.fenced),
            recharges=list(self.executor.recharges),
            loop_lateness=self.health.stats() if self.health is not None else None,
        )


def robot_security(config: RobotConfig) -> tuple[TeamIdentity, ClientSecurity] | None:
    """The member ``config``'s ``[security]`` names and its client side over
    the robot's transport, or None.  Reads the key now, so a missing or
    unreadable key stops the robot at start-up."""
    if config.security is None:
        return None
    mechanism = mechanism_for(config.transport)  # a transport that cannot be secured: before the key
    identity = load_identity(config.security.credentials, config.security.identity or config.robot_id)
    # Each teammate's endpoint must answer with that teammate's credential.
    expected = {m.endpoint.hostport: r for r, m in config.team.items()}
    if config.central is not None:
        expected[config.central.hostport] = "central"
    return identity, mechanism.client(identity, expected)


async def broadcast_decision(
    client: ClientTransport, config: RobotConfig, message: DecisionMessage, recipients: Iterable[str],
    still_up: Callable[[str], bool] = lambda _: True,
) -> None:
    """Send the leader's decision to ``recipients`` (teammates), concurrently;
    a teammate it did not reach is sent it again, up to
    :data:`DECISION_SENDS` times while ``still_up`` says it is up: a
    follower that never gets it waits out its patience and decides nothing
    (found in the simulator, a burst of loss on a radio link)."""
    payload = cbor2.dumps(message.to_dict())
    request = Request(Method.POST, "/decisions", payload=payload, content_format=ContentFormat.CBOR)
    pending = list(recipients)
    for _ in range(DECISION_SENDS):
        peers = [config.team[r].endpoint for r in pending]
        results = await asyncio.gather(
            *(client.request(p, request, timeout=config.query_timeout_s) for p in peers), return_exceptions=True
        )
        pending = [r for r, result in zip(pending, results)
                   if (isinstance(result, BaseException) or not result.status.is_success) and still_up(r)]
        if not pending:
            return
    failed = ", ".join(str(config.team[r].endpoint) for r in pending)
    raise TransportError(f"decision for task {message.decision.seq} not delivered to {failed}")
