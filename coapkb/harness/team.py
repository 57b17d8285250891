"""A whole team on one machine: robots as separate OS processes, a task feeder,
and the record of what happened.

As in the seed's section V, robots form clusters of three; in the distributed
mode the robots of a cluster hold the Location, Object and Capability KBs
(Robot1, Robot2, Robot3 of the seed's Fig. 4), and in the centralised
baseline one server holds all three.  The task list is split into contiguous
shares, one per cluster, fed in parallel; within a cluster tasks are fed one
at a time (the seed's "sequentially triggered from an external source"): the
next goes out once every robot of the cluster has decided the previous one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import random
import signal
import socket
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, AsyncIterator, Awaitable, Callable, Collection, Mapping, Sequence

import cbor2

from ..errors import CoapkbError
from ..agent.query_handler import QUERY_WIRES
from ..agent.lease import LEASE_PATH, lease_duration_s
from ..agent.team_view import STATE_PATH, ObservedStates, States, liveness_floor_s
from ..agent.robot_state import RobotState
from ..agent.stats import RobotStats
from ..config import (
    DISCOVERY_METHODS,
    KB_MODULES,
    DiscoveryConfig,
    STRATEGIES,
    ExecutionModel,
    RobotConfig,
    StartState,
    Teammate,
    dump_config,
)
from ..kb.store import KnowledgeBase
from ..transport.messages import ContentFormat, Method, Request, Status
from ..kb.named_queries import NAMED_QUERIES
from ..transport.coap.reliability import DEFAULT_PROFILE, PROFILE_NAMES
from ..transport import SCHEMES, open_client
from ..world import CLUSTER_SIZE, OBJECT_NS
from ..transport.base import ClientTransport, Endpoint, TrafficCounters, TransportError
from .record import FaultEvent, TaskRecord, TeamRecord
from ..security import SecurityConfig, generate_team, load_identity
from ..security.keys import default_members

log = logging.getLogger(__name__)

MODES = ("distributed", "central")
DEFAULT_ONTOLOGIES = Path(__file__).resolve().parents[2] / "ontologies"


class TeamError(CoapkbError):
    """The team could not be started or did not finish its tasks."""


FAULT_ACTIONS = ("kill", "restart", "stop", "resume")


@dataclass(frozen=True)
class Fault:
    """An injected failure: ``kill`` sends SIGKILL to a robot's process,
    ``restart`` starts it again (same configuration and port), ``stop``
    freezes it (SIGSTOP: a robot cut off, its state intact) and ``resume``
    lets it go on (SIGCONT), ``at_s`` seconds of wall time after the first
    task was fed."""

    action: str
    robot: str
    at_s: float

    @classmethod
    def parse(cls, action: str, text: str) -> "Fault":
        """``Robot4@12s`` (or ``Robot4@12``) for ``action``."""
        robot, sep, when = text.partition("@")
        try:
            at_s = float(when.removesuffix("s"))
        except ValueError:
            at_s = -1.0
        if not sep or not robot or at_s < 0:
            raise ValueError(f"--{action} expects ROBOT@SECONDS, like Robot4@12s, got {text!r}")
        return cls(action, robot, at_s)


#: Each transport's protection with the team's keys (``TeamSpec.security``):
#: the bench's ``security`` column.  A transport not named here runs plain
#: (``zenoh+udp``: Zenoh has TLS only over TCP).
SECURITY_SCHEMES: dict[str, str] = {"coap": "oscore", "zmq": "curve", "zenoh": "tls"}


@dataclass(frozen=True)
class TeamSpec:
    robots: int = 3
    mode: str = "distributed"
    transport: str = "coap"
    strategy: str = "compute-by-all"
    retransmission: str = DEFAULT_PROFILE
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
    #: OSCORE keyed by EDHOC (CoAP), CurveZMQ (ZeroMQ) or mTLS (Zenoh) between every
    #: process, with the team's access policy (issue 12), from throwaway
    #: keys made in the run's directory.  Transports not in
    #: :data:`SECURITY_SCHEMES` run plain.
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

    @property
    def lease_s(self) -> float:
        """How long a robot's lease lasts (coapkb.agent.lease); the feeder
        waits this long after the survivors stop granting a down robot's
        lease before it re-feeds that robot's tasks."""
        return lease_duration_s(liveness_floor_s(self.link_kbps))

    @property
    def secure(self) -> bool:
        return self.security and self.transport in SECURITY_SCHEMES

    @property
    def security_scheme(self) -> str:
        """What protects the team's messages: a :data:`SECURITY_SCHEMES` value, or ``none``."""
        return SECURITY_SCHEMES[self.transport] if self.secure else "none"

    def __post_init__(self) -> None:
        if self.robots < CLUSTER_SIZE or self.robots % CLUSTER_SIZE:
            raise ValueError(f"robots must be a multiple of {CLUSTER_SIZE} (clusters of three), got {self.robots}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.transport not in SCHEMES:
            raise ValueError(f"transport must be one of {', '.join(SCHEMES)}, got {self.transport!r}")
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}")
        if self.retransmission not in PROFILE_NAMES:
            raise ValueError(f"retransmission must be one of {', '.join(PROFILE_NAMES)}, got {self.retransmission!r}")
        if self.query_wire not in QUERY_WIRES:
            raise ValueError(f"query_wire must be one of {', '.join(QUERY_WIRES)}, got {self.query_wire!r}")
        if self.discovery not in DISCOVERY_METHODS:
            raise ValueError(f"discovery must be one of {', '.join(DISCOVERY_METHODS)}, got {self.discovery!r}")
        if self.discovery == "rd" and self.transport != "coap":
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
            if fault.action == "restart" and not any(
                k.action == "kill" and k.robot == fault.robot and k.at_s < fault.at_s for k in self.faults
            ):
                raise ValueError(f"cannot restart {fault.robot} at {fault.at_s:g}s: it is not killed before")
            if fault.action == "resume" and not any(
                k.action == "stop" and k.robot == fault.robot and k.at_s < fault.at_s for k in self.faults
            ):
                raise ValueError(f"cannot resume {fault.robot} at {fault.at_s:g}s: it is not stopped before")
        for kb in KB_MODULES:
            if not (self.ontologies / f"{kb}.owl").is_file():
                raise ValueError(f"no {kb}.owl in {self.ontologies}")

    @property
    def robot_ids(self) -> list[str]:
        return [f"Robot{i}" for i in range(1, self.robots + 1)]

    def clusters(self) -> list[list[str]]:
        ids = self.robot_ids
        return [ids[i : i + CLUSTER_SIZE] for i in range(0, len(ids), CLUSTER_SIZE)]


