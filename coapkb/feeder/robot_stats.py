"""Each robot's statistics (``GET /robot/stats``), downloaded by the feeder
once a run is over, for its record."""

from __future__ import annotations

from collections.abc import Sequence

import cbor2

from ..agent.stats import RobotStats
from ..transport.base import TransportError
from ..transport.messages import ContentFormat, Method, Request
from .channel import Channel

STATS_PATH = "/robot/stats"
#: Requests for one robot's statistics before the feeder gives up on them.
STATS_TRIES = 3


async def collect_stats(channel: Channel, robots: Sequence[str], maybe: Sequence[str] = ()) -> dict[str, RobotStats]:
    """Every robot's statistics; those of ``maybe`` if they answer."""
    stats = {}
    for robot_id in [*robots, *maybe]:
        try:
            stats[robot_id] = await stats_of(channel, robot_id)
        except TransportError:
            if robot_id in maybe:
                continue
            raise
    return stats


async def stats_of(channel: Channel, robot_id: str) -> RobotStats:
    """``robot_id``'s statistics, asked up to :data:`STATS_TRIES` times: a
    burst of loss on a radio link can swallow every retransmission of one
    download, and a run's record is worth another try (found in the
    simulator)."""
    request = Request(Method.GET, STATS_PATH, accept=ContentFormat.CBOR)
    for attempt in range(1, STATS_TRIES + 1):
        try:
            response = await channel.client.request(
                channel.endpoint(robot_id), request, timeout=channel.settings.query_timeout_s
            )
        except TransportError:
            if attempt == STATS_TRIES:
                raise
            continue
        return RobotStats.from_dict(cbor2.loads(response.payload))
    raise AssertionError("unreachable")
