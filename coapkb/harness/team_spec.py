"""What a team run is asked to be: its size and mode, transport, KB
layout, security and discovery (:class:`TeamSpec`), the faults scheduled
into it (:class:`Fault`), and the error a team that cannot start or finish
raises (:class:`TeamError`).

:mod:`.team` starts the processes such a spec describes; the simulator
(:mod:`coapkb.sim`) runs the same spec on a virtual clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..agent.lease import lease_duration_s
from ..agent.observed_states import liveness_floor_s
from ..agent.query_handler import QUERY_WIRES
from ..config import DISCOVERY_METHODS, KB_MODULES, STRATEGIES
from ..feeder import FeederError, FeederSettings
from ..transport import SCHEMES, transport_for
from ..world import CLUSTER_SIZE

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
