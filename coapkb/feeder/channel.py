"""The feeder's line to its team: one client transport and a watcher of
every robot's state, and the requests every part of the feeder makes."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Collection
from dataclasses import dataclass, field

from .. import clock
from ..agent.local_health import LoopHealth
from ..agent.observed_states import OUTCOME_PATH, STATE_PATH, ObservedStates, States, liveness_floor_s
from ..agent.robot_state import RobotState
from ..host import Network, Sockets
from ..transport import ClientSecurity, reliability_for
from ..transport.base import ClientTransport, Endpoint, TransportError
from ..transport.messages import ContentFormat, Method, Request, Response
from .reach import Reach
from .roster import Roster
from .tasks import FeederError


@dataclass(frozen=True)
class FeederSettings:
    """How the feeder talks to the team and how long it waits."""

    transport: str
    #: Wall-clock limit for one task's coordination before the run is declared stuck.
    task_timeout_s: float = 120.0
    #: How long a robot's statistics may take to download.
    query_timeout_s: float = 10.0
    #: The robots' lease (coapkb.agent.lease): a down robot's tasks go round
    #: again once the survivors refused it a lease this long ago; 0 = no fence.
    lease_s: float = 0.0
    #: The robots' link rate (kbit/s), when known: sets the liveness floor.
    link_kbps: float | None = None
    #: What the feeder observes of each robot: its outcome, what the feeder
    #: acts on (RobotState.encode_outcome); or, for a recording, its whole
    #: state, which also says where it is and what it carries.
    watch: str = OUTCOME_PATH

    def __post_init__(self) -> None:
        if self.watch not in (OUTCOME_PATH, STATE_PATH):
            raise ValueError(f"the feeder observes {OUTCOME_PATH} or {STATE_PATH}, not {self.watch}")

    @property
    def watch_request(self) -> Request:
        """What the feeder reads of a robot, asked once (the watcher observes it all along)."""
        return Request(Method.GET, self.watch, accept=ContentFormat.CBOR)



@dataclass
class Channel:
    """Open with :meth:`open`; shared by the feeding loop and the membership."""

    client: ClientTransport
    watcher: ObservedStates
    roster: Roster
    settings: FeederSettings
    #: Robot -> its task posts in flight (see :meth:`forget_posts`).
    #: Per robot, its posts in flight, in the order sent (a dict as an ordered set: cancelled in that order).
    _posting: dict[str, dict[asyncio.Future[Response], None]] = field(default_factory=dict)
    #: Whether the feeder itself is cut off from its robots.
    reach: Reach = field(init=False)

    def __post_init__(self) -> None:
        self.reach = Reach(self.client, self.watcher, self.roster, self.settings.watch_request)

    @classmethod
    @contextlib.asynccontextmanager
    async def open(cls, roster: Roster, settings: FeederSettings, security: ClientSecurity | None = None,
                   network: Network | None = None) -> AsyncIterator[Channel]:
        """A client (on ``network``: the sockets unless a simulator gives one)
        and a watcher (with liveness: the feeder declares a robot down when
        its requests fail, and then waits for the survivors only)."""
        network = network or Sockets()
        # Every exchange with a robot crosses that robot's link both ways:
        # its rate times the feeder's tries as it does the robots' own (the
        # airtime of a state answer in the timeout).  Without it the feeder
        # of a 60-robot team timed its tries as on loopback and sent 13,000
        # retries whose answers filled the robots' links.
        reliability = reliability_for(settings.transport, link_kbps=settings.link_kbps)
        client = await network.open_client(settings.transport, reliability=reliability,
                                           security=security)
        # Local health: the feeder's own loop lateness, so it does not declare
        # robots down for its own busy CPU.
        health = LoopHealth()
        health.start()
        try:
            watcher = ObservedStates(
                client, roster.endpoints, settings.watch, liveness=True,
                liveness_floor_s=liveness_floor_s(settings.link_kbps), health=health,
            )
            channel = cls(client, watcher, roster, settings)
            watcher.confirm_silence = channel.reach.silent_to_the_feeder_only
            watcher.listeners.append(channel.reach.heard_from)
            watcher.start()
            try:
                yield channel
            finally:
                await watcher.aclose()
        finally:
            await health.aclose()
            await client.aclose()

    def endpoint(self, robot_id: str) -> Endpoint:
        return self.roster.endpoints[robot_id]

    async def wait_for(self, predicate: Callable[[States], bool], timeout: float, what: str, *,
                       pending: Callable[[States], Collection[str]] | None = None, of: int = 0) -> States:
        """The robots' states once ``predicate`` holds; a FeederError naming
        ``what`` after ``timeout``.  ``pending``: the robots still awaited of
        ``of``, asked again once one of them came (ObservedStates.wait)."""
        try:
            return await self.watcher.wait(predicate, timeout, pending=pending, of=of)
        except TimeoutError:
            raise FeederError(f"timed out after {timeout:g}s waiting for {what}") from None

    async def state(self, robot_id: str, timeout: float) -> RobotState | None:
        """``robot_id``'s state asked once; None if it does not answer with one."""
        try:
            response = await self.client.request(self.endpoint(robot_id), self.settings.watch_request,
                                                 timeout=timeout)
            return RobotState.decode(response.payload) if response.status.is_success else None
        except (TransportError, ValueError):
            return None

    async def post_task(self, robot_id: str, request: Request, seq: int, name: str) -> Response | None:
        """POST a task to one robot; if it does not answer, ask the watcher
        whether it is down (then the task goes to the survivors only) or
        post again (a robot recognises a repeated post).  The robot's answer,
        None if it is down."""
        watcher = self.watcher
        deadline = clock.monotonic() + self.settings.task_timeout_s
        while True:
            exchange = asyncio.ensure_future(self.client.request(
                self.endpoint(robot_id), request, timeout=max(watcher.request_timeout_s, 1.0)
            ))
            posting = self._posting.setdefault(robot_id, {})
            posting[exchange] = None
            try:
                response = await exchange
            except asyncio.CancelledError:
                current = asyncio.current_task()
                if exchange.cancelled() and (current is None or not current.cancelling()):
                    return None  # forgotten (forget_posts): the robot restarted, the post was its old process's
                raise
            except TransportError as exc:
                await watcher.probe(robot_id)
                if robot_id in watcher.down:
                    return None
                if clock.monotonic() > deadline:
                    raise FeederError(f"{robot_id} refused task {seq} ({name}): {exc}") from None
                continue
            finally:
                posting.pop(exchange, None)
            if not response.status.is_success:
                await watcher.probe(robot_id)  # a restarted robot refuses: it is down for the team
                if robot_id in watcher.down:
                    return None
                raise FeederError(f"{robot_id} refused task {seq} ({name}): {response}")
            return response

    def forget_posts(self, robot_id: str) -> None:
        """Stop the task posts still in flight to ``robot_id``: it restarted,
        and a retransmission of its old process's post would reach the new
        process (same endpoint) as a task of its own, which the new process
        took and executed before the task went round again (found in the
        simulator)."""
        for exchange in self._posting.pop(robot_id, {}):
            exchange.cancel()
