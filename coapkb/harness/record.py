"""What a team run leaves behind: its set-up, the feeder's task records
(:class:`~coapkb.feeder.record.TaskRecord`), the faults injected and the
robots' statistics.

The record belongs to the harness, not to the feeder: it names the team's
set-up (mode, strategy, query wire) and the injected faults, which only the
harness knows; the feeder's part of it is the task records.
:meth:`TeamRecord.to_dict` is the JSON that ``coapkb team --record`` writes
(the same keys and layout as before these were dataclasses);
:meth:`TeamRecord.from_dict` reads such a file back.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from ..agent.stats import RobotStats
from ..agent.task_assigner import robot_sort_key
from ..feeder.record import FateCounts, TaskRecord
from ..transport.base import TrafficCounters


@dataclass
class FaultEvent:
    """A failure injected during a run, when it happened, and how long the
    feeder took to declare the robot down (kills only)."""

    action: str
    robot: str
    #: Seconds after the first task was fed.
    at_s: float
    detected_after_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"action": self.action, "robot": self.robot, "at_s": self.at_s,
                "detected_after_s": self.detected_after_s}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FaultEvent:
        detected = data.get("detected_after_s")
        return cls(str(data["action"]), str(data["robot"]), float(data["at_s"]),
                   None if detected is None else float(detected))


@dataclass(frozen=True)
class TeamRecord:
    """One team run: its set-up, every task in the order given, times and statistics."""

    mode: str
    transport: str
    strategy: str
    query_wire: str
    robots: list[str]
    clusters: list[list[str]]
    tasks: list[TaskRecord]
    #: Feeding the first task until every cluster decided its last one, seconds.
    coordination_s: float
    #: Until every robot also finished executing, seconds.
    completion_s: float
    robot_stats: dict[str, RobotStats]
    #: The task feeder's own transport counters.
    feeder_traffic: TrafficCounters
    #: Failures injected (``--kill``, ``--restart``).
    faults: list[FaultEvent] = field(default_factory=list)
    #: Robots the feeder declared down: robot -> why.
    down: dict[str, str] = field(default_factory=dict)

    @property
    def disputed(self) -> list[TaskRecord]:
        """Tasks on which the robots disagreed or one of them failed."""
        return [t for t in self.tasks if not t.agreed]

    def to_dict(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "transport": self.transport,
            "strategy": self.strategy,
            "query_wire": self.query_wire,
            "robots": list(self.robots),
            "clusters": [list(c) for c in self.clusters],
            "tasks": [t.to_dict() for t in self.tasks],
            "coordination_s": round(self.coordination_s, 6),
            "completion_s": round(self.completion_s, 6),
            "robot_stats": {r: s.to_dict() for r, s in self.robot_stats.items()},
            "feeder_traffic": self.feeder_traffic.as_dict(),
            "faults": [f.to_dict() for f in self.faults],
            "down": dict(self.down),
            "fates": asdict(FateCounts.of(self.tasks)),  # derived, like a task's "fate"; ignored on reading
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TeamRecord:
        """A record read back from ``coapkb team --record``'s JSON."""
        return cls(
            mode=str(data["mode"]),
            transport=str(data["transport"]),
            strategy=str(data["strategy"]),
            query_wire=str(data["query_wire"]),
            robots=[str(r) for r in data["robots"]],
            clusters=[[str(r) for r in c] for c in data["clusters"]],
            tasks=[TaskRecord.from_dict(t) for t in data["tasks"]],
            coordination_s=float(data["coordination_s"]),
            completion_s=float(data["completion_s"]),
            robot_stats={r: RobotStats.from_dict(s) for r, s in data["robot_stats"].items()},
            feeder_traffic=TrafficCounters.from_dict(data["feeder_traffic"]),
            faults=[FaultEvent.from_dict(f) for f in data.get("faults") or ()],
            down={str(r): str(why) for r, why in (data.get("down") or {}).items()},
        )


def summarise(record: TeamRecord) -> str:
    """A human summary of a team record."""
    tasks = record.tasks
    done = [t for t in tasks if t.fate == "assigned"]
    per_robot: dict[str, int] = {}
    for t in done:
        assert t.assigned_to is not None
        per_robot[t.assigned_to] = per_robot.get(t.assigned_to, 0) + 1
    stats = record.robot_stats.values()
    traffic = sum((s.traffic for s in stats), TrafficCounters())
    local = sum(s.queries.local for s in stats)
    remote = sum(s.queries.remote for s in stats)
    cached = sum(s.queries.cached for s in stats)
    lines = [
        f"{len(record.robots)} robots, {record.mode}, {record.transport}, {record.strategy}: "
        + FateCounts.of(tasks).line(),
        "assigned: " + ", ".join(f"{r} {n}" for r, n in sorted(per_robot.items(), key=lambda x: robot_sort_key(x[0]))),
        f"coordination {record.coordination_s:.2f} s, completion {record.completion_s:.2f} s",
        f"robots sent {traffic.bytes_sent:,} B in {traffic.messages_sent:,} messages, "
        f"received {traffic.bytes_received:,} B; "
        f"queries: {local} local, {remote} remote, {cached} answered from the cache",
    ]
    charged = sorted(((r, len(robot.recharges)) for r, robot in record.robot_stats.items() if robot.recharges),
                     key=lambda x: robot_sort_key(x[0]))
    if charged:
        lines.append("recharged at a dock: " + ", ".join(f"{r} {n}x" for r, n in charged))
    for event in record.faults:
        detected = "" if event.detected_after_s is None else f", declared down {event.detected_after_s:.1f} s later"
        lines.append(f"{event.action} {event.robot} at {event.at_s:.1f} s{detected}")
    for task in tasks:
        if task.fate == "not-found":
            lines.append(f"not found: task {task.seq} {task.object} (cluster {task.cluster}): {task.not_found}")
    for robot_id, robot in sorted(record.robot_stats.items(), key=lambda x: robot_sort_key(x[0])):
        if robot.fenced:
            lines.append(f"{robot_id} dropped task(s) {', '.join(map(str, robot.fenced))} unpicked: "
                         "it had lost its lease (fenced)")
    return "\n".join(lines)
