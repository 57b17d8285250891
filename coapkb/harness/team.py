"""A whole team on one machine: robots as separate OS processes, faults
injected into them, fed by the feeder (:mod:`coapkb.feeder`) in this
process, and the record of what happened (:mod:`.record`).

As in the seed's section V, robots form clusters of three; in the distributed
mode the robots of a cluster hold the Location, Object and Capability KBs
(Robot1, Robot2, Robot3 of the seed's Fig. 4), and in the centralised
baseline one server holds all three.  The harness writes every robot's
configuration, starts and stops the processes, kills, stops and restarts
them on schedule, and tells the feeder when a restarted robot is back.

The parts: :mod:`.team_spec` says what the team is (its faults too),
:mod:`.placement` where each process runs and on which port,
:mod:`.processes` starts, faults and stops the processes, :mod:`.team_run`
feeds one task list and :mod:`.fault_injector` carries out its faults; the
:class:`Team` here writes the robots' configurations and joins the parts.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import random
import tempfile
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NotRequired, TypedDict

from ..agent.robot_state import RobotState
from ..agent.stats import RobotStats
from ..config import (
    KB_MODULES,
    DiscoveryConfig,
    ExecutionModel,
    RobotConfig,
    StartState,
    Teammate,
    dump_config,
)
from ..feeder import FeederSettings, Roster, TaskRecord, feeder_security
from ..feeder.restock import Restocker, operator_security, shelf_places
from ..feeder.tasks import Entry, Restock
from ..kb.results import expect_select
from ..kb.store import KnowledgeBase, named_rows
from ..security import SecurityConfig, generate_team, load_identity
from ..security.keys import default_members
from ..transport.base import Endpoint
from ..world import CLUSTER_SIZE, OBJECT_NS
from ..world.service import WorldServer
from ..world.truth import WorldTruth
from .kbs import kbs_for_team
from .placement import Placement, PortReservation
from .processes import TeamProcesses
from .record import TeamRecord
from .team_run import TeamRun, team_record
from .team_spec import DEFAULT_ONTOLOGIES, FAULT_ACTIONS, MODES, Fault, TeamError, TeamSpec

if TYPE_CHECKING:  # discovery is imported only when a team uses it
    from ..discovery import ResourceDirectory
    from ..transport import ClientSecurity

__all__ = [
    "CLUSTER_MODULES",
    "DEFAULT_ONTOLOGIES",
    "FAULT_ACTIONS",
    "MODES",
    "Fault",
    "Placement",
    "PortReservation",
    "RobotStart",
    "Team",
    "TeamError",
    "TeamSpec",
    "cluster_modules",
    "draw_tasks",
    "next_cluster_replicas",
    "product_names",
    "robot_configs",
    "robot_starts",
    "team_record",
]

log = logging.getLogger(__name__)


def product_names(object_kb: KnowledgeBase) -> list[str]:
    """Every product's name in the Object KB, sorted."""
    result = object_kb.query(
        f"PREFIX o: <{OBJECT_NS}> SELECT ?name WHERE {{ ?p o:Product_name ?name }} ORDER BY ?name",
        row_limit=10_000_000,
    )
    return [str(row[0]) for row in expect_select(result, "the product names").rows]


def draw_tasks(
    n: int, ontologies: Path = DEFAULT_ONTOLOGIES, seed: int = 1, exclude: Sequence[str] = ()
) -> list[str]:
    """``n`` product names drawn (with a seed) from the Object KB: each object
    once while there are products left (a picked object is gone: a repeat
    would be skipped), then again in a new draw, and so on."""
    names = [name for name in product_names(KnowledgeBase.load([ontologies / "Object.owl"])) if name not in exclude]
    if not names:
        raise TeamError("the Object KB has no products")
    rng = random.Random(seed)
    drawn: list[str] = []
    while len(drawn) < n:
        drawn += rng.sample(names, min(len(names), n - len(drawn)))
    return drawn


class RobotStart(TypedDict):
    """A robot's start as the KBs give it: :class:`~coapkb.config.StartState`'s fields."""

    aisle: int
    rack: int
    battery_wh: NotRequired[float]
    payload_kg: NotRequired[float]


