"""One simulated run: the real feeder and robots on the simulated network,
under one seed's fault schedule, and the history the checker judges.

Every robot is the real :class:`~coapkb.agent.robot.Robot` (its controller,
team view, lease, query handler and executor) started on a
:class:`~coapkb.host.Host` of its own simulated process; the feeder is the
real :class:`~coapkb.feeder.Feeder` in another.  A third process carries out
the schedule: it kills, freezes and restarts robots, cuts links and starves
loops at the scheduled simulated times.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import logging
import os
import random
import re
import sys
import tempfile
import time
import weakref
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO, cast

from ..agent.observed_states import liveness_floor_s
from ..agent.robot import Robot
from ..agent.task_executor import PICKED
from ..config import RobotConfig
from ..feeder import Feeder, FeederError, Roster, TaskRecord
from ..harness.kbs import kbs_for_team
from ..harness.record import FaultEvent as RecordedFault
from ..harness.record import TeamRecord
from ..harness.team import DEFAULT_ONTOLOGIES, TeamSpec, product_names, robot_configs, team_record
from ..host import Host
from ..kb.store import KnowledgeBase
from ..model.results import QueryResult
from ..transport.base import Endpoint, TransportError
from ..world.truth import WorldTruth
from ..world.vocabulary import ONTOLOGIES
from .catch_up import CatchUps
from .disk import SimDisk
from .faults import FaultEvent, FaultMix, Schedule, draw_schedule
from .loop import Process, Scheduler, SimLoop, SimulationError
from .network import SimNetwork
from .observed import FilesQuads, Grant, GrantLog, Shelf, Take
from .observers import ObserverView, draw_observers, observers_caught_up, views
from .operator import Holders, Operator, WriteOp, shows
from .saboteur import Forgery, Saboteur

log = logging.getLogger(__name__)

#: A run still going after this much simulated time is stuck.
DEFAULT_LIMIT_S = 3600.0
#: How long the holders may take, once the last write is answered and the
#: faults healed, to agree (anti-entropy rounds every few seconds).
REPLICATION_SETTLE_S = 60.0
#: A data folder's journal is compacted into a snapshot past this many bytes
#: (a robot's: 1 MiB, which no run reaches): a few dozen records.
COMPACT_AFTER_BYTES = 2048


@dataclass(frozen=True)
class SimSpec:
    """What every run of a profile shares; the seed draws the rest."""

    robots: int = 3
    tasks: int = 10
    strategy: str = "compute-by-all"
    faults: FaultMix = field(default_factory=FaultMix)
    ontologies: Path = DEFAULT_ONTOLOGIES
    #: As ``coapkb team``: simulated motion runs this many times faster than real motion.
    time_scale: float = 50.0
    query_timeout_s: float = 5.0
    task_timeout_s: float = 120.0
    limit_s: float = DEFAULT_LIMIT_S
    #: How many robots of a cluster hold each KB module (as ``coapkb team --replication``).
    replication: int = 2
    #: These tasks instead of ``tasks`` drawn by the seed.
    task_list: tuple[str, ...] | None = None
    #: These fault events instead of those drawn by the seed (the link faults still come from ``faults``).
    schedule: tuple[FaultEvent, ...] | None = None
    #: Called with each task's record once decided, and the run: a scenario's own faults (tests).
    scenario: Callable[[TaskRecord, SimulatedTeam], None] | None = None
    #: An operator's writes to random robots' KBs during the run (0: the KBs stay read-only).
    writes: int = 0
    #: Every robot of a cluster starts where its first robot does, with the
    #: same battery and load: equal costs, so the tie-break decides.
    ties: bool = False
    #: Every robot keeps its writes in a data folder of its own (a journal,
    #: fsynced before a write is answered): a kill keeps the folder, and may
    #: tear the journal's tail; a restart restores from it.
    storage: bool = False
    #: Observers of the written knowledge (``coapkb query --observe``), each
    #: of one module at one holder, judged at the end (:mod:`.observers`).
    observers: int = 0
    #: Each replica's bound on dots waiting past a gap and tombstones
    #: (:attr:`~coapkb.kb.replica.ReplicaLimits.cloud_max`; 0: the default,
    #: 10,000, which a run's writes never reach).  Small, a holder refuses
    #: deltas at the bound (5.03, never 2.04) and takes them again in order.
    waiting_max: int = 0

    def team(self) -> TeamSpec:
        return TeamSpec(
            robots=self.robots, strategy=self.strategy, ontologies=self.ontologies, security=False,
            query_timeout_s=self.query_timeout_s, task_timeout_s=self.task_timeout_s,
            time_scale=self.time_scale, link_kbps=35.0 if self.faults.lossy else None, replication=self.replication,
            kb_writable=self.writes > 0,
        )

    @property
    def horizon_s(self) -> float:
        """Over how much simulated time the faults are drawn: about the run's
        length (a cluster decides and executes a task in well under a second
        of simulated time on these settings)."""
        per_cluster = self.tasks / max(1, self.robots // 3)
        return 1.0 + 0.6 * per_cluster


@dataclass(frozen=True)
class Pick:
    """One pick that counted, as the picking robot logged it."""

    robot: str
    incarnation: int
    seq: int
    object: str
    at_s: float


@dataclass
class RunResult:
    """What one seed's run gave (picklable: runs travel between worker processes)."""

    seed: int
    schedule: str
    record: TeamRecord | None
    #: Why the run did not finish (a hang, the feeder gave up), or None.
    error: str | None
    picks: list[Pick]
    #: Robots out at the end (killed and not restarted, or left frozen): none of their state is final.
    crashes: list[str]
    #: Exceptions a robot or the feeder logged with their traceback (:class:`_History`).
    exceptions: list[str] = field(default_factory=list)
    #: The tasks the feeder was given, in order.
    fed: list[str] = field(default_factory=list)
    #: Invariants broken (filled in by :mod:`.invariants`), and disagreements the schedule explains.
    violations: list[str] = field(default_factory=list)
    excused: list[str] = field(default_factory=list)
    #: Bounded-state readings at the end: name -> (value, bound).
    bounds: dict[str, tuple[int, int]] = field(default_factory=dict)
    events: list[FaultEvent] = field(default_factory=list)
    #: The links lose messages (loss or bursts in the fault mix).
    lossy: bool = False
    #: When the first task was fed (simulated s): the schedule's times count from here.
    fed_at: float = 0.0
    #: (robot, incarnation) -> when each of its outcome reports reached the feeder, and the jobs done it told.
    reports: dict[tuple[str, int], list[tuple[float, int]]] = field(default_factory=dict)
    #: The fate counts in one line (kept when the record is dropped).
    fates: str = ""
    #: Each task's coordination, from its post to the feeder's having its
    #: decisions, simulated s (kept when the record is dropped).
    coordination_s: list[float] = field(default_factory=list)
    #: The operator's writes, as they were answered.
    writes: list[WriteOp] = field(default_factory=list)
    #: (module, value) -> how an acknowledged value's last copy died, in a
    #: run without data folders: the loss the schedule excuses.
    lost_copies: dict[tuple[str, int], str] = field(default_factory=dict)
    #: (module, value) -> how the last copy of a settled delete of it died,
    #: in a run without data folders: the value back is excused.
    lost_removals: dict[tuple[str, int], str] = field(default_factory=dict)
    #: The forged syncs sent, and how each was answered.
    forgeries: list[Forgery] = field(default_factory=list)
    #: How long each restarted holder took to show what its co-holders showed
    #: at its restart (simulated s; :mod:`.catch_up`).
    catch_up_s: list[float] = field(default_factory=list)
    #: Queries answered by a restarted holder before it caught up (:mod:`.catch_up`).
    stale_reads: list[str] = field(default_factory=list)
    #: Per module: how many robots hold it.
    holders: dict[str, int] = field(default_factory=dict)
    #: At the end, per module: each running holder's version of it.
    versions: dict[str, dict[str, str]] = field(default_factory=dict)
    #: At the end, per module and running holder: the log values its queries see.
    values: dict[str, dict[str, frozenset[int]]] = field(default_factory=dict)
    #: At the end, per module: the holders whose triples differ from the first
    #: holder's, with a few of the differing triples (empty: equal).
    differences: dict[str, list[str]] = field(default_factory=dict)
    #: Moments two holders of a module were at one version with different triples.
    split_versions: list[str] = field(default_factory=list)
    #: Where a dead robot's data folder would restore otherwise than the robot held.
    restores: list[str] = field(default_factory=list)
    #: Each observer of the written knowledge at the end, and what its robot shows.
    observers: list[ObserverView] = field(default_factory=list)
    #: Every take at a shelf and every lease granted, from outside the robots.
    takes: list[Take] = field(default_factory=list)
    grants: list[Grant] = field(default_factory=list)
    #: The robots' lease, seconds (0: no fence).
    lease_s: float = 0.0
    #: (cluster, seq) -> when the feeder had the task's decision (simulated s).
    decided_at: dict[tuple[int, int], float] = field(default_factory=dict)
    #: Liveness: when the last fault healed, when every task was settled and
    #: when the replicas agreed (simulated s; None: never), and the bounds.
    healed_at: float = 0.0
    settled_at: float | None = None
    converged_at: float | None = None
    settle_bound_s: float = 0.0
    sim_s: float = 0.0
    cpu_s: float = 0.0
    steps: int = 0
    messages: int = 0
    lost: int = 0


