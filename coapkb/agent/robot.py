"""One running robot: its KB, server, client and the workflow modules,
wired.  Its resources besides the KB's are :mod:`.robot_resources`; its
requests to teammates beyond observing them, :mod:`.teammate_calls`."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

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
from ..transport import ClientSecurity, ServerSecurity, reliability_for
from ..transport.base import ClientTransport, Endpoint, ServerTransport, TransportError
from ..transport.router import Router
from ..world import Position, layout_from_row
from ..world.service import WorldClient
from .controller import DEFAULT_BOUNDS, Controller, RobotBounds
from .fact_push import FactPusher, PushedFacts
from .knowledge_writer import KnowledgeWriter
from .lease import Lease
from .local_health import LoopHealth
from .observed_states import OUTCOME_PATH, PLAN_PATH, STATE_PATH
from .progress import ProgressPacing, acted_on
from .query_handler import QueryError, QueryHandler
from .robot_resources import FinalOutcome, RobotResources
from .robot_state import BOOT_LIMIT, LiveState, PlannedState, RobotState
from .stats import RobotStats
from .task_assigner import robot_sort_key
from .task_executor import LeaseHold, TaskExecutor
from .team_view import TeamView
from .teammate_calls import TeammateCalls

if TYPE_CHECKING:  # discovery is imported only when a robot uses it
    from ..discovery.client import DirectoryClient


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


def _serve_kb(config: RobotConfig, kb: KnowledgeBase | None, client: ClientTransport, host: Host, boot: int,
              router: Router) -> tuple[KnowledgeBase | LiveKB | None, Keeper | None, Replicator | None]:
    """The robot's KB served on ``router``: the files' as loaded, or, on a
    writable team, a live one kept in the data folder (if any) and spread
    to the other holders.  In memory, each incarnation writes as a writer
    of its own (its counts start again at 1); with a data folder, it
    restores what the folder holds and writes on as the folder's writer."""
    if kb is None:
        return None, None, None
    served: KnowledgeBase | LiveKB = kb
    keeper: Keeper | None = None
    replicator: Replicator | None = None
    if config.kb_writable:
        known = {m: [t.robot_id for t in config.holders_of(m)] for m in KB_MODULES}
        live, keeper = open_live(kb, config.robot_id, boot, config.data_dir, wall_ms=host.wall_ms,
                                 holders=known, background=host.threads, disk=host.disk)
        served = live
        replicator = Replicator(live, client, module_holders(config, live.names), rng=host.rng)
    KBResources(served, threads=host.threads, replicator=replicator,
                read_only=f"{config.robot_id}'s knowledge base is read-only (kb_writable = false in its TOML, "
                          "or coapkb team --read-only): leave kb_writable out or set it true, "
                          "and start the robot again").mount(router)
    return served, keeper, replicator


def module_holders(config: RobotConfig, modules: Iterable[str]) -> list[Holder]:
    """The other robots holding any of ``modules``: teammates, then the
    holders in other clusters (``replicas``, some of them standbys)."""
    held = set(modules)
    mates = [(m, False) for m in config.team.values() if m.robot_id != config.robot_id]
    mates += [(m, True) for m in config.replicas.values()]
    return [Holder(m.robot_id, m.endpoint, tuple(k for k in m.kbs if k in held), remote, m.standby)
            for m, remote in mates if held & set(m.kbs)]


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
        final_outcome: FinalOutcome | None = None,
    ) -> None:
        self.config = config
        self.kb = kb
        self.server: ServerTransport | None = None
        self.client = client
        self.router = router
        self.controller = controller
        self.team = team
        self.executor = executor
        self.queries = queries
        #: Paces the notifications of /robot/state and /robot/outcome (set at start).
        self.progress: tuple[ProgressPacing, ...] = ()
        #: Its own resources' handlers (mounted at start).
        self.resources = RobotResources(config, team, controller, final_outcome or FinalOutcome(), self.stats)
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
    async def start(cls, config: RobotConfig, *, query_wire: str = "compact", host: Host | None = None,
                    bounds: RobotBounds = DEFAULT_BOUNDS) -> Robot:
        """Start the robot ``config`` describes on ``host`` (the operating
        system unless a simulator gives one), remembering at most ``bounds``."""
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
            robot = await cls._start(config, query_wire, host, bounds)
        except BaseException:
            if directory is not None:
                await directory.aclose()
            raise
        robot.directory = directory
        return robot

    @classmethod
    async def _start(cls, config: RobotConfig, query_wire: str, host: Host, bounds: RobotBounds) -> Robot:
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
        # Teammates tell a restart by it.
        boot = host.rng.randrange(1, BOOT_LIMIT)
        try:
            served, keeper, replicator = _serve_kb(config, kb, client, host, boot, router)
        except BaseException:
            await client.aclose()
            raise
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
        queries = _query_handler(config, served, kb_client, client, team, router, query_wire,
                                 None if replicator is None else replicator.caught_up)
        final = FinalOutcome()
        publish_live, publish_decision, pacings = _publishers(router, team, final)
        fence = _fence(config, teammates, client, team)
        knowledge = _knowledge_writer(config, served, replicator, kb_client, team, host) if config.kb_writable else None
        world = host.world if host.world is not None else (
            WorldClient(config.world) if config.world is not None else None)
        executor = TaskExecutor(config.execution, own.live, publish_live, lease=fence, robot_id=config.robot_id,
                                world=world, knowledge=knowledge)
        calls = TeammateCalls(client, config, team)
        controller = Controller(
            config, queries, team, executor, publish_decision, calls.send_decision, calls.ask_decision,
            calls.ask_claims, bounds,
        )
        robot = cls(config, kb, client, router, controller, team, executor, queries, final)
        robot.progress = pacings
        robot.health = health
        robot.replicator = replicator
        robot.keeper = keeper
        robot.knowledge = knowledge
        robot.resources.mount(router)  # before serving: the transport publishes the resource list
        try:
            robot.server = await host.network.serve(
                router, config.bind, reliability=reliability, options=table,
                security=None if secured is None else _server_side(config, secured[0], controller))
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
        if queries.pushed is not None:
            queries.pushed.start()
        executor.start()
        controller.start()
        return robot

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
        if self.queries.pushed is not None:
            await self.queries.pushed.aclose()
        if self.queries.pusher is not None:
            self.queries.pusher.close()
        if self.replicator is not None:
            await self.replicator.aclose()
        if self.health is not None:
            await self.health.aclose()
        if self.server is not None:
            await self.server.aclose()
        await self.client.aclose()
        if self.keeper is not None:
            self.keeper.close()

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