def robot_starts(ontologies: Path) -> dict[str, RobotStart]:
    """Initial position, battery and payload of every robot, from the Location and
    Capability KBs (the generator puts the robots' homes and specs there)."""
    location = KnowledgeBase.load([ontologies / "Location.owl"])
    capability = KnowledgeBase.load([ontologies / "Capability.owl"])
    starts: dict[str, RobotStart] = {}
    for row in named_rows(location, "robot-positions"):
        starts[str(row["robo_id"])] = {"aisle": int(row["aisle_no"]), "rack": int(row["rack_no"])}
    for row in named_rows(capability, "robot-specs"):
        entry = starts.setdefault(str(row["robo_id"]), {"aisle": 1, "rack": 0})
        entry["battery_wh"] = float(row["battery"])
        entry["payload_kg"] = float(row["payload"])
    return starts


#: The seed's Fig. 4: the i-th robot of a cluster holds the i-th module.
CLUSTER_MODULES = ("Location", "Object", "Capability")


def cluster_modules(index: int, spec: TeamSpec) -> tuple[str, ...]:
    """The modules the ``index``-th robot of a cluster holds: its own and, with
    replication r, the next r-1 (so each module lives on r robots)."""
    return tuple(CLUSTER_MODULES[(index + j) % CLUSTER_SIZE] for j in range(spec.replication))


def robot_configs(
    spec: TeamSpec,
    endpoints: dict[str, Endpoint],
    *,
    central: Endpoint | None = None,
    security: SecurityConfig | None = None,
    discovery: Callable[[int, Sequence[str]], DiscoveryConfig] | None = None,
    world: Path | None = None,
) -> dict[str, RobotConfig]:
    """Every robot's configuration for ``spec``, each listening at its
    ``endpoints`` entry: its cluster as teammates (with ``discovery``, a
    Resource Directory's configuration per cluster, each robot knows only
    itself and finds the rest), its KB modules, its start from the KBs."""
    starts = robot_starts(spec.ontologies)
    configs: dict[str, RobotConfig] = {}
    clusters = spec.clusters()
    for cluster_no, cluster in enumerate(clusters, 1):
        team = {
            mate: Teammate(mate, endpoints[mate], cluster_modules(i, spec) if spec.mode == "distributed" else ())
            for i, mate in enumerate(cluster)
        }
        found = DiscoveryConfig() if discovery is None else discovery(cluster_no, cluster)
        for robot_id in cluster:
            configs[robot_id] = RobotConfig(
                robot_id=robot_id,
                bind=endpoints[robot_id],
                kb_files=tuple(spec.ontologies / f"{kb}.owl" for kb in team[robot_id].kbs),
                team=team if discovery is None else {robot_id: team[robot_id]},
                discovery=found,
                lease_s=spec.lease_s,
                start=StartState(**starts.get(robot_id, {"aisle": 1, "rack": 0})),
                strategy=spec.strategy,
                central=central,
                query_timeout_s=spec.query_timeout_s,
                link_kbps=spec.link_kbps,
                execution=ExecutionModel(time_scale=spec.time_scale),
                security=security,
                kb_writable=spec.kb_writable and spec.mode == "distributed",
                replicas=next_cluster_replicas(spec, clusters, cluster_no - 1, robot_id, endpoints),
                world=world,
            )
    return configs


def next_cluster_replicas(
    spec: TeamSpec, clusters: Sequence[Sequence[str]], index: int, robot_id: str, endpoints: dict[str, Endpoint]
) -> dict[str, Teammate]:
    """The holder of the same modules in the next cluster (a ring over the
    clusters): every write passes on to one robot more, whatever the
    team's size, and reaches every cluster around the ring.  As standbys,
    the other robots of the next and the previous cluster that hold one of
    its modules: asked only when its usual holders do not answer, they keep
    it in step when the ring lost a robot in each of two clusters (its
    teammate and its next-cluster holder, both killed, left a robot of nine
    without a module's later writes; found in the simulator)."""
    if not spec.kb_writable or spec.mode != "distributed" or len(clusters) < 2:
        return {}
    place = list(clusters[index]).index(robot_id)
    mine = set(cluster_modules(place, spec))
    replicas: dict[str, Teammate] = {}
    following = clusters[(index + 1) % len(clusters)]
    if place < len(following):
        mate = following[place]
        replicas[mate] = Teammate(mate, endpoints[mate], cluster_modules(place, spec))
    for near in (following, clusters[(index - 1) % len(clusters)]):
        for at, other in enumerate(near):
            kbs = cluster_modules(at, spec)
            if other not in replicas and mine & set(kbs):
                replicas[other] = Teammate(other, endpoints[other], kbs, standby=True)
    return replicas