class SharedAnswers(KnowledgeBase):
    """A loaded KB whose answers are computed once per worker process and
    shared by every simulated robot that holds it.  The KB is read-only, so
    each robot would compute the very same (immutable) answer: running the
    query once per robot was most of a simulated run's CPU.  Errors are not
    kept: they are raised again each time."""

    #: Distinct queries kept before the memo starts afresh (a bound, not a tuning).
    MAX_ANSWERS = 100_000

    def __init__(self, kb: KnowledgeBase) -> None:
        super().__init__(kb.backend, kb.engine, kb.names, kb.paths, kb.prefixes, kb.etag)
        self._answers: dict[tuple[str, int], QueryResult] = {}

    def query(self, sparql: str, *, row_limit: int = 1000, time_budget_s: float | None = None) -> QueryResult:
        key = (sparql, row_limit)
        answer = self._answers.get(key)
        if answer is None:
            answer = super().query(sparql, row_limit=row_limit, time_budget_s=time_budget_s)
            if len(self._answers) >= self.MAX_ANSWERS:
                self._answers.clear()
            self._answers[key] = answer
        return answer


class KBCache:
    """The KB modules and team configurations, loaded once per worker process:
    they are read-only, so every simulated robot may share them."""

    def __init__(self, scratch: Path | None = None) -> None:
        #: Where generated KBs go: a folder of their own in ``scratch`` (a
        #: worker's, which its parent removes after the pool ends: a worker
        #: ends without removing its own), else in the temporary folder.
        self._scratch = scratch
        self._kbs: dict[tuple[Path, ...], KnowledgeBase] = {}
        self._configs: dict[TeamSpec, dict[str, RobotConfig]] = {}
        self._products: dict[Path, list[str]] = {}
        self._ontologies: dict[tuple[Path, int, bool], Path] = {}
        self._generated: tempfile.TemporaryDirectory[str] | None = None
        #: The files' quads of the KBs loaded here, for the end of each run's comparison.
        self.files = FilesQuads()

    def load(self, files: Sequence[Path], index_dir: Path | None = None) -> KnowledgeBase:
        key = tuple(files)
        kb = self._kbs.get(key)
        if kb is None:
            kb = self._kbs[key] = SharedAnswers(KnowledgeBase.load(list(files)))
        return kb

    def products(self, ontologies: Path) -> list[str]:
        names = self._products.get(ontologies)
        if names is None:
            names = self._products[ontologies] = product_names(self.load([ontologies / "Object.owl"]))
        return names

    def team(self, spec: SimSpec) -> TeamSpec:
        """``spec``'s team, on KBs that know every robot of it: generated once
        per worker for a team larger than the given KBs know, as ``coapkb
        team`` does (:func:`~coapkb.harness.kbs.kbs_for_team`)."""
        team = spec.team()
        known = self._ontologies.get((spec.ontologies, spec.robots, spec.ties))
        if known is None:
            if self._generated is None:
                self._generated = tempfile.TemporaryDirectory(prefix="coapkb-sim-", dir=self._scratch)
            into = Path(self._generated.name) / f"robots-{spec.robots}"
            known = kbs_for_team(spec.ontologies, team.robot_ids, into).ontologies
            if spec.ties:
                known = uniform_robots(known, Path(self._generated.name) / f"ties-{spec.robots}")
            self._ontologies[(spec.ontologies, spec.robots, spec.ties)] = known
        return dataclasses.replace(team, ontologies=known)

    def configs(self, spec: TeamSpec) -> dict[str, RobotConfig]:
        configs = self._configs.get(spec)
        if configs is None:
            endpoints = {r: Endpoint("coap", f"10.0.0.{i}", 5683) for i, r in enumerate(spec.robot_ids, 1)}
            configs = self._configs[spec] = robot_configs(spec, endpoints)
        return configs