def draw_tasks(
    n: int, ontologies: Path = DEFAULT_ONTOLOGIES, seed: int = 1, exclude: Sequence[str] = ()
) -> list[str]:
    """``n`` product names drawn (with a seed, with replacement) from the Object KB."""
    kb = KnowledgeBase.load([ontologies / "Object.owl"])
    result = kb.query(
        f"PREFIX o: <{OBJECT_NS}> SELECT ?name WHERE {{ ?p o:Product_name ?name }} ORDER BY ?name",
        row_limit=10_000_000,
    )
    names = [str(row[0]) for row in result.rows if str(row[0]) not in exclude]  # type: ignore[union-attr]
    if not names:
        raise TeamError("the Object KB has no products")
    rng = random.Random(seed)
    return [rng.choice(names) for _ in range(n)]


def read_tasks_file(path: str | Path) -> list[str]:
    """One product name per line; blank lines and ``#`` comments ignored."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise TeamError(f"cannot read tasks file {path}: {exc.strerror}") from None
    tasks = [line.split("#", 1)[0].strip() for line in lines]
    return [t for t in tasks if t]


def split_tasks(tasks: Sequence[str], clusters: int) -> list[list[str]]:
    """Contiguous, near-equal shares, in order (the seed splits N tasks into equal sets)."""
    bounds = [round(i * len(tasks) / clusters) for i in range(clusters + 1)]
    return [list(tasks[bounds[i] : bounds[i + 1]]) for i in range(clusters)]


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def robot_starts(ontologies: Path) -> dict[str, dict[str, float | int]]:
    """Initial position, battery and payload of every robot, from the Location and
    Capability KBs (the generator puts the robots' homes and specs there)."""
    location = KnowledgeBase.load([ontologies / "Location.owl"])
    capability = KnowledgeBase.load([ontologies / "Capability.owl"])
    starts: dict[str, dict[str, float | int]] = {}
    for row in location.query(NAMED_QUERIES["robot-positions"].render({})).as_dicts():  # type: ignore[union-attr]
        starts[str(row["robo_id"])] = {"aisle": int(row["aisle_no"]), "rack": int(row["rack_no"])}
    for row in capability.query(NAMED_QUERIES["robot-specs"].render({})).as_dicts():  # type: ignore[union-attr]
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


class Placement:
    """Where each process of the team runs: here, on loopback, each on a free port.

    The benchmark's link emulator subclasses this to put every robot in its
    own network namespace behind an emulated link."""

    def endpoint(self, name: str, spec: TeamSpec) -> Endpoint:
        kind = socket.SOCK_DGRAM if spec.transport in ("coap", "zenoh+udp") else socket.SOCK_STREAM
        return Endpoint(spec.transport, spec.host, _free_port(kind))

    def command(self, name: str, argv: list[str]) -> list[str]:
        """The command line that starts ``argv`` for process ``name``."""
        return argv


class Team:
    """Start with :meth:`launch` (an async context manager), then :meth:`run`."""

    def __init__(self, spec: TeamSpec, workdir: Path, placement: Placement | None = None) -> None:
        self.spec = spec
        self.workdir = workdir
        self.placement = placement or Placement()
        self.processes: dict[str, asyncio.subprocess.Process] = {}
        self.endpoints: dict[str, Endpoint] = {}
        self.central: Endpoint | None = None
        self._stderr_tails: dict[str, list[str]] = {}
        self._argv: dict[str, list[str]] = {}
        #: Restarted robots, up again and waiting to join at the next task.
        self._restarted: set[str] = set()
        #: Robot -> the first task of its current process (0: the first one).
        self._incarnation: dict[str, int] = {}
        #: The team's key directory (``coapkb keys``'s layout) when the spec is secure.
        self.team_dir: Path | None = None
        #: The Resource Directory the feeder hosts (``discovery="rd"``).
        self.directory: Any = None
        #: Stopped robots let go on again: alive, though the team has them down.
        self._resumed: set[str] = set()
        #: Down robots whose tasks may go round again: the survivors no
        #: longer grant them a lease, and it has run out (:meth:`_fence`).
        self._fenced_off: set[str] = set()

    # ---------------------------------------------------------------- processes

    def write_configs(self) -> dict[str, Path]:
        spec = self.spec
        starts = robot_starts(spec.ontologies)
        paths: dict[str, Path] = {}
        for cluster in spec.clusters():
            for robot_id in cluster:
                self.endpoints[robot_id] = self.placement.endpoint(robot_id, spec)
        for cluster_no, cluster in enumerate(spec.clusters(), 1):
            team = {
                mate: Teammate(mate, self.endpoints[mate], cluster_modules(i, spec) if spec.mode == "distributed" else ())
                for i, mate in enumerate(cluster)
            }
            discovery = DiscoveryConfig()
            if self.directory is not None:
                discovery = DiscoveryConfig(
                    "rd", rd=self.directory.endpoint, rd_identity="feeder", cluster=f"cluster{cluster_no}",
                    members=len(cluster), lifetime_s=spec.rd_lifetime_s, wait_s=spec.task_timeout_s,
                )
            for robot_id in cluster:
                config = RobotConfig(
                    robot_id=robot_id,
                    bind=self.endpoints[robot_id],
                    kb_files=tuple(spec.ontologies / f"{kb}.owl" for kb in team[robot_id].kbs),
                    # With a directory, each robot knows only itself and finds the rest.
                    team=team if self.directory is None else {robot_id: team[robot_id]},
                    discovery=discovery,
                    lease_s=spec.lease_s,
                    start=StartState(**starts.get(robot_id, {"aisle": 1, "rack": 0})),  # type: ignore[arg-type]
                    strategy=spec.strategy,
                    retransmission=spec.retransmission,
                    central=self.central,
                    query_timeout_s=spec.query_timeout_s,
                    link_kbps=spec.link_kbps,
                    execution=ExecutionModel(time_scale=spec.time_scale),
                    security=None if self.team_dir is None else SecurityConfig(self.team_dir),
                )
                path = self.workdir / f"{robot_id}.toml"
                path.write_text(dump_config(config), encoding="utf-8")
                paths[robot_id] = path
        return paths

    async def _spawn(self, name: str, argv: list[str], ready_prefix: str) -> str:
        self._argv[name] = argv
        proc = await asyncio.create_subprocess_exec(
            *self.placement.command(name, [sys.executable, "-m", "coapkb", *argv]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.processes[name] = proc
        assert proc.stdout is not None and proc.stderr is not None
        tail: list[str] = []
        self._stderr_tails[name] = tail
        asyncio.create_task(_drain(proc.stderr, tail), name=f"stderr-{name}")
        try:
            line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode().strip()
        except asyncio.TimeoutError:
            line = ""
        if not line.startswith(ready_prefix):
            await proc.wait() if proc.returncode is not None else None
            raise TeamError(f"{name} did not start: {line or ' '.join(tail[-3:]) or 'no output'}")
        asyncio.create_task(_drain(proc.stdout, []), name=f"stdout-{name}")
        return line

    @classmethod
    @contextlib.asynccontextmanager
    async def launch(cls, spec: TeamSpec, placement: Placement | None = None) -> AsyncIterator["Team"]:
        """Start every process; on exit (normal, error or Ctrl-C) stop them all."""
        with tempfile.TemporaryDirectory(prefix="coapkb-team-") as tmp:
            team = cls(spec, Path(tmp), placement)
            try:
                if spec.secure and spec.credentials is not None:
                    team.team_dir = spec.credentials
                elif spec.secure:
                    team.team_dir = Path(tmp) / "keys"
                    generate_team(team.team_dir, default_members(spec.robots))
                if spec.mode == "central":
                    team.central = team.placement.endpoint("central", spec)
                    kbs = [str(spec.ontologies / f"{kb}.owl") for kb in KB_MODULES]
                    secured = [] if team.team_dir is None else ["--credentials", str(team.team_dir), "--identity", "central"]
                    await team._spawn(
                        "central",
                        ["serve", "--kb", *kbs, "--bind", team.central.hostport, "--transport", spec.transport, *secured],
                        "serving",
                    )
                if spec.discovery == "rd":
                    if type(team.placement) is not Placement:
                        # The feeder's directory listens on the feeder's host only.
                        raise TeamError("discovery rd runs on loopback only, not behind emulated links")
                    from ..discovery import ResourceDirectory

                    identity = None if team.team_dir is None else load_identity(team.team_dir, "feeder")
                    team.directory = await ResourceDirectory.start(Endpoint("coap", spec.host, 0), identity)
                configs = team.write_configs()
                # A TaskGroup cancels the other start-ups as soon as one fails.
                try:
                    async with asyncio.TaskGroup() as starting:
                        for robot_id, path in configs.items():
                            argv = ["agent", "--config", str(path), "--query-wire", spec.query_wire]
                            starting.create_task(team._spawn(robot_id, argv, "robot"))
                except ExceptionGroup as failed:
                    raise failed.exceptions[0] from None
                yield team
            finally:
                await team.stop()

    async def stop(self) -> None:
        try:
            await self._stop_processes()
        finally:
            if self.directory is not None:
                await self.directory.aclose()

    async def _stop_processes(self) -> None:
        for proc in self.processes.values():
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
                    proc.send_signal(signal.SIGCONT)  # a stopped robot must run to take SIGTERM
        for name, proc in self.processes.items():
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except asyncio.TimeoutError:
                log.warning("%s did not stop on SIGTERM; killing it", name)
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()

    def crashed(self) -> list[str]:
        return [f"{n} (exit {p.returncode}): {' '.join(self._stderr_tails[n][-2:])}"
                for n, p in self.processes.items() if p.returncode is not None]

    # ---------------------------------------------------------------- feeding

    async def run(
        self,
        tasks: Sequence[str],
        progress: Callable[[TaskRecord], None] | None = None,
        finished: Callable[[], Awaitable[None]] | None = None,
    ) -> TeamRecord:
        """Feed the tasks, wait for every robot to finish executing, return the record.

        ``finished`` is awaited once every robot is done and before the feeder
        downloads their statistics (a benchmark reads its counters there, so
        that download is not charged to the system)."""
        spec = self.spec
        client = await open_client(spec.transport, retransmission=spec.retransmission, security=self.feeder_security())
        # With liveness the feeder declares a robot down when its requests
        # fail, and then waits for the survivors only.
        watcher = ObservedStates(
            client, self.endpoints, STATE_PATH, liveness=True, liveness_floor_s=liveness_floor_s(spec.link_kbps)
        )
        watcher.start()
        started = time.monotonic()
        records: list[TaskRecord] = []
        events: list[FaultEvent] = []
        injector = asyncio.create_task(self._inject(started, events), name="faults")
        try:
            shares = split_tasks(tasks, len(spec.clusters()))
            per_cluster = await asyncio.gather(
                *(
                    self._feed_cluster(client, watcher, index, cluster, share, progress)
                    for index, (cluster, share) in enumerate(zip(spec.clusters(), shares))
                )
            )
            coordination_s = max(decided_at for _, decided_at in per_cluster) - started
            completion_s = time.monotonic() - started
            for share_records, _ in per_cluster:
                records.extend(share_records)
            if finished is not None:
                await finished()
            # A resumed robot is down for the team but answers: its counts
            # show what it executed (nothing the others were given).
            resumed = [r for r in spec.robot_ids if r in self._resumed and r in watcher.down]
            stats = await self._collect_stats(client, watcher.alive, resumed)
            feeder = replace(client.counters)  # a copy: the client still counts while closing
        finally:
            injector.cancel()
            await asyncio.gather(injector, return_exceptions=True)
            await watcher.aclose()
            await client.aclose()
        for event in events:
            if event.robot in watcher.down_at and event.action in ("kill", "stop"):
                event.detected_after_s = round(watcher.down_at[event.robot] - started - event.at_s, 3)
        return self._record(records, stats, feeder, coordination_s, completion_s, events, dict(watcher.down))

    def feeder_security(self) -> Any:
        """The feeder's OSCORE/EDHOC, CurveZMQ or mTLS client side, or None for an insecure team."""
        if self.team_dir is None:
            return None
        expected = {e.hostport: r for r, e in self.endpoints.items()}
        if self.central is not None:
            expected[self.central.hostport] = "central"
        if self.spec.transport == "zmq":
            from ..security.curve import ZmqClientSecurity

            return ZmqClientSecurity(load_identity(self.team_dir, "feeder"), expected)
        if self.spec.transport == "zenoh":
            from ..security.zenoh_tls import ZenohClientSecurity

            return ZenohClientSecurity(load_identity(self.team_dir, "feeder"), expected)
        from ..security.coap import ClientSecurity

        return ClientSecurity(load_identity(self.team_dir, "feeder"), expected)

    def pause(self, robot_id: str, stop: bool = True) -> None:
        """Freeze robot ``robot_id``'s process (SIGSTOP: cut off, its state
        intact) or let it go on (SIGCONT); a resumed robot's statistics go
        into the record if it answers."""
        with contextlib.suppress(ProcessLookupError):
            self.processes[robot_id].send_signal(signal.SIGSTOP if stop else signal.SIGCONT)
        if not stop:
            self._resumed.add(robot_id)

    async def _inject(self, started: float, events: list[FaultEvent]) -> None:
        """Carry out the spec's faults at their wall times after ``started``."""
        for fault in sorted(self.spec.faults, key=lambda f: f.at_s):
            # A schedule, not a wait for an event: the user asked for this time.
            await asyncio.sleep(max(0.0, started + fault.at_s - time.monotonic()))
            at_s = round(time.monotonic() - started, 3)
            if fault.action == "restart":
                # Same configuration and port; it joins at the next task fed.
                await self._spawn(fault.robot, self._argv[fault.robot], "robot")
                self._restarted.add(fault.robot)
                log.warning("restarted %s at %.1fs", fault.robot, at_s)
                events.append(FaultEvent(fault.action, fault.robot, at_s))
                continue
            proc = self.processes[fault.robot]
            if fault.action in ("stop", "resume"):
                self.pause(fault.robot, fault.action == "stop")
                log.warning("%s %s at %.1fs", "stopped" if fault.action == "stop" else "resumed", fault.robot, at_s)
                events.append(FaultEvent(fault.action, fault.robot, at_s))
                continue
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGKILL)
            await proc.wait()
            log.warning("killed %s at %.1fs", fault.robot, at_s)
            events.append(FaultEvent(fault.action, fault.robot, at_s))

    async def _feed_cluster(
        self,
        client: ClientTransport,
        watcher: ObservedStates,
        index: int,
        cluster: list[str],
        share: list[str],
        progress: Callable[[TaskRecord], None] | None,
    ) -> tuple[list[TaskRecord], float]:
        """Feed one cluster's share; returns its records and when its last task was decided."""
        records: list[TaskRecord] = []
        queue: list[tuple[str, int | None]] = [(name, None) for name in share]
        #: Tasks of a robot's previous process, found when it joins again.
        reruns: list[TaskRecord] = []
        seq = 0
        decided_at = time.monotonic()
        while queue:
            for name, reassigned_from in queue:
                seq += 1
                joining = sorted(r for r in cluster if r in self._restarted)
                if joining:
                    reruns += self._prepare_join(watcher, records, joining, seq)
                if records:
                    await self._take_back(client, watcher, cluster, records)
                record = await self._feed_task(client, watcher, index, cluster, seq, name, joining)
                record.reassigned_from = reassigned_from
                records.append(record)
                if progress is not None:
                    progress(record)
            decided_at = time.monotonic()
            # Until the cluster's survivors have executed everything: a robot
            # that dies meanwhile is found by the stalled wait's liveness requests.
            await _wait_for(
                watcher,
                lambda s: all(r in watcher.down or _idle(s, r) for r in cluster),
                self.spec.task_timeout_s * 4,
                f"cluster {index + 1} to finish executing",
            )
            # Tasks assigned to robots that went down before executing them
            # go round again, in their order, to the survivors: once the
            # down robot can no longer pick them (the fence).
            for robot_id in cluster:
                if robot_id in watcher.down and robot_id not in self._fenced_off and _unexecuted(
                    records, watcher, robot_id, self._incarnation
                ):
                    if await self._fence(client, watcher, cluster, robot_id):
                        self._fenced_off.add(robot_id)
                    else:
                        await self._settle(client, robot_id)
            found = {r.seq: r for r in reruns + _orphans(records, watcher, self._incarnation, self._fenced_off)}
            orphans = [found[s] for s in sorted(found)]
            reruns = []
            queue = [(r.object, r.seq) for r in orphans]
        return records, decided_at

    def _prepare_join(
        self, watcher: ObservedStates, records: list[TaskRecord], joining: list[str], seq: int
    ) -> list[TaskRecord]:
        """Before restarted robots join at task ``seq``: their previous
        processes' unexecuted tasks (returned, to go round again), then count
        on them afresh."""
        for robot_id in joining:
            self._restarted.discard(robot_id)
            # A restart the feeder made itself: the old process is gone even if
            # no failed request told yet (killed: it cannot pick anything).
            watcher.down.setdefault(robot_id, "restarted")
        orphans = _orphans(records, watcher, self._incarnation, joining, only=joining)
        for robot_id in joining:
            self._incarnation[robot_id] = seq
            self._fenced_off.discard(robot_id)
            watcher.readmit(robot_id)
        return orphans

    async def _take_back(
        self, client: ClientTransport, watcher: ObservedStates, cluster: list[str], records: Sequence[TaskRecord]
    ) -> None:
        """Feed again a robot the feeder has down but its teammates still
        count as a member (their last decision names it): it was only slow
        or cut off, and under "compute by all" they wait for its plan after
        every task.  It is asked once; if it answers with the same process (a
        new one joins instead, at a task boundary), it is given the tasks it
        missed, in order, and fed from now on like the others."""
        last = records[-1]
        # A dead robot is asked at each task boundary until its teammates
        # leave it out (a task or two): a few round trips, not a liveness
        # timeout, since silence here only means "not back yet".
        srtt = watcher.round_trip.srtt
        timeout = watcher.request_timeout_s if srtt is None else min(watcher.request_timeout_s, max(0.25, 3 * srtt))
        for robot_id in cluster:
            if (robot_id not in watcher.down or robot_id not in last.members or robot_id in self._fenced_off
                    or robot_id in self._restarted):
                continue
            try:
                response = await client.request(
                    self.endpoints[robot_id], Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR),
                    timeout=timeout,
                )
                state = RobotState.decode(response.payload) if response.status.is_success else None
            except (TransportError, ValueError):
                continue
            known = watcher.states.get(robot_id)
            if state is None or known is None or state.boot != known.boot:
                continue
            seen = state.last.seq if state.last is not None else 0
            missed = [r for r in records if r.seq > seen]
            log.warning("%s answers again and its teammates still count it: fed again from task %d",
                        robot_id, seen + 1)
            watcher.readmit(robot_id)
            for record in missed:  # the robot takes tasks strictly in order
                await self._post_task(client, watcher, robot_id, _task_post(record.seq, record.object, record.joined),
                                      record.seq, record.object)

    async def _feed_task(
        self, client: ClientTransport, watcher: ObservedStates, index: int, cluster: list[str], seq: int, name: str,
        joining: Sequence[str] = (),
    ) -> TaskRecord:
        fed = time.monotonic()
        request = _task_post(seq, name, joining)
        live = [r for r in cluster if r not in watcher.down]
        if not live:
            raise TeamError(f"every robot of cluster {index + 1} is down: {watcher.down}")
        await asyncio.gather(*(self._post_task(client, watcher, r, request, seq, name) for r in live))

        def decided(states: States, robot_id: str) -> bool:
            last = states[robot_id].last if robot_id in states else None
            return last is not None and last.seq >= seq

        states = await _wait_for(
            watcher,
            lambda s: all(r in watcher.down or decided(s, r) for r in cluster),
            self.spec.task_timeout_s,
            f"decisions on task {seq} ({name}) from {', '.join(r for r in cluster if r not in watcher.down)}",
        )
        record = TaskRecord(object=name, cluster=index + 1, seq=seq, coordination_s=time.monotonic() - fed,
                            joined=list(joining))
        decisions = {r: d for r in cluster if decided(states, r) and (d := states[r].last) is not None}
        if len({(d.assigned_to, d.unavailable, d.error) for d in decisions.values()}) > 1:
            # Robots that differ may have decided and then died before the
            # feeder noticed: ask each once, so the dead ones' decisions are void.
            await asyncio.gather(*(watcher.probe(r) for r in decisions if r not in watcher.down))
        # The decision is the survivors': a robot that decided and then went
        # down executes nothing (its task, if any, goes round again), and one
        # left out of a newer membership by the others took no part in it.
        newest = max(decisions.values(), key=lambda d: d.epoch, default=None)
        survivors = [r for r in decisions if r not in watcher.down]
        for robot_id in cluster:
            decision = decisions.get(robot_id)
            if decision is None:
                record.absent[robot_id] = watcher.down.get(robot_id, "no decision")
                continue
            if robot_id in watcher.down and survivors:
                record.absent[robot_id] = f"{watcher.down[robot_id]} (its decision is void)"
                continue
            if newest is not None and decision.epoch < newest.epoch and robot_id not in newest.members:
                record.absent[robot_id] = f"left out of membership epoch {newest.epoch} (its decision is void)"
                continue
            record.decisions[robot_id] = decision.assigned_to
            record.epochs[robot_id] = decision.epoch
            if decision.members and not record.members:
                record.members = list(decision.members)
            if decision.error:
                record.errors[robot_id] = decision.error
            if decision.unavailable and record.unavailable is None:
                record.unavailable = decision.unavailable
            if decision.skipped:
                record.skipped = True
            if decision.costs and not record.costs:
                record.costs = dict(decision.costs)
                record.reasons = dict(decision.reasons)
        assigned = {d for d in record.decisions.values() if d is not None}
        record.assigned_to = assigned.pop() if len(assigned) == 1 else None
        return record

    async def _post_task(
        self, client: ClientTransport, watcher: ObservedStates, robot_id: str, request: Request, seq: int, name: str
    ) -> None:
        """POST a task to one robot; if it does not answer, ask the watcher
        whether it is down (then the task goes to the survivors only) or
        post again (a robot recognises a repeated post)."""
        deadline = time.monotonic() + self.spec.task_timeout_s
        while True:
            try:
                response = await client.request(
                    self.endpoints[robot_id], request, timeout=max(watcher.request_timeout_s, 1.0)
                )
            except TransportError as exc:
                await watcher.probe(robot_id)
                if robot_id in watcher.down:
                    return
                if time.monotonic() > deadline:
                    raise TeamError(f"{robot_id} refused task {seq} ({name}): {exc}") from None
                continue
            if not response.status.is_success:
                await watcher.probe(robot_id)  # a restarted robot refuses: it is down for the team
                if robot_id in watcher.down:
                    return
                raise TeamError(f"{robot_id} refused task {seq} ({name}): {response}")
            return

    async def _settle(self, client: ClientTransport, robot_id: str) -> None:
        """Wait until ``robot_id`` (down for the feeder, but its teammates
        still grant it: it came back) has executed what it holds, so its
        statistics in the record are final."""
        request = Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR)
        with contextlib.suppress(TransportError, ValueError, TimeoutError):
            async with asyncio.timeout(self.spec.task_timeout_s * 4):
                async for response in client.observe(self.endpoints[robot_id], request):
                    live = RobotState.decode(response.payload).live
                    if live.activity == "idle" and live.queued == 0:
                        return

    async def _fence(self, client: ClientTransport, watcher: ObservedStates, cluster: list[str], robot_id: str) -> bool:
        """Before down ``robot_id``'s tasks go round again: ask every survivor
        of its cluster whether it still grants it a lease (each probes it
        first), then wait the lease out from the last refusal.  False if a
        survivor still grants it (it answers them: its tasks stay its own)."""
        if self.spec.lease_s <= 0:
            return True
        request = Request(Method.GET, LEASE_PATH, {"r": robot_id, "check": ""})

        async def refused_at(survivor: str) -> float | None:
            """When ``survivor`` said it no longer grants ``robot_id`` (now if it is down)."""
            while survivor not in watcher.down:
                try:
                    response = await client.request(
                        self.endpoints[survivor], request, timeout=self.spec.task_timeout_s
                    )
                except TransportError:
                    await watcher.probe(survivor)
                    continue
                if response.status == Status.FORBIDDEN:
                    return time.monotonic()
                if response.status.is_success:
                    return None
                raise TeamError(f"{survivor} answered {response.status.dotted} about {robot_id}'s lease: {response.text()}")
            return time.monotonic()

        survivors = [r for r in cluster if r != robot_id and r not in watcher.down]
        answers = await asyncio.gather(*(refused_at(r) for r in survivors))
        if any(at is None for at in answers):
            granting = [r for r, at in zip(survivors, answers) if at is None]
            log.warning("%s still grant %s a lease: its tasks stay with it", ", ".join(granting), robot_id)
            return False
        # Waiting the lease out is the fence itself: any lease the robot
        # holds was granted before the last refusal, so it ends within this.
        last = max(answers, default=time.monotonic())
        await asyncio.sleep(max(0.0, last + self.spec.lease_s - time.monotonic()))
        # From now on the robot can pick nothing: if it answers (it was only
        # cut off), its state is final and says what it did pick.
        with contextlib.suppress(TransportError, ValueError):
            response = await client.request(
                self.endpoints[robot_id], Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR),
                timeout=watcher.request_timeout_s,
            )
            state = RobotState.decode(response.payload)
            known = watcher.states.get(robot_id)
            if response.status.is_success and known is not None and state.boot == known.boot:
                watcher.states[robot_id] = state
        log.warning("%s's lease has run out: its unexecuted tasks go round again", robot_id)
        return True

    async def _collect_stats(
        self, client: ClientTransport, robots: Sequence[str], maybe: Sequence[str] = ()
    ) -> dict[str, RobotStats]:
        """Every robot's statistics; those of ``maybe`` if they answer."""
        request = Request(Method.GET, "/robot/stats", accept=ContentFormat.CBOR)
        stats = {}
        for robot_id in [*robots, *maybe]:
            endpoint = self.endpoints[robot_id]
            try:
                response = await client.request(endpoint, request, timeout=self.spec.query_timeout_s)
            except TransportError:
                if robot_id in maybe:
                    continue
                raise
            stats[robot_id] = RobotStats.from_dict(cbor2.loads(response.payload))
        return stats

    def _record(
        self,
        records: list[TaskRecord],
        stats: dict[str, RobotStats],
        feeder: TrafficCounters,
        coordination_s: float,
        completion_s: float,
        faults: list[FaultEvent] | None = None,
        down: dict[str, str] | None = None,
    ) -> TeamRecord:
        spec = self.spec
        # Restore the order given: cluster shares are contiguous.
        records.sort(key=lambda r: (r.cluster, r.seq))
        return TeamRecord(
            mode=spec.mode,
            transport=spec.transport,
            strategy=spec.strategy,
            retransmission=spec.retransmission,
            query_wire=spec.query_wire,
            robots=spec.robot_ids,
            clusters=spec.clusters(),
            tasks=records,
            # Rounded as the JSON record has always been, so the benchmark row
            # made from this record holds the same numbers as before.
            coordination_s=round(coordination_s, 6),
            completion_s=round(completion_s, 6),
            robot_stats=stats,
            feeder_traffic=feeder,
            faults=list(faults or []),
            down=dict(down or {}),
        )