class Team:
    """The team's processes (:class:`~.processes.TeamProcesses`): started
    with :meth:`launch` (an async context manager), their configurations
    written, fed with :meth:`run` (:class:`~.team_run.TeamRun`), faults
    injected on the spec's schedule."""

    def __init__(self, spec: TeamSpec, workdir: Path, placement: Placement | None = None) -> None:
        self.spec = spec
        self.workdir = workdir
        self.placement = placement or Placement()
        #: The team's processes: started, faulted and stopped.
        self.os_processes = TeamProcesses(self.placement, spec.log_dir)
        self.endpoints: dict[str, Endpoint] = {}
        self.central: Endpoint | None = None
        #: The team's key directory (``coapkb keys``'s layout) when the spec is secure.
        self.team_dir: Path | None = None
        #: The Resource Directory the feeder hosts (``discovery="rd"``).
        self.directory: ResourceDirectory | None = None
        #: The one world the robots find objects in (:mod:`coapkb.world.service`).
        self.world: WorldServer | None = None
        #: Deliveries made by the last :meth:`run` (``restock`` entries of its list).
        self.restocked = 0

    @property
    def processes(self) -> dict[str, asyncio.subprocess.Process]:
        """Every process of the team by name: the robots and the central server."""
        return self.os_processes.by_name

    # ---------------------------------------------------------------- start and stop

    @classmethod
    @contextlib.asynccontextmanager
    async def launch(
        cls, spec: TeamSpec, placement: Placement | None = None, notice: Callable[[str], None] = log.warning
    ) -> AsyncIterator[Team]:
        """Start every process; on exit (normal, error or Ctrl-C) stop them all.

        When the spec's KBs do not know every robot of the team, the team runs
        on KBs generated for it in the run's directory (:mod:`.kbs`), and
        ``notice`` is told so in one line."""
        with tempfile.TemporaryDirectory(prefix="coapkb-team-") as tmp:
            kbs = kbs_for_team(spec.ontologies, spec.robot_ids, Path(tmp) / "ontologies")
            if kbs.generated is not None:
                notice(kbs.generated)
                spec = dataclasses.replace(spec, ontologies=kbs.ontologies)
            team = cls(spec, Path(tmp), placement)
            try:
                await team._start_services()
                await team._start_robots(team.write_configs())
                yield team
            finally:
                await team.stop()

    async def _start_services(self) -> None:
        """What the robots need before they start: the team's keys, the central
        server (central mode), the feeder's Resource Directory (``rd``) and the world."""
        spec = self.spec
        if spec.secure and spec.credentials is not None:
            self.team_dir = spec.credentials
        elif spec.secure:
            self.team_dir = self.workdir / "keys"
            generate_team(self.team_dir, default_members(spec.robots))
        if spec.mode == "central":
            self.central = self.placement.endpoint("central", spec)
            kb_files = [str(spec.ontologies / f"{kb}.owl") for kb in KB_MODULES]
            secured = [] if self.team_dir is None else ["--credentials", str(self.team_dir), "--identity", "central"]
            await self.os_processes.spawn(
                "central",
                ["serve", "--kb", *kb_files, "--bind", self.central.hostport, "--transport", spec.transport, *secured],
                "serving",
            )
        if spec.discovery == "rd":
            if type(self.placement) is not Placement:
                # The feeder's directory listens on the feeder's host only.
                raise TeamError("discovery rd runs on loopback only, not behind emulated links")
            from ..discovery import ResourceDirectory

            identity = None if self.team_dir is None else load_identity(self.team_dir, "feeder")
            self.directory = await ResourceDirectory.start(Endpoint("coap", spec.host, 0), identity)
        # The ground truth of the shelves, shared by every robot.
        self.world = WorldServer(WorldTruth.with_misplaced(spec.misplaced), self.workdir / "world.sock")
        await self.world.start()

    async def _start_robots(self, configs: dict[str, Path]) -> None:
        """Every robot with its configuration file, once each has said it is ready."""
        # A few clusters start at a time: a robot's start-up is CPU
        # work (imports, KBs, keys), and 99 at once on two cores would
        # make each take longer than TeamProcesses.spawn waits for its ready line.
        # A whole cluster at once: a robot says it is ready once it has
        # heard from its teammates (or after a bound), so a teammate
        # left waiting for a slot would hold its mates' slots for that
        # bound (10 s a robot at 30 robots on slow links).  A TaskGroup
        # cancels the other start-ups as soon as one fails.
        slots = asyncio.Semaphore(max(1, 2 * (os.cpu_count() or 1) // CLUSTER_SIZE))

        async def start(cluster: list[str]) -> None:
            async with slots:
                try:
                    async with asyncio.TaskGroup() as mates:
                        for robot_id in cluster:
                            argv = ["agent", "--config", str(configs[robot_id]), "--query-wire", self.spec.query_wire]
                            mates.create_task(self.os_processes.spawn(robot_id, argv, "robot"))
                except ExceptionGroup as failed:
                    raise failed.exceptions[0] from None

        try:
            async with asyncio.TaskGroup() as starting:
                for cluster in self.spec.clusters():
                    starting.create_task(start(list(cluster)))
        except ExceptionGroup as failed:
            raise failed.exceptions[0] from None

    async def stop(self) -> None:
        """Stop every process, then the feeder's directory and the world."""
        try:
            await self.os_processes.stop()
        finally:
            if self.directory is not None:
                await self.directory.aclose()
            if self.world is not None:
                await self.world.aclose()

    def crashed(self) -> list[str]:
        """Every process that exited, with its exit code and last lines."""
        return self.os_processes.crashed()

    # ---------------------------------------------------------------- configurations

    def write_configs(self) -> dict[str, Path]:
        spec = self.spec
        for robot_id in spec.robot_ids:
            self.endpoints[robot_id] = self.placement.endpoint(robot_id, spec)
        directory = self.directory

        def registration(cluster_no: int, cluster: Sequence[str]) -> DiscoveryConfig:
            assert directory is not None  # asked for only when the feeder hosts one
            return DiscoveryConfig(
                "rd", rd=directory.endpoint, rd_identity="feeder", cluster=f"cluster{cluster_no}",
                members=len(cluster), lifetime_s=spec.rd_lifetime_s, wait_s=spec.task_timeout_s,
            )

        configs = robot_configs(
            spec, self.endpoints, central=self.central,
            security=None if self.team_dir is None else SecurityConfig(self.team_dir),
            discovery=None if directory is None else registration,
            world=None if self.world is None else self.world.path,
        )
        paths: dict[str, Path] = {}
        for robot_id, config in configs.items():
            if config.kb_writable:
                config = dataclasses.replace(config, data_dir=self.data_dir(robot_id))
            path = self.workdir / f"{robot_id}.toml"
            path.write_text(dump_config(config), encoding="utf-8")
            paths[robot_id] = path
        return paths

    def data_dir(self, robot_id: str) -> Path:
        """Where writable robot ``robot_id`` keeps its writes (TeamSpec.data_dir)."""
        return (self.spec.data_dir or self.workdir / "data") / robot_id

    # ---------------------------------------------------------------- feeding

    def roster(self) -> Roster:
        """The team as the feeder knows it: the robots' endpoints and clusters."""
        return Roster({r: self.endpoints[r] for r in self.spec.robot_ids}, self.spec.clusters())

    def feeder_settings(self) -> FeederSettings:
        return self.spec.feeder_settings()

    async def run(
        self,
        tasks: Sequence[Entry],
        progress: Callable[[TaskRecord], None] | None = None,
        finished: Callable[[], Awaitable[None]] | None = None,
        on_state: Callable[[str, RobotState], None] | None = None,
        on_stats: tuple[float, Callable[[dict[str, RobotStats]], None]] | None = None,
    ) -> TeamRecord:
        """Feed the tasks, wait for every robot to finish executing, return the record.

        ``finished`` is awaited once every robot is done and before the feeder
        downloads their statistics (a benchmark reads its counters there, so
        that download is not charged to the system).  ``on_state`` is told
        of every robot state the feeder observes (a recording); ``on_stats``
        (seconds, sink): every live robot's statistics that often while the
        run lasts (a recording's series; the downloads are the feeder's
        traffic, so a benchmark leaves this out)."""
        restocker = await self._restocker() if any(isinstance(t, Restock) for t in tasks) else None
        run = TeamRun(self.spec, self.os_processes, self.roster(), self.feeder_settings(), self.feeder_security(),
                      restocker)
        record = await run.feed(tasks, progress, finished, on_state, on_stats)
        self.restocked = 0 if restocker is None else restocker.done
        return record

    async def kb_positions(self) -> dict[str, tuple[int, int]]:
        """Every robot's position as the Location KB now says it (its first
        holder in each cluster, asked with the feeder's credentials)."""
        from ..kb.client import KBClient  # the KB client is only needed here, after a run
        from ..transport import open_client

        positions: dict[str, tuple[int, int]] = {}
        client = await open_client(self.spec.transport, security=self.feeder_security())
        try:
            kb = KBClient(client, timeout=self.spec.query_timeout_s, cache=False)
            for cluster in self.spec.clusters():
                holder = next(r for i, r in enumerate(cluster) if "Location" in cluster_modules(i, self.spec))
                rows = expect_select(await kb.named(self.endpoints[holder], "robot-positions"), "robot-positions").as_dicts()
                positions.update({str(r["robo_id"]): (int(r["aisle_no"]), int(r["rack_no"]))
                                  for r in rows if str(r["robo_id"]) in cluster})
        finally:
            await client.aclose()
        return positions

    async def _restocker(self) -> Restocker:
        """What makes the list's deliveries: into the Location KB of a
        writable team (as the team's operator), and into the world."""
        from ..transport import open_client  # only a list with deliveries needs a second client

        spec = self.spec
        holders: list[list[tuple[str, Endpoint]]] = []
        if spec.kb_writable and spec.mode == "distributed":
            holders = [[(r, self.endpoints[r]) for i, r in enumerate(cluster) if "Location" in cluster_modules(i, spec)]
                       for cluster in spec.clusters()]
        expected = {e.hostport: r for r, e in self.endpoints.items()}
        security = operator_security(spec.transport, self.team_dir, expected)
        places = shelf_places(KnowledgeBase.load([spec.ontologies / "Location.owl"]))
        client = await open_client(spec.transport, security=security)
        return Restocker(client, places, holders, None if self.world is None else self.world.truth,
                         timeout_s=spec.query_timeout_s)

    def feeder_security(self) -> ClientSecurity | None:
        """The feeder's client side for this team (None for an insecure team)."""
        expected = {e.hostport: r for r, e in self.endpoints.items()}
        if self.central is not None:
            expected[self.central.hostport] = "central"
        return feeder_security(self.spec.transport, self.team_dir, expected)

    # ---------------------------------------------------------------- faults

    def pause(self, robot_id: str, stop: bool = True) -> None:
        """Freeze robot ``robot_id``'s process (SIGSTOP: cut off, its state
        intact) or let it go on (SIGCONT); a resumed robot's statistics go
        into the record if it answers."""
        self.os_processes.pause(robot_id, stop)

    async def kill(self, robot_id: str) -> None:
        """SIGKILL robot ``robot_id``'s process and wait until it is gone."""
        await self.os_processes.kill(robot_id)

    async def restart(self, robot_id: str) -> None:
        """Start robot ``robot_id`` again, same configuration and port, once
        it has said it is ready (its old process must be gone)."""
        await self.os_processes.restart(robot_id, "robot")
