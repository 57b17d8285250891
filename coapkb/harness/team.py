"""A whole team on one machine: robots as separate OS processes, faults
injected into them, fed by the feeder (:mod:`coapkb.feeder`) in this
process, and the record of what happened (:mod:`.record`).

As in the seed's section V, robots form clusters of three; in the distributed
mode the robots of a cluster hold the Location, Object and Capability KBs
(Robot1, Robot2, Robot3 of the seed's Fig. 4), and in the centralised
baseline one server holds all three.  The harness writes every robot's
configuration, starts and stops the processes, kills, stops and restarts
them on schedule, and tells the feeder when a restarted robot is back.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import random
import signal
import socket
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, NotRequired, TypedDict

from ..agent.lease import lease_duration_s
from ..agent.observed_states import STATE_PATH, liveness_floor_s
from ..agent.query_handler import QUERY_WIRES
from ..agent.robot_state import RobotState
from ..agent.stats import RobotStats
from ..config import (
    DISCOVERY_METHODS,
    KB_MODULES,
    STRATEGIES,
    DiscoveryConfig,
    ExecutionModel,
    RobotConfig,
    StartState,
    Teammate,
    dump_config,
)
from ..feeder import Feeder, FeederError, FeederSettings, FeedOutcome, Roster, TaskRecord, feeder_security
from ..feeder.restock import Restocker, operator_security, shelf_places
from ..feeder.tasks import Entry, Restock
from ..kb.results import expect_select
from ..kb.store import KnowledgeBase, named_rows
from ..security import SecurityConfig, generate_team, load_identity
from ..security.keys import default_members
from ..transport import SCHEMES, transport_for
from ..transport.base import Endpoint, TrafficCounters, TransportError
from ..world import CLUSTER_SIZE, OBJECT_NS
from ..world.service import WorldServer
from ..world.truth import WorldTruth
from .kbs import kbs_for_team
from .record import FaultEvent, TeamRecord

if TYPE_CHECKING:  # discovery is imported only when a team uses it
    from ..discovery import ResourceDirectory
    from ..transport import ClientSecurity

log = logging.getLogger(__name__)

MODES = ("distributed", "central")
DEFAULT_ONTOLOGIES = Path(__file__).resolve().parents[2] / "ontologies"


class TeamError(FeederError):
    """The team could not be started or did not finish its tasks (the
    feeder's own failures are :class:`~coapkb.feeder.FeederError`)."""


FAULT_ACTIONS = ("kill", "restart", "stop", "resume")


@dataclass(frozen=True)
class Fault:
    """An injected failure: ``kill`` sends SIGKILL to a robot's process,
    ``restart`` starts it again (same configuration and port), ``stop``
    freezes it (SIGSTOP: a robot cut off, its state intact) and ``resume``
    lets it go on (SIGCONT), ``at_s`` seconds of wall time after the first
    task was fed, or, with ``at_task``, once its cluster's task of that
    number is decided (the same story on a fast machine and a slow one)."""

    action: str
    robot: str
    at_s: float = 0.0
    at_task: int | None = None

    @classmethod
    def parse(cls, action: str, text: str) -> Fault:
        """``Robot4@12s`` (or ``Robot4@12``), or ``Robot4@task3``, for ``action``."""
        robot, sep, when = text.partition("@")
        if when.startswith("task"):
            number = when.removeprefix("task")
            if sep and robot and number.isdigit() and int(number) >= 1:
                return cls(action, robot, at_task=int(number))
            raise ValueError(f"--{action} expects ROBOT@taskN with N from 1, like Robot4@task3, got {text!r}")
        try:
            at_s = float(when.removesuffix("s"))
        except ValueError:
            at_s = -1.0
        if not sep or not robot or at_s < 0:
            raise ValueError(f"--{action} expects ROBOT@SECONDS or ROBOT@taskN, like Robot4@12s or Robot4@task3, "
                             f"got {text!r}")
        return cls(action, robot, at_s)

    @property
    def when(self) -> str:
        return f"task {self.at_task}" if self.at_task is not None else f"{self.at_s:g}s"

    def before(self, other: Fault) -> bool:
        """Whether it is scheduled before ``other`` (both by time or both by task)."""
        if (self.at_task is None) != (other.at_task is None):
            return False
        if self.at_task is not None and other.at_task is not None:
            return self.at_task < other.at_task
        return self.at_s < other.at_s




@dataclass(frozen=True)
class TeamSpec:
    robots: int = 3
    mode: str = "distributed"
    transport: str = "coap"
    strategy: str = "compute-by-all"
    query_wire: str = "compact"
    ontologies: Path = DEFAULT_ONTOLOGIES
    host: str = "127.0.0.1"
    query_timeout_s: float = 10.0
    #: The robots' link rate (kbit/s), when they run behind an emulated link.
    link_kbps: float | None = None
    time_scale: float = 50.0
    #: Wall-clock limit for one task's coordination before the run is declared stuck.
    task_timeout_s: float = 120.0
    #: How many robots of a cluster hold each KB module (distributed mode):
    #: 2 = every module on two of the three robots, so one may fail.
    replication: int = 2
    #: Failures injected during the run (``coapkb team --kill/--restart``).
    faults: tuple[Fault, ...] = ()
    #: The robots' KBs take writes and replicate them (distributed mode):
    #: within a cluster, and with the same-place robot of the next cluster.
    kb_writable: bool = False
    #: OSCORE keyed by EDHOC (CoAP), CurveZMQ (ZeroMQ) or mTLS (Zenoh) between every
    #: process, with the team's access policy, from throwaway keys made in
    #: the run's directory.  A transport the registry knows no security for
    #: (``zenoh+udp``) runs plain.
    security: bool = True
    #: An existing team directory (``coapkb keys``) to use instead of throwaway keys.
    credentials: Path | None = None
    #: How robots find their teammates: ``static`` (each config lists its
    #: cluster) or ``rd`` (each config lists the robot alone; the feeder
    #: hosts a Resource Directory where robots register and look the
    #: cluster up: coapkb.discovery).  Static by default: the harness writes
    #: every configuration itself, so its map is exact, and benchmarks do
    #: not pay the directory's traffic.
    discovery: str = "static"
    #: Registration lifetime in the directory (``rd``), seconds.
    rd_lifetime_s: int = 60
    #: Where each process's log goes, one ``NAME.log`` per process at INFO
    #: level (``coapkb bench --trace``): the robots' own account of each task
    #: and each wait.  None: only the last lines are kept, for errors.
    log_dir: Path | None = None
    #: Objects that are not where the KB says (``--misplace``): the robot sent
    #: finds the shelf empty, the task ends as not found.
    misplaced: tuple[str, ...] = ()
    #: Where a writable team's robots keep their writes, one folder per
    #: robot (``DIR/Robot1``...), kept after the run; None: in the run's
    #: own folder, gone with it (a robot killed and restarted during the
    #: run still comes back with what it had).
    data_dir: Path | None = None

    @property
    def lease_s(self) -> float:
        """How long a robot's lease lasts (coapkb.agent.lease); the feeder
        waits this long after the survivors stop granting a down robot's
        lease before it re-feeds that robot's tasks."""
        return lease_duration_s(liveness_floor_s(self.link_kbps))

    @property
    def secure(self) -> bool:
        return self.security and transport_for(self.transport).security is not None

    @property
    def security_scheme(self) -> str:
        """What protects the team's messages (the registry's mechanism name: ``oscore``, ``curve``, ``tls``), or ``none``."""
        security = transport_for(self.transport).security
        return security if self.security and security is not None else "none"

    def __post_init__(self) -> None:
        if self.robots < CLUSTER_SIZE or self.robots % CLUSTER_SIZE:
            raise ValueError(f"robots must be a multiple of {CLUSTER_SIZE} (clusters of three), got {self.robots}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.transport not in SCHEMES:
            raise ValueError(f"transport must be one of {', '.join(SCHEMES)}, got {self.transport!r}")
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}")
        if self.query_wire not in QUERY_WIRES:
            raise ValueError(f"query_wire must be one of {', '.join(QUERY_WIRES)}, got {self.query_wire!r}")
        if self.discovery not in DISCOVERY_METHODS:
            raise ValueError(f"discovery must be one of {', '.join(DISCOVERY_METHODS)}, got {self.discovery!r}")
        if self.discovery == "rd" and not transport_for(self.transport).resource_directory:
            raise ValueError(f"discovery rd needs the coap transport (a Resource Directory speaks CoAP), not {self.transport}")
        if self.rd_lifetime_s < 1:
            raise ValueError(f"rd_lifetime_s must be at least 1, got {self.rd_lifetime_s}")
        if not 1 <= self.replication <= CLUSTER_SIZE:
            raise ValueError(f"replication must be 1 to {CLUSTER_SIZE} (robots per cluster), got {self.replication}")
        for fault in self.faults:
            if fault.action not in FAULT_ACTIONS:
                raise ValueError(f"fault action must be one of {', '.join(FAULT_ACTIONS)}, got {fault.action!r}")
            if fault.robot not in self.robot_ids:
                raise ValueError(f"cannot {fault.action} {fault.robot}: the team is {', '.join(self.robot_ids)}")
            for undo, first, done in (("restart", "kill", "killed"), ("resume", "stop", "stopped")):
                if fault.action != undo:
                    continue
                earlier = [k for k in self.faults if k.action == first and k.robot == fault.robot]
                if not any(k.before(fault) for k in earlier):
                    mixed = any((k.at_task is None) != (fault.at_task is None) for k in earlier)
                    hint = " (schedule both by seconds or both by task)" if mixed else ""
                    raise ValueError(f"cannot {undo} {fault.robot} at {fault.when}: it is not {done} before{hint}")
        for kb in KB_MODULES:
            if not (self.ontologies / f"{kb}.owl").is_file():
                raise ValueError(f"no {kb}.owl in {self.ontologies}")

    @property
    def robot_ids(self) -> list[str]:
        return [f"Robot{i}" for i in range(1, self.robots + 1)]

    def feeder_settings(self) -> FeederSettings:
        """How the feeder talks to this team and how long it waits."""
        return FeederSettings(
            transport=self.transport, task_timeout_s=self.task_timeout_s,
            query_timeout_s=self.query_timeout_s, lease_s=self.lease_s, link_kbps=self.link_kbps,
        )

    def clusters(self) -> list[list[str]]:
        ids = self.robot_ids
        return [ids[i : i + CLUSTER_SIZE] for i in range(0, len(ids), CLUSTER_SIZE)]


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


class PortReservation:
    """Free ports for the team's servers on one host, each held bound until
    its process is about to start.

    The robots' configurations name every teammate's port, so ports are
    chosen before any robot starts, and a robot binds its own (a bound socket
    cannot be handed to the child: aiocoap, ZeroMQ and Zenoh bind their own).
    Asking the OS for port 0 and closing the socket again lets a later ask, or
    a robot's client socket, get the same port before its server binds it: a
    team of 99 then fails to start now and then.  So the ports are taken
    below the kernel's ephemeral range (no client socket is ever given one
    there) and each stays bound here -- no second team member, and no other
    team started meanwhile, can take it -- until :meth:`release` just before
    its process starts."""

    #: Where the search starts: above the well-known and most registered
    #: services' ports (and below Linux's default ephemeral range, 32768-60999).
    LOWEST = 20000

    def __init__(self, host: str) -> None:
        self.host = host
        self._held: dict[str, socket.socket] = {}
        low, _ = _ephemeral_range()
        self._candidates = list(range(self.LOWEST, low)) if low - self.LOWEST >= 1000 else []
        # A random order: two teams allocating at once try different ports first.
        random.SystemRandom().shuffle(self._candidates)

    def take(self, name: str, kind: int) -> int:
        """A port held for process ``name`` (``kind``: SOCK_DGRAM or SOCK_STREAM)."""
        self.release(name)
        while self._candidates:
            port = self._candidates.pop()
            held = socket.socket(socket.AF_INET, kind)
            try:
                held.bind((self.host, port))
            except OSError:  # in use by something else
                held.close()
                continue
            self._held[name] = held
            return port
        # No range below the ephemeral one (a tuned kernel): an OS-chosen port, still held.
        held = socket.socket(socket.AF_INET, kind)
        held.bind((self.host, 0))
        self._held[name] = held
        return int(held.getsockname()[1])

    def release(self, name: str) -> None:
        """Let ``name``'s process bind its port (no-op if none is held)."""
        held = self._held.pop(name, None)
        if held is not None:
            held.close()

    def close(self) -> None:
        for name in list(self._held):
            self.release(name)


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range of ports for client sockets (Linux; its default elsewhere)."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999


async def _sample(feeder: Feeder, every_s: float, sink: Callable[[dict[str, RobotStats]], None]) -> None:
    """Every ``every_s`` seconds, every live robot's statistics to ``sink``;
    a robot that does not answer is left out of that sample."""
    while True:
        await asyncio.sleep(every_s)  # a sampling period: nothing to await but the clock
        watcher = feeder.watcher
        try:
            stats = await feeder.collect_stats([], maybe=[r for r in watcher.alive])
        except TransportError:
            continue
        sink(stats)


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
    team's size, and reaches every cluster around the ring."""
    if not spec.kb_writable or spec.mode != "distributed" or len(clusters) < 2:
        return {}
    place = list(clusters[index]).index(robot_id)
    following = clusters[(index + 1) % len(clusters)]
    if place >= len(following):
        return {}
    mate = following[place]
    return {mate: Teammate(mate, endpoints[mate], cluster_modules(place, spec))}


class Placement:
    """Where each process of the team runs: here, on loopback, each on a free
    port held for it until it starts (:class:`PortReservation`).

    The benchmark's link emulator subclasses this to put every robot in its
    own network namespace behind an emulated link."""

    def __init__(self) -> None:
        self._ports: PortReservation | None = None

    def endpoint(self, name: str, spec: TeamSpec) -> Endpoint:
        kind = socket.SOCK_DGRAM if transport_for(spec.transport).datagram else socket.SOCK_STREAM
        if self._ports is None:
            self._ports = PortReservation(spec.host)
        return Endpoint(spec.transport, spec.host, self._ports.take(name, kind))

    def starting(self, name: str) -> None:
        """Process ``name`` is about to start and bind its endpoint."""
        if self._ports is not None:
            self._ports.release(name)

    def close(self) -> None:
        """Let go of whatever is still held for processes that never started."""
        if self._ports is not None:
            self._ports.close()

    def command(self, name: str, argv: list[str]) -> list[str]:
        """The command line that starts ``argv`` for process ``name``."""
        return argv


class Team:
    """The team's processes: started with :meth:`launch` (an async context
    manager), fed with :meth:`run`, faults injected on the spec's schedule."""

    def __init__(self, spec: TeamSpec, workdir: Path, placement: Placement | None = None) -> None:
        self.spec = spec
        self.workdir = workdir
        self.placement = placement or Placement()
        self.processes: dict[str, asyncio.subprocess.Process] = {}
        self.endpoints: dict[str, Endpoint] = {}
        self.central: Endpoint | None = None
        self._stderr_tails: dict[str, list[str]] = {}
        self._argv: dict[str, list[str]] = {}
        #: The team's key directory (``coapkb keys``'s layout) when the spec is secure.
        self.team_dir: Path | None = None
        #: The Resource Directory the feeder hosts (``discovery="rd"``).
        self.directory: ResourceDirectory | None = None
        #: Stopped robots let go on again: alive, though the team has them down.
        self._resumed: set[str] = set()
        #: Held while a fault is carried out: the run's end waits for one under way.
        self._faulting = asyncio.Lock()
        #: The one world the robots find objects in (:mod:`coapkb.world.service`).
        self.world: WorldServer | None = None
        #: Deliveries made by the last :meth:`run` (``restock`` entries of its list).
        self.restocked = 0

    # ---------------------------------------------------------------- processes

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

    async def _spawn(self, name: str, argv: list[str], ready_prefix: str) -> str:
        self._argv[name] = argv
        self.placement.starting(name)
        log_file: Path | None = None
        if self.spec.log_dir is not None:
            self.spec.log_dir.mkdir(parents=True, exist_ok=True)
            log_file = self.spec.log_dir / f"{name}.log"
            argv = ["-v", *argv]
        proc = await asyncio.create_subprocess_exec(
            *self.placement.command(name, [sys.executable, "-m", "coapkb", *argv]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.processes[name] = proc
        assert proc.stdout is not None and proc.stderr is not None
        tail: list[str] = []
        self._stderr_tails[name] = tail
        asyncio.create_task(_drain(proc.stderr, tail, log_file), name=f"stderr-{name}")
        try:
            line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode().strip()
        except TimeoutError:
            line = ""
        if not line.startswith(ready_prefix):
            await proc.wait() if proc.returncode is not None else None
            # The robot's own "coapkb: error: ..." line, without its prefix:
            # this one is said as "coapkb: ..." too.
            said = line or " ".join(t.removeprefix("coapkb: ").removeprefix("error: ") for t in tail[-3:])
            raise TeamError(f"{name} did not start: {said or 'no output'}")
        asyncio.create_task(_drain(proc.stdout, []), name=f"stdout-{name}")
        return line

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
                if spec.secure and spec.credentials is not None:
                    team.team_dir = spec.credentials
                elif spec.secure:
                    team.team_dir = Path(tmp) / "keys"
                    generate_team(team.team_dir, default_members(spec.robots))
                if spec.mode == "central":
                    team.central = team.placement.endpoint("central", spec)
                    kb_files = [str(spec.ontologies / f"{kb}.owl") for kb in KB_MODULES]
                    secured = [] if team.team_dir is None else ["--credentials", str(team.team_dir), "--identity", "central"]
                    await team._spawn(
                        "central",
                        ["serve", "--kb", *kb_files, "--bind", team.central.hostport, "--transport", spec.transport, *secured],
                        "serving",
                    )
                if spec.discovery == "rd":
                    if type(team.placement) is not Placement:
                        # The feeder's directory listens on the feeder's host only.
                        raise TeamError("discovery rd runs on loopback only, not behind emulated links")
                    from ..discovery import ResourceDirectory

                    identity = None if team.team_dir is None else load_identity(team.team_dir, "feeder")
                    team.directory = await ResourceDirectory.start(Endpoint("coap", spec.host, 0), identity)
                # The ground truth of the shelves, shared by every robot.
                team.world = WorldServer(WorldTruth.with_misplaced(spec.misplaced), Path(tmp) / "world.sock")
                await team.world.start()
                configs = team.write_configs()
                # A few clusters start at a time: a robot's start-up is CPU
                # work (imports, KBs, keys), and 99 at once on two cores would
                # make each take longer than _spawn waits for its ready line.
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
                                    argv = ["agent", "--config", str(configs[robot_id]),
                                            "--query-wire", spec.query_wire]
                                    mates.create_task(team._spawn(robot_id, argv, "robot"))
                        except ExceptionGroup as failed:
                            raise failed.exceptions[0] from None

                try:
                    async with asyncio.TaskGroup() as starting:
                        for cluster in spec.clusters():
                            starting.create_task(start(list(cluster)))
                except ExceptionGroup as failed:
                    raise failed.exceptions[0] from None
                yield team
            finally:
                await team.stop()

    async def stop(self) -> None:
        self.placement.close()
        try:
            await self._stop_processes()
        finally:
            if self.directory is not None:
                await self.directory.aclose()
            if self.world is not None:
                await self.world.aclose()

    async def _stop_processes(self) -> None:
        for proc in self.processes.values():
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
                    proc.send_signal(signal.SIGCONT)  # a stopped robot must run to take SIGTERM
        for name, proc in self.processes.items():
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                log.warning("%s did not stop on SIGTERM; killing it", name)
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()

    def crashed(self) -> list[str]:
        return [f"{n} (exit {p.returncode}): {' '.join(self._stderr_tails[n][-2:])}"
                for n, p in self.processes.items() if p.returncode is not None]

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
        spec = self.spec
        events: list[FaultEvent] = []
        cluster_of = {r: n for n, cluster in enumerate(spec.clusters(), 1) for r in cluster}
        by_task = sorted((f for f in spec.faults if f.at_task is not None), key=lambda f: f.at_task or 0)

        def on_progress(record: TaskRecord) -> Awaitable[None] | None:
            if progress is not None:
                progress(record)
            # A fault scheduled at this task: carried out before the cluster's next task is fed.
            due = [f for f in by_task if cluster_of[f.robot] == record.cluster and record.seq >= (f.at_task or 0)]
            for fault in due:
                by_task.remove(fault)
            return self._carry_all(feeder, started, events, due) if due else None

        restocker = await self._restocker() if any(isinstance(t, Restock) for t in tasks) else None
        # Told of states (a recording): each robot's whole state, where it is included.
        settings = self.feeder_settings() if on_state is None else replace(self.feeder_settings(), watch=STATE_PATH)
        async with contextlib.AsyncExitStack() as closing, \
                Feeder.open(self.roster(), settings, self.feeder_security()) as feeder:
            if restocker is not None:
                closing.push_async_callback(restocker.client.aclose)
                feeder.restocker = restocker
            if on_state is not None:
                feeder.watcher.listeners.append(on_state)
            started = time.monotonic()
            injector = asyncio.create_task(self._inject(feeder, started, events), name="faults")
            sampler = None if on_stats is None else asyncio.create_task(_sample(feeder, *on_stats), name="stats")
            try:
                outcome = await feeder.feed(tasks, on_progress, started)
                if finished is not None:
                    await finished()
                watcher = feeder.watcher
                # A resumed robot is down for the team but answers: its counts
                # show what it executed (nothing the others were given).
                resumed = [r for r in spec.robot_ids if r in self._resumed and r in watcher.down]
                # A fault under way (a restart whose process is starting) ends first; a robot
                # whose process is dead is asked only if it answers: its death may not be seen yet.
                async with self._faulting:
                    dead = [r for r in watcher.alive if self.processes[r].returncode is not None]
                    stats = await feeder.collect_stats([r for r in watcher.alive if r not in dead],
                                                       [*resumed, *dead])
                traffic = feeder.traffic  # a copy: the client still counts while closing
            finally:
                for helper in (injector, sampler):
                    if helper is not None:
                        helper.cancel()
                await asyncio.gather(*(h for h in (injector, sampler) if h is not None), return_exceptions=True)
            down, down_at = dict(watcher.down), dict(watcher.down_at)
        self.restocked = 0 if restocker is None else restocker.done
        for event in events:
            if event.robot in down_at and event.action in ("kill", "stop"):
                event.detected_after_s = round(down_at[event.robot] - started - event.at_s, 3)
        return team_record(self.spec, outcome, stats, traffic, events, down)

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
        with contextlib.suppress(ProcessLookupError):
            self.processes[robot_id].send_signal(signal.SIGSTOP if stop else signal.SIGCONT)
        if not stop:
            self._resumed.add(robot_id)

    async def kill(self, robot_id: str) -> None:
        """SIGKILL robot ``robot_id``'s process and wait until it is gone."""
        proc = self.processes[robot_id]
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGKILL)
        await proc.wait()

    async def restart(self, robot_id: str) -> None:
        """Start robot ``robot_id`` again, same configuration and port, once
        it has said it is ready (its old process must be gone)."""
        await self._spawn(robot_id, self._argv[robot_id], "robot")

    async def _inject(self, feeder: Feeder, started: float, events: list[FaultEvent]) -> None:
        """Carry out the spec's faults scheduled by time, at their wall times after ``started``."""
        for fault in sorted((f for f in self.spec.faults if f.at_task is None), key=lambda f: f.at_s):
            # A schedule, not a wait for an event: the user asked for this time.
            await asyncio.sleep(max(0.0, started + fault.at_s - time.monotonic()))
            await self._carry_out(feeder, started, events, fault)

    async def _carry_all(self, feeder: Feeder, started: float, events: list[FaultEvent], faults: list[Fault]) -> None:
        for fault in faults:
            await self._carry_out(feeder, started, events, fault)

    async def _carry_out(self, feeder: Feeder, started: float, events: list[FaultEvent], fault: Fault) -> None:
        async with self._faulting:
            at_s = round(time.monotonic() - started, 3)
            if fault.action == "restart":
                await self.restart(fault.robot)
                await feeder.membership.rejoin(fault.robot)  # it joins at the next task fed
                log.warning("restarted %s at %.1fs", fault.robot, at_s)
            elif fault.action in ("stop", "resume"):
                self.pause(fault.robot, fault.action == "stop")
                log.warning("%s %s at %.1fs", "stopped" if fault.action == "stop" else "resumed", fault.robot, at_s)
            else:
                await self.kill(fault.robot)
                log.warning("killed %s at %.1fs", fault.robot, at_s)
            events.append(FaultEvent(fault.action, fault.robot, at_s))


def team_record(
    spec: TeamSpec,
    outcome: FeedOutcome,
    stats: dict[str, RobotStats],
    feeder: TrafficCounters,
    faults: list[FaultEvent],
    down: dict[str, str],
) -> TeamRecord:
    """The record of one run of ``spec``'s team (real processes or simulated)."""
    return TeamRecord(
        mode=spec.mode,
        transport=spec.transport,
        strategy=spec.strategy,
        query_wire=spec.query_wire,
        robots=spec.robot_ids,
        clusters=spec.clusters(),
        tasks=outcome.tasks,
        # Rounded as the JSON record has always been, so the benchmark row
        # made from this record holds the same numbers as before.
        coordination_s=round(outcome.coordination_s, 6),
        completion_s=round(outcome.completion_s, 6),
        robot_stats=stats,
        feeder_traffic=feeder,
        faults=faults,
        down=down,
    )


async def _drain(stream: asyncio.StreamReader, tail: list[str], log_file: Path | None = None, keep: int = 20) -> None:
    """Read a child's output so it never blocks on a full pipe; keep the last
    lines, and all of them in ``log_file`` (appended: a restart continues it)."""
    with contextlib.ExitStack() as closing:
        out = closing.enter_context(log_file.open("ab")) if log_file is not None else None
        while line := await stream.readline():
            if out is not None:
                out.write(line)
            tail.append(line.decode(errors="replace").rstrip())
            del tail[:-keep]