def _query_handler(config: RobotConfig, served: KnowledgeBase | LiveKB | None, kb_client: KBClient,
                   client: ClientTransport, team: TeamView, router: Router, query_wire: str,
                   caught_up: Callable[[], Awaitable[None]] | None) -> QueryHandler:
    """The Query Handler, pushing the answers it gives itself from the
    modules this robot holds (once ``caught_up``, if replicated) and taking
    those its holders push to it."""
    held = config.team[config.robot_id].kbs if served is not None else ()
    queries = QueryHandler(
        config, served, kb_client, wire=query_wire, down=lambda r: team.down.get(r),
        on_failure=team.request_failed, pusher=FactPusher(router, tuple(held), caught_up) if held else None,
    )
    pushing = queries.pushing_holders()
    if pushing:
        queries.pushed = PushedFacts(client, pushing, on_gone=team.request_failed)
    return queries


def _publishers(router: Router, team: TeamView, final: FinalOutcome) -> tuple[
        Callable[[LiveState], None], Callable[[RobotState], None], tuple[ProgressPacing, ...]]:
    """What the executor and the controller call when the robot's state
    changes (its live part; a decision), and the pacing of the notifications
    they send: ``/robot/state`` for people (progress at most once a second),
    ``/robot/outcome`` for the feeder (never progress alone: only what it
    acts on, the changes of one loop turn as one notification), and
    ``/robot/plan`` for teammates at each decision."""
    state_changed = ProgressPacing(lambda: router.notify(STATE_PATH))
    outcome_changed = ProgressPacing(lambda: router.notify(OUTCOME_PATH))

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

    return publish_live, publish_decision, (state_changed, outcome_changed)


def _knowledge_writer(config: RobotConfig, served: KnowledgeBase | LiveKB | None, replicator: Replicator | None,
                      kb_client: KBClient, team: TeamView, host: Host) -> KnowledgeWriter:
    """What writes the executor's picks, positions and loads into the KB (a writable team)."""
    return KnowledgeWriter(
        lambda module, update, write_id: write_knowledge(config, served, replicator, kb_client, module, update,
                                                         team.is_up, write_id),
        config.robot_id, host.wall_ms, new_write_id=kb_client.new_write_id)


def _fence(config: RobotConfig, teammates: dict[str, Endpoint], client: ClientTransport,
           team: TeamView) -> LeaseHold | None:
    """The lease a robot holds before each pick (None: no fence, ``lease_s`` 0)."""
    if config.lease_s <= 0:
        return None
    lease = Lease(
        config.robot_id, teammates, client, config.lease_s,
        request_timeout_s=lambda: team.request_timeout_s, down=lambda: team.down,
        left_out=lambda: team.membership.excluded, on_failure=team.request_failed,
    )
    return lease.hold


def _server_side(config: RobotConfig, identity: TeamIdentity, controller: Controller) -> ServerSecurity:
    """The server side of the robot's security: decisions only from whom its Controller waits for."""
    deciders = (lambda: {controller.leader}) if config.strategy == "compute-and-communicate" else (lambda: ())
    return server_security(config.transport, identity, AccessPolicy(deciders))


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
