"""A team run as Foxglove sees it: an MCAP file and, optionally, the live
Foxglove WebSocket server, fed from what the feeder sees.

Channels (docs/recording.md says what each carries):

=====================  =====================  ==================================================
topic                  schema                 what
=====================  =====================  ==================================================
``/warehouse``         foxglove.SceneUpdate   aisles, racks, charging docks, the depot (at the start, and to a viewer subscribing)
``/robots/poses``      foxglove.FrameTransforms  each robot's frame in ``warehouse`` as it reports
``/robots/markers``    foxglove.SceneUpdate   a labelled marker per robot in its own frame
``/robots/state``      JSON ``coapkb.RobotState``  activity, job, queue, jobs done, battery, load
``/tasks``             JSON ``coapkb.Task``   each task's record: decisions, costs, reasons, fate
``/robots/traffic``    JSON ``coapkb.Traffic``  per robot, sampled and at the end: bytes, retransmissions, latencies
``/log``               foxglove.Log           the run's log lines (WARNING and above)
=====================  =====================  ==================================================

MCAP metadata ``coapkb``: the command, versions, the team, its link settings.

foxglove-sdk (its core in Rust) is imported here only, and this module only
by the commands that record: a robot's start-up does not change.
"""

from __future__ import annotations

import json
import logging
import platform
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import foxglove
from foxglove import channels

from ..errors import CoapkbError
from ..world import DEPOT, Layout, Position
from .stats import percentile

if TYPE_CHECKING:
    from ..agent.robot_state import RobotState
    from ..agent.stats import RobotStats
    from ..feeder.record import TaskRecord
    from .record import TeamRecord

#: The frame the warehouse is drawn in; each robot has a frame of its own name.
WORLD_FRAME = "warehouse"
#: Log lines at or above this level go to ``/log``.
LOG_LEVEL = logging.WARNING

_STATE_SCHEMA = {
    "type": "object", "title": "coapkb.RobotState",
    "properties": {
        "robot": {"type": "string"}, "activity": {"type": "string"}, "executing": {"type": ["string", "null"]},
        "queued": {"type": "integer"}, "done": {"type": "integer"}, "aisle": {"type": "number"},
        "rack": {"type": "number"}, "battery_wh": {"type": "number"}, "load_kg": {"type": "number"},
        "payload_kg": {"type": "number"}, "last_task": {"type": "integer"},
    },
}
_TASK_SCHEMA = {
    "type": "object", "title": "coapkb.Task",
    "properties": {
        "seq": {"type": "integer"}, "cluster": {"type": "integer"}, "object": {"type": "string"},
        "fate": {"type": "string"}, "assigned_to": {"type": ["string", "null"]},
        "decisions": {"type": "object"}, "costs": {"type": "object"}, "reasons": {"type": "object"},
        "skip_reason": {"type": ["string", "null"]}, "not_found": {"type": ["string", "null"]},
        "coordination_s": {"type": "number"},
    },
}
_TRAFFIC_SCHEMA = {
    "type": "object", "title": "coapkb.Traffic",
    "properties": {
        "robot": {"type": "string"}, "bytes_sent": {"type": "integer"}, "bytes_received": {"type": "integer"},
        "messages_sent": {"type": "integer"}, "retransmissions": {"type": "integer"},
        "query_p50_ms": {"type": ["number", "null"]}, "query_p99_ms": {"type": ["number", "null"]},
        "executed": {"type": "integer"},
    },
}


class RecordingError(CoapkbError):
    """The recording could not be opened (the file, the port)."""


