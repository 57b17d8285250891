"""Each robot's statistics (``GET /robot/stats``), downloaded by the feeder
once a run is over, for its record."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

import cbor2

from .. import clock
from ..agent.stats import RobotStats
from ..transport.base import PeerGone, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .channel import Channel

STATS_PATH = "/robot/stats"


async def collect_stats(channel: Channel, robots: Sequence[str], maybe: Sequence[str] = ()) -> dict[str, RobotStats]:
    """Every robot's statistics; those of ``maybe`` if they answer the first time they are asked."""
    stats = {}
    for robot_id in [*robots, *maybe]:
        try:
            stats[robot_id] = await stats_of(channel, robot_id, patient=robot_id not in maybe)
        except TransportError:
            if robot_id in maybe:
                continue
            raise
    return stats


async def stats_of(channel: Channel, robot_id: str, *, patient: bool = True) -> RobotStats:
    """``robot_id``'s statistics, asked again until a task timeout has
    passed: a burst of loss on a radio link
    can swallow every retransmission of one download, and a run's record is
    worth another try.  Three tries were once the rule: at 20 % loss each
    fails about one time in three, and in the simulator one robot's three
    in a row failed, with the run (seed 18 of the progress profile).  Not
    ``patient``: asked once (a robot that may be dead, or a periodic
    sample).  Asked again for a task timeout, a robot killed just before a
    run's end held the statistics of the others, and the fault that was to
    start it again waited behind them until a test's bound."""
    request = Request(Method.GET, STATS_PATH, accept=ContentFormat.CBOR)
    deadline = clock.monotonic() + (channel.settings.task_timeout_s if patient else 0.0)
    while True:
        try:
            response = await channel.client.request(
                channel.endpoint(robot_id), request, timeout=channel.settings.query_timeout_s
            )
        except TransportError as exc:
            if clock.monotonic() >= deadline:
                raise
            if isinstance(exc, PeerGone):
                # Nobody there now: a robot a power cut took at the end of
                # the run, started again (simulator seed 63111 of the storage
                # profile), is asked again once a request's time has passed.
                await asyncio.sleep(channel.settings.query_timeout_s)
            continue
        return RobotStats.from_dict(cbor2.loads(response.payload))