class _History(logging.Handler):
    """The robots' log lines, read as the run's history: picks (the
    executor's :data:`PICKED` line), the exceptions logged with their
    traceback (a bug whatever the schedule: the code caught what it did not
    expect, to keep the robot alive) and, when tracing, every warning."""

    def __init__(self, names: dict[SimLoop, Process], clock: Callable[[], float],
                 trace: Callable[[str], None] | None) -> None:
        super().__init__(logging.INFO)
        self.names = names
        self.clock = clock
        self.trace = trace
        self.picks: list[Pick] = []
        self.exceptions: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            loop: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            loop = None
        process = self.names.get(loop) if isinstance(loop, SimLoop) else None
        name = process.name if process is not None else "-"
        if record.msg is PICKED and isinstance(record.args, tuple):
            obj, seq = cast("tuple[object, int]", record.args)  # PICKED's: the object, the task's number (%d)
            incarnation = process.incarnation if process is not None else 0
            self.picks.append(Pick(name, incarnation, int(seq), str(obj),
                                   round(self.clock(), 6)))
            if self.trace is not None:
                self.trace(f"pick {name} task {seq} {obj}")
            return
        if record.levelno >= logging.ERROR and record.exc_info is not None and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            self.exceptions.append(f"{name} at {self.clock():.3f}s: {record.getMessage()}: "
                                   f"{type(exc).__name__}: {exc}"[:300])
        if record.levelno >= logging.WARNING and self.trace is not None:
            self.trace(f"log {name} {record.getMessage()}")