class RunRecorder:
    """Logs a run to an MCAP file (``path``) and/or the live server
    (``live``: host and port), one Foxglove context for both."""

    def __init__(self, path: Path | None, live: tuple[str, int] | None, robots: Sequence[str],
                 layout: Layout | None, docks: Sequence[Position] = (), depot: Position = DEPOT,
                 metadata: Mapping[str, str] | None = None) -> None:
        self._messages = foxglove.messages
        self.context = foxglove.Context()
        self.path = path
        self._mcap = None
        self.server = None
        try:
            if path is not None:
                self._mcap = foxglove.open_mcap(str(path), allow_overwrite=True, context=self.context)
            if live is not None:
                self.server = foxglove.start_server(name="coapkb", host=live[0], port=live[1],
                                                    context=self.context, server_listener=_Viewers(self))
        except Exception as exc:  # noqa: BLE001 - the SDK's errors have no common class: a file or a port
            self.close()
            raise RecordingError(f"cannot record: {exc}") from None
        self.robots = list(robots)
        self.layout = layout
        self._scene = channels.SceneUpdateChannel("/warehouse", context=self.context)
        self._poses = channels.FrameTransformsChannel("/robots/poses", context=self.context)
        self._markers = channels.SceneUpdateChannel("/robots/markers", context=self.context)
        self._log = channels.LogChannel("/log", context=self.context)
        self._states = foxglove.Channel("/robots/state", schema=_STATE_SCHEMA, message_encoding="json",
                                        context=self.context)
        self._tasks = foxglove.Channel("/tasks", schema=_TASK_SCHEMA, message_encoding="json", context=self.context)
        self._traffic = foxglove.Channel("/robots/traffic", schema=_TRAFFIC_SCHEMA, message_encoding="json",
                                         context=self.context)
        if self._mcap is not None and metadata:
            self._mcap.write_metadata("coapkb", {k: str(v) for k, v in metadata.items()})
        self.messages = 0
        #: topic -> the scene drawn there: sent again to a viewer subscribing later.
        self._drawn: dict[str, Any] = {}
        self._handler = _LogHandler(self)
        if layout is not None:
            self._draw_warehouse(layout, docks, depot)

    # ------------------------------------------------------------ the scene

    def _xy(self, aisle: float, rack: float) -> tuple[float, float]:
        """Metres in the warehouse frame; fractional places (a robot between
        two) interpolate between their neighbours."""
        assert self.layout is not None
        low = Position(max(1, min(self.layout.aisles, int(aisle))), max(0, min(self.layout.racks_per_aisle + 1, int(rack))))
        x, y = self.layout.xy(low)
        return x + (aisle - low.aisle) * self.layout.aisle_spacing_m, y + (rack - low.rack) * self.layout.rack_length_m

    def _draw_warehouse(self, layout: Layout, docks: Sequence[Position], depot: Position) -> None:
        m = self._messages
        racks = []
        for aisle in range(1, layout.aisles + 1):
            for rack in range(1, layout.racks_per_aisle + 1):
                x, y = layout.xy(Position(aisle, rack))
                # The racks line the aisle on its right: offset by half a spacing.
                racks.append(m.CubePrimitive(
                    pose=m.Pose(position=m.Vector3(x=x + layout.aisle_spacing_m / 2, y=y, z=0.5),
                                orientation=m.Quaternion(w=1.0)),
                    size=m.Vector3(x=0.8, y=layout.rack_length_m * 0.9, z=1.0),
                    color=m.Color(r=0.55, g=0.45, b=0.3, a=0.9)))
        spheres = [m.SpherePrimitive(pose=m.Pose(position=_vector(m, *layout.xy(d), 0.3), orientation=m.Quaternion(w=1.0)),
                                     size=m.Vector3(x=0.6, y=0.6, z=0.6), color=m.Color(r=0.1, g=0.7, b=0.2, a=1.0))
                   for d in docks]
        texts = [m.TextPrimitive(pose=m.Pose(position=_vector(m, *layout.xy(depot), 1.0), orientation=m.Quaternion(w=1.0)),
                                 billboard=True, font_size=14.0, scale_invariant=True,
                                 color=m.Color(r=1, g=1, b=1, a=1), text="depot")]
        scene = m.SceneUpdate(entities=[
            m.SceneEntity(frame_id=WORLD_FRAME, id="racks", cubes=racks),
            m.SceneEntity(frame_id=WORLD_FRAME, id="docks", spheres=spheres, texts=texts),
        ])
        self._draw(self._scene, "/warehouse", scene)
        markers = m.SceneUpdate(entities=[
            m.SceneEntity(frame_id=robot, id=robot, frame_locked=True,
                          cubes=[m.CubePrimitive(pose=m.Pose(position=m.Vector3(z=0.3), orientation=m.Quaternion(w=1.0)),
                                                 size=m.Vector3(x=0.7, y=0.7, z=0.6),
                                                 color=m.Color(r=0.2, g=0.4, b=0.9, a=1.0))],
                          texts=[m.TextPrimitive(pose=m.Pose(position=m.Vector3(z=1.0), orientation=m.Quaternion(w=1.0)),
                                                 billboard=True, font_size=12.0, scale_invariant=True,
                                                 color=m.Color(r=1, g=1, b=1, a=1), text=robot)])
            for robot in self.robots])
        self._draw(self._markers, "/robots/markers", markers)

    def _draw(self, channel: Any, topic: str, scene: Any) -> None:
        self._drawn[topic] = (channel, scene)
        self._log_message(channel, scene)

    def draw_again(self, topic: str) -> None:
        """A viewer subscribed to ``topic`` after it was drawn: draw it again."""
        drawn = self._drawn.get(topic)
        if drawn is not None:
            self._log_message(*drawn)

    # ------------------------------------------------------------ events

    def robot_state(self, robot_id: str, state: RobotState) -> None:
        """A robot's state as the feeder observed it: its pose and its job."""
        m = self._messages
        live, plan = state.live, state.plan
        now = time.time_ns()
        if self.layout is not None:
            x, y = self._xy(live.aisle, live.rack)
            transform = m.FrameTransform(timestamp=_stamp(m, now), parent_frame_id=WORLD_FRAME, child_frame_id=robot_id,
                                         translation=m.Vector3(x=x, y=y, z=0.0), rotation=m.Quaternion(w=1.0))
            self._log_message(self._poses, m.FrameTransforms(transforms=[transform]), now)
        self._log_message(self._states, {
            "robot": robot_id, "activity": live.activity, "executing": live.executing, "queued": live.queued,
            "done": live.done, "aisle": live.aisle, "rack": live.rack, "battery_wh": plan.battery_wh,
            "load_kg": plan.load_kg, "payload_kg": plan.payload_kg, "last_task": plan.seq,
        }, now)

    def task(self, record: TaskRecord) -> None:
        data = record.to_dict()
        self._log_message(self._tasks, {key: data.get(key) for key in _TASK_SCHEMA["properties"]} | {
            "fate": record.fate})

    def finished(self, record: TeamRecord) -> None:
        """The run's end: every task's final fate, and each robot's traffic."""
        self.final_fates(record.tasks)
        self.traffic(record.robot_stats)

    def final_fates(self, tasks: Sequence[TaskRecord]) -> None:
        """The tasks whose fate changed after they were decided (not found at
        the shelf, sent round again), once more: the last word on a task."""
        for task in tasks:
            if task.fate in ("not-found", "reassigned"):
                self.task(task)

    def traffic(self, robot_stats: Mapping[str, RobotStats]) -> None:
        for robot_id, stats in sorted(robot_stats.items()):
            latencies = stats.queries.remote_latencies
            self._log_message(self._traffic, {
                "robot": robot_id, "bytes_sent": stats.traffic.bytes_sent,
                "bytes_received": stats.traffic.bytes_received, "messages_sent": stats.traffic.messages_sent,
                "retransmissions": stats.traffic.retransmissions,
                "query_p50_ms": _ms(percentile(latencies, 50)), "query_p99_ms": _ms(percentile(latencies, 99)),
                "executed": stats.executed,
            })

    def log_record(self, record: logging.LogRecord) -> None:
        m = self._messages
        level = {logging.DEBUG: m.LogLevel.Debug, logging.INFO: m.LogLevel.Info,
                 logging.WARNING: m.LogLevel.Warning, logging.ERROR: m.LogLevel.Error,
                 logging.CRITICAL: m.LogLevel.Fatal}.get(record.levelno, m.LogLevel.Warning)
        now = int(record.created * 1e9)
        self._log_message(self._log, m.Log(timestamp=_stamp(m, now), level=level, message=record.getMessage(),
                                           name=record.name, file=record.pathname, line=record.lineno), now)

    @property
    def log_handler(self) -> logging.Handler:
        """Add it to a logger: its lines at ``LOG_LEVEL`` and above go to ``/log``."""
        return self._handler

    def _log_message(self, channel: Any, message: Any, now: int | None = None) -> None:
        channel.log(message, log_time=now if now is not None else time.time_ns())
        self.messages += 1

    def close(self, *, keep_serving: bool = False) -> None:
        """Close the MCAP file, and stop the live server unless ``keep_serving``
        (a viewer opened late still sees the whole run; close again to stop it)."""
        if self._mcap is not None:
            self._mcap.close()
            self._mcap = None
        if self.server is not None and not keep_serving:
            self.server.stop()
            self.server = None