def _idle(states: States, robot_id: str) -> bool:
    state = states.get(robot_id)
    return state is not None and state.live.activity == "idle" and state.live.queued == 0


def _unexecuted(
    records: list[TaskRecord], watcher: ObservedStates, robot_id: str, incarnation: Mapping[str, int] | None = None
) -> list[TaskRecord]:
    """The tasks assigned to ``robot_id``'s current process that it has not
    executed (nor dropped), not yet sent round again.  A robot executes its
    jobs in the order assigned, so its last observed ``done`` count says how
    many of them are finished (a job finished in the instant before a crash
    counts as not done: done again rather than lost)."""
    taken = {r.reassigned_from for r in records if r.reassigned_from is not None}
    state = watcher.states.get(robot_id)
    done = state.live.done if state is not None else 0
    fenced = set(state.live.fenced) if state is not None else set()
    first = (incarnation or {}).get(robot_id, 0)
    mine = [r for r in records if r.assigned_to == robot_id and r.seq >= first and r.seq not in fenced]
    return [r for r in mine[done:] if r.seq not in taken and r.orphaned is None]


def _orphans(
    records: list[TaskRecord], watcher: ObservedStates, incarnation: Mapping[str, int] | None = None,
    fenced_off: Collection[str] = (),
    only: Collection[str] | None = None,
) -> list[TaskRecord]:
    """Tasks to send round again: those a robot now down had not executed
    (only once it is ``fenced_off``: it can no longer pick them), and those a
    robot dropped because it lost its lease.  Only the tasks of a robot's
    last process count: the process before a restart had its own, handled
    when it joined again.  A re-run that is dropped again is not sent round
    a third time: no robot of the cluster could hold a lease for it.
    ``only``: these robots' tasks alone."""
    taken = {r.reassigned_from for r in records if r.reassigned_from is not None}
    orphans = []
    for robot_id in fenced_off:
        if robot_id not in watcher.down or (only is not None and robot_id not in only):
            continue
        for record in _unexecuted(records, watcher, robot_id, incarnation):
            record.orphaned = f"{robot_id} went down before executing it: {watcher.down[robot_id]}"
            orphans.append(record)
    for robot_id, state in watcher.states.items():
        if not state.live.fenced or (only is not None and robot_id not in only):
            continue
        first = (incarnation or {}).get(robot_id, 0)
        for record in records:
            if record.assigned_to != robot_id or record.seq < first or record.seq not in state.live.fenced:
                continue
            if record.seq in taken or record.orphaned is not None or record.unavailable is not None:
                continue
            why = f"{robot_id} dropped it unexecuted: {state.live.fence_reason}"
            if record.reassigned_from is not None:
                record.unavailable = why
                continue
            record.orphaned = why
            orphans.append(record)
    return sorted(orphans, key=lambda r: r.seq)


def _task_post(seq: int, name: str, joining: Sequence[str] = ()) -> Request:
    """The POST of task ``seq``.  The task stream orders joins: every robot
    admits the joiners at this task."""
    body = cbor2.dumps({"seq": seq, "object": name, **({"join": list(joining)} if joining else {})})
    return Request(Method.POST, "/tasks", payload=body, content_format=ContentFormat.CBOR)


async def _wait_for(
    watcher: ObservedStates, predicate: Callable[[States], bool], timeout: float, what: str
) -> States:
    try:
        return await watcher.wait(predicate, timeout)
    except TimeoutError:
        raise TeamError(f"timed out after {timeout:g}s waiting for {what}") from None


async def _drain(stream: asyncio.StreamReader, tail: list[str], keep: int = 20) -> None:
    """Read a child's output so it never blocks on a full pipe; keep the last lines."""
    while line := await stream.readline():
        tail.append(line.decode(errors="replace").rstrip())
        del tail[:-keep]
