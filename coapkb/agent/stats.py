"""A robot's statistics, as served on ``GET /robot/stats`` and kept in team records.

The wire form (CBOR or JSON) is :meth:`RobotStats.to_dict`; readers (the team
harness, the benchmark) rebuild the record with :meth:`RobotStats.from_dict`
and use its fields, so the keys are spelled here only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..transport.base import TrafficCounters
from .local_health import LatenessStats
from .query_handler import QueryStats


@dataclass(frozen=True, slots=True)
class Recharge:
    """One charge a robot made before task ``seq``: at the dock (aisle, rack),
    from ``arrive_wh`` up to ``full_wh``."""

    seq: int
    dock: tuple[int, int]
    arrive_wh: float
    full_wh: float

    def to_dict(self) -> dict[str, Any]:
        return {"seq": self.seq, "dock": list(self.dock), "arrive_wh": round(self.arrive_wh, 6),
                "full_wh": round(self.full_wh, 6)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Recharge:
        aisle, rack = data["dock"]
        return cls(int(data["seq"]), (int(aisle), int(rack)), float(data["arrive_wh"]), float(data["full_wh"]))


@dataclass(frozen=True, slots=True)
class RobotStats:
    """One robot's traffic counters and query statistics at one moment."""

    robot_id: str
    transport: str
    strategy: str
    query_wire: str
    #: The client's reliability description (``describe()``: profile and
    #: per-peer estimates).  Its shape differs by reliability profile, so it
    #: stays a mapping; ``None`` for transports without one (ZeroMQ).
    retransmission: Mapping[str, Any] | None
    #: The same for the server's notifications.
    server_retransmission: Mapping[str, Any] | None
    #: ``None`` while the robot has no server (never, once it has started).
    server: TrafficCounters | None
    client: TrafficCounters
    #: Counts and the latency (seconds, rounded to microseconds) of each remote query.
    queries: QueryStats = field(default_factory=QueryStats)
    executed: int = 0
    idle: bool = False
    #: Tasks whose jobs this robot dropped unexecuted: it lost its lease (the fence).
    fenced: list[int] = field(default_factory=list)
    #: The charges it made at a dock, in order.
    recharges: list[Recharge] = field(default_factory=list)
    #: How late its own event loop ran (local health), if measured.
    loop_lateness: LatenessStats | None = None

    @property
    def traffic(self) -> TrafficCounters:
        """Client and server counters together."""
        return self.client + (self.server or TrafficCounters())

    @property
    def spurious_retransmissions(self) -> int:
        """Retransmissions the client's reliability layer found needless (per
        peer, profiles that detect them); 0 where nothing is detected."""
        peers = (self.retransmission or {}).get("peers") or {}
        return sum(int(p.get("spurious_retransmissions", 0)) for p in peers.values())

    def to_dict(self) -> dict[str, Any]:
        """The wire form (key names and order as served since the first version)."""
        return {
            "robot_id": self.robot_id,
            "transport": self.transport,
            "strategy": self.strategy,
            "query_wire": self.query_wire,
            "retransmission": self.retransmission,
            "server_retransmission": self.server_retransmission,
            "server": None if self.server is None else self.server.as_dict(),
            "client": self.client.as_dict(),
            "queries": self.queries.as_dict(),
            "remote_latencies_s": list(self.queries.remote_latencies),
            "executed": self.executed,
            "idle": self.idle,
            # Added for the fence and for charging; only when there is
            # something to say, so the usual form stays as it was.
            **({"fenced": list(self.fenced)} if self.fenced else {}),
            **({"recharges": [r.to_dict() for r in self.recharges]} if self.recharges else {}),
            **({"loop_lateness": self.loop_lateness.as_dict()} if self.loop_lateness is not None else {}),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RobotStats:
        """The inverse of :meth:`to_dict` (a decoded ``GET /robot/stats`` body)."""
        queries = data.get("queries") or {}
        server = data.get("server")
        return cls(
            robot_id=str(data["robot_id"]),
            transport=str(data["transport"]),
            strategy=str(data["strategy"]),
            query_wire=str(data["query_wire"]),
            retransmission=data.get("retransmission"),
            server_retransmission=data.get("server_retransmission"),
            server=None if server is None else TrafficCounters.from_dict(server),
            client=TrafficCounters.from_dict(data["client"]),
            queries=QueryStats(
                local=int(queries.get("local", 0)),
                remote=int(queries.get("remote", 0)),
                failed=int(queries.get("failed", 0)),
                cached=int(queries.get("cached", 0)),
                failovers=int(queries.get("failovers", 0)),
                hedged=int(queries.get("hedged", 0)),
                pushed=int(queries.get("pushed", 0)),
                remote_latencies=[float(x) for x in data.get("remote_latencies_s") or ()],
            ),
            executed=int(data.get("executed", 0)),
            idle=bool(data.get("idle", False)),
            fenced=[int(seq) for seq in data.get("fenced") or ()],
            recharges=[Recharge.from_dict(r) for r in data.get("recharges") or ()],
            loop_lateness=LatenessStats.from_dict(data["loop_lateness"]) if data.get("loop_lateness") else None,
        )