@contextlib.contextmanager
def _capturing(handler: _History) -> Iterator[None]:
    """The package's log through ``handler`` only (no echo to stderr), picks included."""
    package = logging.getLogger("coapkb")
    executor = logging.getLogger("coapkb.agent.task_executor")
    saved = (package.propagate, package.level, executor.level)
    package.addHandler(handler)
    package.propagate = False
    package.setLevel(logging.WARNING)
    executor.setLevel(logging.INFO)
    try:
        yield
    finally:
        package.removeHandler(handler)
        package.propagate, _, _ = saved
        package.setLevel(saved[1])
        executor.setLevel(saved[2])


@contextlib.contextmanager
def _asyncgen_hooks(owner: weakref.WeakKeyDictionary[Any, asyncio.AbstractEventLoop]) -> Iterator[None]:
    """Async generators closed on the loop that ran them, as ``run_forever``
    arranges for one real loop (the simulator steps many)."""

    def first(agen: Any) -> None:
        owner[agen] = asyncio.get_running_loop()

    def finalize(agen: Any) -> None:
        loop = owner.pop(agen, None)
        if loop is not None and not loop.is_closed():
            loop.call_soon(loop.create_task, agen.aclose())

    saved = sys.get_asyncgen_hooks()
    sys.set_asyncgen_hooks(firstiter=first, finalizer=finalize)
    try:
        yield
    finally:
        sys.set_asyncgen_hooks(*saved)


_ROBOT_INDIVIDUAL = re.compile(
    r'(<owl:NamedIndividual rdf:about="[^"]*#(Robot\d+)">.*?</owl:NamedIndividual>)', re.S)


def uniform_robots(ontologies: Path, into: Path) -> Path:
    """``ontologies`` with every robot of the Capability KB made a copy of
    the first one (its grips, payload, battery, speed and energy use): with
    one start for a cluster, every robot costs the same, and the tie-break
    decides every task (``SimSpec.ties``)."""
    into.mkdir(parents=True, exist_ok=True)
    for name in ("Object.owl", "Location.owl"):
        (into / name).write_bytes((ontologies / name).read_bytes())
    text = (ontologies / "Capability.owl").read_text(encoding="utf-8")
    robots = _ROBOT_INDIVIDUAL.findall(text)
    if robots:
        model, first = robots[0]
        text = _ROBOT_INDIVIDUAL.sub(lambda m: model.replace(first + "<", m[2] + "<").replace(
            f"#{first}\"", f"#{m[2]}\""), text)
    (into / "Capability.owl").write_text(text, encoding="utf-8")
    return into


def draw_tasks(names: list[str], count: int, rng: random.Random) -> list[str]:
    return [rng.choice(names) for _ in range(count)]