class _Viewers(foxglove.ServerListener):
    """The live server's listener: a viewer subscribing to the scene gets it
    (it was drawn once, at the start)."""

    def __init__(self, recorder: RunRecorder) -> None:
        self._recorder = recorder

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self._recorder.draw_again(channel.topic)


class _LogHandler(logging.Handler):
    def __init__(self, recorder: RunRecorder) -> None:
        super().__init__(LOG_LEVEL)
        self._recorder = recorder

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self._recorder.log_record(record)
        except Exception:  # noqa: BLE001 - a log line must never stop the run
            self.handleError(record)


def warehouse(location_kb: Path) -> tuple[Layout | None, list[Position]]:
    """The layout and the charging docks, from the Location KB's file (or a
    folder holding ``Location.owl``)."""
    from ..kb.store import KnowledgeBase, named_rows
    from ..world import layout_from_row

    location = KnowledgeBase.load([location_kb / "Location.owl" if location_kb.is_dir() else location_kb])
    rows = named_rows(location, "warehouse-layout")
    docks = named_rows(location, "charging-docks")
    layout = layout_from_row(rows[0]) if rows else None
    return layout, [Position(int(r["aisle_no"]), int(r["rack_no"])) for r in docks]


def run_metadata(command: Sequence[str], **settings: object) -> dict[str, str]:
    """The MCAP metadata of a run: the command, versions and settings."""
    from importlib.metadata import PackageNotFoundError, version

    def of(package: str) -> str:
        try:
            return version(package)
        except PackageNotFoundError:
            return "?"

    return {"command": " ".join(command), "coapkb": of("coapkb"), "aiocoap": of("aiocoap"),
            "foxglove-sdk": of("foxglove-sdk"), "python": sys.version.split()[0], "platform": platform.platform(),
            **{k: json.dumps(v) if not isinstance(v, str) else v for k, v in settings.items()}}


def _vector(m: Any, x: float, y: float, z: float) -> Any:
    return m.Vector3(x=x, y=y, z=z)


def _stamp(m: Any, ns: int) -> Any:
    return m.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1000, 1)