class SimulatedTeam:
    """One run: the processes, the network, the schedule, and what they left.

    ``controls`` are the faults a scenario may inject itself, from the
    feeder's progress (a robot frozen right after it was given a task), the
    way ``coapkb team``'s tests do with real processes."""

    def __init__(self, spec: SimSpec, seed: int, kbs: KBCache, trace: TextIO | None = None) -> None:
        rng = random.Random(seed)
        self.spec, self.seed, self.kbs = spec, seed, kbs
        self.team = kbs.team(spec)
        drawn = draw_tasks(kbs.products(self.team.ontologies), spec.tasks, random.Random(rng.random()))
        self.tasks = list(spec.task_list) if spec.task_list is not None else drawn
        schedule = draw_schedule(spec.faults, self.team.clusters(), spec.horizon_s, random.Random(rng.random()))
        if spec.schedule is not None:
            schedule = Schedule(schedule.link, tuple(sorted(spec.schedule, key=lambda e: e.at_s)))
        self.schedule = schedule
        scheduler_rng, network_rng, self._boot_rng = (random.Random(rng.random()) for _ in range(3))
        self._out = trace
        self.scheduler = Scheduler(scheduler_rng, self.note)
        self.network = SimNetwork(self.scheduler, network_rng, schedule.link, self.note if trace else None)
        self.configs = kbs.configs(self.team)
        if spec.ties:
            first = {r: self.configs[c[0]].start for c in self.team.clusters() for r in c}
            self.configs = {r: dataclasses.replace(c, start=first[r]) for r, c in self.configs.items()}
        self._data: tempfile.TemporaryDirectory[str] | None = None
        if spec.storage:
            # In memory where the machine has it: the run's crashes are
            # simulated (a torn tail is written, not a power cut), so an
            # fdatasync to a real disk would cost time and prove nothing.
            self._data = tempfile.TemporaryDirectory(prefix="coapkb-sim-data-", dir=_memory_folder())
            self.configs = {r: dataclasses.replace(c, data_dir=Path(self._data.name) / r)
                            for r, c in self.configs.items()}
        self.processes: dict[SimLoop, Process] = {}
        self.current: dict[str, Process] = {}
        self.robots: dict[str, Robot] = {}
        #: The one warehouse every robot of the run finds objects in (or not).
        self.world = WorldTruth()
        clock = lambda: self.scheduler.clock.now  # noqa: E731 - read at each event
        self.shelf = Shelf(self.world, self.processes, clock)
        self.grants = GrantLog(clock)
        self.network.answer_hooks.append(self.grants.answered)
        self.history = _History(self.processes, clock, self.note if trace else None)
        #: The machine's disk the data folders sync to (:mod:`.disk`).
        self.disk = SimDisk()
        self.decided_at: dict[tuple[int, int], float] = {}
        self.settled_at: float | None = None
        self.converged_at: float | None = None
        self.feeder: Feeder | None = None
        self.fed_at: float | None = None
        self.resumed: set[str] = set()
        self.recorded: list[RecordedFault] = []
        #: Set once every task is done: from then on the schedule only heals (no new faults after the run).
        self.ending = False
        #: The holders' KBs, and the operator's writes (``spec.writes``) into them.
        self.holders = Holders(self.configs, self.robots, self.current, lambda: self.elapsed_s, kbs.files)
        self.catch_ups = CatchUps(clock, shows)
        self.network.answer_hooks.append(self.catch_ups.answered)
        self.operator = Operator(self.holders, self.network, clock, self.note, self.catch_ups)
        self._write_seed = rng.random()
        # Drawn last: a seed's other draws stay what they were before disks.
        self.saboteur = Saboteur(self, random.Random(rng.random()))
        # After it, and only with observers: a seed without them runs as before.
        self.observers = draw_observers(
            spec.observers, random.Random(rng.random()), {m: self.holders.of(m) for m in sorted(ONTOLOGIES)},
            lambda robot: self.configs[robot].bind) if spec.observers else []

    def note(self, text: str) -> None:
        """A line of the trace, stamped with the simulated time; the data
        folders' temporary parent as ``DATA`` (its name is drawn afresh at
        every run, and a replay must give the same trace)."""
        if self._out is not None:
            if self._data is not None:
                text = text.replace(self._data.name, "DATA")
            self._out.write(f"{self.scheduler.clock.now:11.6f} {text}\n")

    # ------------------------------------------------------------- processes

    def _spawn(self, name: str) -> Process:
        process = self.scheduler.spawn(name)
        self.processes[process.loop] = process
        self.current[name] = process
        return process

    async def _start_robot(self, robot_id: str, process: Process) -> Robot:
        clock = self.scheduler.clock
        host = Host(self.network.for_process(process), random.Random(self._boot_rng.random()), self.kbs.load,
                    threads=False, wall_ms=lambda: int(clock.now * 1000), world=self.shelf, disk=self.disk)
        robot = await Robot.start(self.configs[robot_id], host=host)
        if robot.keeper is not None:
            # Compacted within a run's few writes, so snapshots are written and restored from too.
            robot.keeper.compact_after_bytes = COMPACT_AFTER_BYTES
        self.robots[robot_id] = robot
        live = robot.replicator.live if robot.replicator is not None else None
        if live is not None and self.spec.waiting_max:
            for replica in live.replicas.values():
                replica.bound_waiting(self.spec.waiting_max)
        self.holders.started(robot_id, live, clock.now)
        if live is not None:
            live.listeners.append(lambda _: self.catch_ups.changed(robot_id, live))
            self.catch_ups.changed(robot_id, live)
        return robot

    # ------------------------------------------------------------- faults

    def inject(self, event: FaultEvent) -> None:
        """Carry out ``event`` now (``event.at_s`` is what the record says)."""
        action, target = event.action, event.targets[0]
        process = self.current[target]
        if (action == "kill" and process.status == "dead") or (action == "restart" and process.status != "dead"):
            # Two faults that overlap on one robot: a power cut killed it
            # before its own kill came, or brought it back before its own
            # restart.  Killing the dead would tear its journal twice (a
            # record that is no prefix of any: a corrupt file), and a second
            # process would find its data folder locked.
            self.note(f"fault {event}: nothing to do, {target} is {'dead' if action == 'kill' else 'running'}")
            return
        self.note(f"fault {event}")
        if action == "kill":
            if not self.spec.storage:
                self.operator.last_copies(target)
            self.catch_ups.killed(target)
            self.scheduler.kill(process)
            self.saboteur.torn_disk(target)
        elif action == "restart":
            self.catch_ups.expect(target, self.operator.owed(target))
            reborn = self._spawn(target)
            feeder = self.feeder

            async def restart() -> None:
                await self._start_robot(target, reborn)
                if feeder is not None:
                    # It joins at the next task fed, as the harness tells the feeder: in the feeder's process.
                    self.scheduler.start(self.current["feeder"], feeder.membership.rejoin(target))

            self.scheduler.start(reborn, restart())
        elif action == "freeze":
            self.scheduler.freeze(process)
        elif action == "resume":
            self.scheduler.resume(process)
            self.resumed.add(target)
        elif action == "cut":
            self.network.cut(target, event.targets, event.other)
        elif action == "heal":
            self.network.heal(target)
        elif action == "starve":
            process.starve(event.amount, (self.fed_at or 0.0) + event.until_s, self.scheduler.clock.now)
        elif action.endswith("-picking"):
            self.saboteur.trap(event)
        elif action == "crash":
            self.saboteur.power_cut(target, event.amount)
        elif action == "forge":
            self.saboteur.forge(target, event.other[0])
        if not action.endswith("-picking"):
            self.recorded.append(RecordedFault(action, "+".join(event.targets), round(self.elapsed_s, 3)))

    @property
    def elapsed_s(self) -> float:
        """Simulated seconds since the first task was fed."""
        return self.scheduler.clock.now - (self.fed_at or 0.0)

    def control(self, action: str, robot: str) -> None:
        """A fault a scenario injects now: kill, restart, freeze or resume ``robot``."""
        self.inject(FaultEvent(round(self.elapsed_s, 3), action, (robot,)))

    async def _run_schedule(self) -> None:
        loop = asyncio.get_running_loop()
        for event in self.schedule.events:
            await asyncio.sleep(max(0.0, (self.fed_at or 0.0) + event.at_s - loop.time()))
            if self.ending and event.action not in ("heal", "resume"):
                continue
            self.inject(event)

    # ------------------------------------------------------------- writes

    # ------------------------------------------------------------- the run

    async def _feed(self, chaos: Process) -> TeamRecord:
        team, feeder_process = self.team, self.current["feeder"]
        roster = Roster({r: c.bind for r, c in self.configs.items()}, team.clusters())
        async with Feeder.open(roster, team.feeder_settings(), None,
                               self.network.for_process(feeder_process)) as feeder:
            self.feeder = feeder
            self.fed_at = started = asyncio.get_running_loop().time()
            schedule = self.scheduler.start(chaos, self._run_schedule())
            writer = None
            if self.spec.writes:
                operator = self._spawn("operator")
                writer = self.scheduler.start(operator, self.operator.write(
                    operator, random.Random(self._write_seed), self.spec.writes, self.spec.horizon_s, started,
                    undo=self.schedule.link.late > 0))
            for observer in self.observers:
                watching = self._spawn(observer.name)
                self.scheduler.start(watching, observer.run(watching, self.network))
            scenario = self.spec.scenario

            def progress(record: TaskRecord) -> None:
                self.decided_at[(record.cluster, record.seq)] = round(self.elapsed_s, 6)
                if scenario is not None:
                    scenario(record, self)
            try:
                outcome = await feeder.feed(self.tasks, progress, started)
                self.ending = True
                # Every partition healed, every robot resumed and idle before the
                # statistics are asked for, as a run's report would be.  Those run
                # in other processes, whose tasks this loop cannot await: look
                # again shortly (simulated time, free).
                # The faults a trap, a power cut or a forger started end too (a
                # robot resumed, restarted): the run ends with every fault healed.
                while (not schedule.done() or not self._settled()  # noqa: ASYNC110 - other processes' state, no event to await
                       or not self.saboteur.done):
                    await asyncio.sleep(0.5)
                self.settled_at = round(self.elapsed_s, 6)
                if writer is not None:
                    # Quiescence for the KBs: the writes delivered and anti-entropy done.
                    while not writer.done():  # noqa: ASYNC110 - as above
                        await asyncio.sleep(0.5)
                    deadline = asyncio.get_running_loop().time() + REPLICATION_SETTLE_S
                    while not self.holders.agree() and asyncio.get_running_loop().time() < deadline:  # noqa: ASYNC110 - as above
                        await asyncio.sleep(0.5)
                    self.converged_at = round(self.elapsed_s, 6) if self.holders.agree() else None
                if self.observers and self.converged_at is not None:
                    await observers_caught_up(self.observers, self.holders.running)
                watcher = feeder.watcher
                alive = [r for r in watcher.alive if self.current[r].status == "running"]
                maybe = [r for r in team.robot_ids if r in self.resumed and r in watcher.down]
                stats = await feeder.collect_stats(alive, maybe)
            finally:
                schedule.cancel()
            return team_record(team, outcome, stats, feeder.traffic, self.recorded, dict(watcher.down))

    @property
    def settle_bound_s(self) -> float:
        """How long after the last fault healed (or the last task was decided,
        whichever is later) every task may take to settle: see
        docs/simulation.md, "Liveness"."""
        return settle_bound_s(self.team.lease_s, self.spec.query_timeout_s, liveness_floor_s(self.team.link_kbps))

    def _writers_bound(self) -> int:
        """The most writers a replica's version vector may name: one per
        robot with data folders (a restart writes on under its folder's
        name), else one per process a robot ran (a life kept in memory that
        could not fence its earlier lives writes under a name of its own;
        docs/knowledge.md, "One name for the lives of a robot kept in
        memory")."""
        return len(self.configs) if self.spec.storage else len(self.holders.lives)

    def _settled(self) -> bool:
        """Every running robot has executed what it holds and sent what it wrote of it."""
        return all(
            robot.executor.live.activity == "idle" and not robot.executor.live.queued
            and (robot.knowledge is None or not robot.knowledge.pending)
            for robot_id, robot in self.robots.items() if self.current[robot_id].status == "running"
        )

    def run(self) -> RunResult:
        """Start the robots, feed the tasks under the schedule, and return what happened."""
        cpu = time.process_time()
        spec, scheduler = self.spec, self.scheduler
        self.note(f"seed {self.seed}: {spec.robots} robots, {len(self.tasks)} tasks, {spec.strategy}; "
                  f"schedule: {self.schedule}")
        self.note(f"tasks: {' '.join(self.tasks)}")
        owner: weakref.WeakKeyDictionary[Any, asyncio.AbstractEventLoop] = weakref.WeakKeyDictionary()
        error: str | None = None
        record: TeamRecord | None = None
        bounds: dict[str, tuple[int, int]] = {}
        gc_was_enabled = gc.isenabled()
        gc.disable()  # collection timing is the one thing refcounting does not fix: keep it out of the run
        try:
            with _capturing(self.history), _asyncgen_hooks(owner):
                starting = [scheduler.start(p, self._start_robot(r, p))
                            for r, p in ((r, self._spawn(r)) for r in self.team.robot_ids)]
                self._spawn("feeder")
                chaos = self._spawn("faults")
                try:
                    scheduler.run(lambda: all(t.done() for t in starting), spec.limit_s)
                    for task in starting:
                        task.result()
                    fed = scheduler.start(self.current["feeder"], self._feed(chaos))
                    scheduler.run(fed.done, spec.limit_s)
                    record = fed.result()
                except (SimulationError, FeederError, TransportError, TimeoutError) as exc:
                    error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                bounds = _bounds(self.robots, scheduler, self._writers_bound())
                versions, values, differences = self.holders.outcome() if spec.writes else ({}, {}, {})
                observed = views(self.observers, self.holders.running())
                catch_up_s = self.catch_ups.finish()
                scheduler.shutdown()  # the end: what is still pending is abandoned, not a crash
                _release_disks(self.robots, self._data)
        finally:
            if gc_was_enabled:
                gc.enable()
        return RunResult(
            seed=self.seed, schedule=str(self.schedule), record=record, error=error, picks=self.history.picks,
            crashes=list(scheduler.crashes), exceptions=list(self.history.exceptions), bounds=bounds,
            events=sorted([*self.schedule.events, *self.saboteur.sprung], key=lambda e: e.at_s),
            lossy=spec.faults.lossy, sim_s=round(scheduler.clock.now, 6), cpu_s=time.process_time() - cpu,
            steps=scheduler.steps, messages=self.network.sent, lost=self.network.lost,
            fed_at=self.fed_at or 0.0, reports=self.network.reports, fed=list(self.tasks),
            writes=list(self.operator.write_log), lost_copies=dict(self.operator.lost_copies),
            lost_removals=dict(self.operator.lost_removals), forgeries=list(self.saboteur.forgeries),
            catch_up_s=catch_up_s, stale_reads=list(self.catch_ups.stale_reads), holders={m: len(self.holders.of(m)) for m in sorted(ONTOLOGIES)},
            versions=versions, values=values, differences=differences,
            split_versions=list(self.holders.split_versions), observers=observed, restores=list(self.saboteur.restores), takes=list(self.shelf.takes), grants=list(self.grants.grants),
            lease_s=self.team.lease_s, decided_at=dict(self.decided_at), healed_at=healed_at(self.schedule.events),
            settled_at=self.settled_at, converged_at=self.converged_at, settle_bound_s=self.settle_bound_s,
        )


def healed_at(events: Sequence[FaultEvent]) -> float:
    """When the last fault of ``events`` ended (s after the first task was fed)."""
    def ended(e: FaultEvent) -> float:
        if e.action.endswith("-picking"):
            return e.until_s + e.amount  # sprung at the latest as it expires
        return e.until_s if e.action == "starve" else e.at_s
    return max((ended(e) for e in events), default=0.0)


def _release_disks(robots: Mapping[str, Robot], data: tempfile.TemporaryDirectory[str] | None) -> None:
    """Every data folder closed and removed (the run is over)."""
    for robot in robots.values():
        if robot.keeper is not None:
            robot.keeper.journal.close()
    if data is not None:
        data.cleanup()


def _memory_folder() -> str | None:
    """A folder in memory (Linux's /dev/shm) if writable here, else None (the temporary folder)."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def settle_bound_s(lease_s: float, query_timeout_s: float, floor_s: float) -> float:
    """How long a healed team may take to settle its last tasks and agree.

    Once every fault has healed, what can still be outstanding is one task
    a fenced or suspected robot dropped: the feeder finds it down (a few
    liveness floors), waits the lease out (``lease_s``), feeds it again,
    its cluster decides it (every question within ``query_timeout_s``,
    asked at most twice), and its robot carries it out.  Twice that sum
    leaves room for one more round of the same (a second task of the same
    robot) and the statistics' collection; the replicas' anti-entropy
    rounds fit well inside it."""
    return 2 * (4 * floor_s + lease_s + 2 * query_timeout_s + EXECUTION_S)


#: The longest a task's execution takes in simulated time (travel, pick and
#: delivery at ``time_scale`` 50).
EXECUTION_S = 5.0


def run_seed(spec: SimSpec, seed: int, kbs: KBCache, trace: TextIO | None = None) -> RunResult:
    """Run ``spec``'s team under seed ``seed``'s schedule; the result's
    ``violations`` are empty until :func:`coapkb.sim.invariants.check` fills them."""
    return SimulatedTeam(spec, seed, kbs, trace).run()


#: Tasks one process may hold at once in a team of N robots: a handful per teammate's exchanges.
TASKS_PER_PEER = 12
TASKS_BASE = 40


def _bounds(robots: dict[str, Robot], scheduler: Scheduler, writers: int) -> dict[str, tuple[int, int]]:
    """State that must stay bounded whatever the schedule: (reading, bound);
    ``writers``: the most writers a replica may know of."""
    peers = len(robots) + 1
    readings: dict[str, tuple[int, int]] = {}
    for robot_id, robot in robots.items():
        bounds = robot.controller.bounds
        readings[f"{robot_id} posts remembered"] = (len(robot.resources.accepted), bounds.posts_remembered)
        readings[f"{robot_id} decisions kept"] = (len(robot.controller.log), bounds.decisions_kept)
        if robot.replicator is not None:
            for module, replica in robot.replicator.live.replicas.items():
                known = set(replica.context.vv) | {d.writer for d in replica.context.cloud}
                readings[f"{robot_id} writers in the version vector of {module}"] = (len(known), writers)
    for process in scheduler.processes:
        if process.alive:
            pending = sum(1 for t in asyncio.all_tasks(process.loop) if not t.done())
            readings[f"{process.name} tasks"] = (pending, TASKS_BASE + TASKS_PER_PEER * peers)
    return readings
