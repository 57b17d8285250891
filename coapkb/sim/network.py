"""The simulated network: the one transport interface over seeded, faulty links.

Every message between two simulated processes crosses a directed
:class:`Link` that may lose it (independently, or in bursts: a two-state
Gilbert-Elliott channel), delay it (a base delay plus jitter, so messages
overtake each other) or deliver it twice; a partition drops whatever
crosses it, both ways.  On top, the transport behaves as CoAP's does for
the code above it:

* a request is retried on an RFC 6298 timeout (doubling) until its
  caller's deadline, each try a new exchange, as the CoAP client's
  reliability layer sends it (a fresh token and message ID): the server
  runs every try that reaches it, and the answer to any try answers the
  request.  A datagram delivered twice is one exchange, answered again
  from the server's exchange cache (RFC 7252 4.5).  An Observe
  registration is confirmable, one exchange however often it is sent, as
  the CoAP client sends it;
* a request to an endpoint whose process is dead fails at once (the
  kernel's ICMP port unreachable), unless a partition drops that too;
* an observation (RFC 7641) registers with a request; each change is a
  notification, sent once and never acknowledged (NON) but for every
  ``confirm_every``-th and those the service marks ``confirm``, as the CoAP
  server does (NotificationTypes): those are confirmable, retried until
  acknowledged, superseded by a newer one, and dropped with the observer
  after ``NOTIFY_TRIES`` -- the client is not told, as in CoAP, and must
  notice by its own requests.

What it does not model: the CoAP reliability layer's own timing (when it
hedges a retry, which :attr:`LinkModel.hedge` draws at random instead;
congestion windows, airtime), Block-wise transfer, message sizes on the
wire, and security.  Those are tested over real sockets.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
import logging
import random
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ..agent.observed_states import OUTCOME_PATH
from ..agent.robot_state import RobotState
from ..transport.base import Endpoint, PeerGone, PeerTimeout, PeerUnreachable, Service, TrafficCounters, handle_safely
from ..transport.messages import Request, Response
from ..transport.rtt import RttEstimator
from .loop import Process, Scheduler

if TYPE_CHECKING:
    from ..transport import ClientSecurity, Reliability
    from ..transport.security import ServerSecurity

log = logging.getLogger(__name__)

#: RFC 7252's MAX_TRANSMIT_WAIT: how long an observation's registration is tried.
REGISTRATION_TIMEOUT_S = 93.0
#: How long a server remembers an answered exchange (RFC 7252's EXCHANGE_LIFETIME).
EXCHANGE_LIFETIME_S = 247.0
#: Tries of one notification before the server drops its observer.
NOTIFY_TRIES = 5
#: Bytes a message costs beside its payload (CoAP header, token, options): a nominal figure.
HEADER_BYTES = 12


#: The least a message held back (:attr:`LinkModel.late`) is late by: longer
#: than a try's timeout on these links, so its sender's retry overtakes it.
LATE_MIN_S = 0.5
#: The spacing of a hedged retry's two copies (the reliability layer's, on a fast link).
HEDGE_GAP_S = 0.01


@dataclass(frozen=True)
class LinkModel:
    """How every directed link between two processes treats a message."""

    #: One-way delay, seconds, and uniform jitter on top (messages reorder when it exceeds their spacing).
    delay_s: float = 0.002
    jitter_s: float = 0.001
    #: Independent loss probability of each message.
    loss: float = 0.0
    #: Bursty loss (a two-state Gilbert-Elliott channel in time): the share
    #: of time a link spends in bad periods, their mean length, and the loss
    #: probability during one (a robot behind a shelf, a forklift passing).
    burst: float = 0.0
    burst_s: float = 0.5
    burst_loss: float = 0.8
    #: Probability that a message is delivered twice.
    duplicate: float = 0.0
    #: Probability that a message is held back, and for how long at most: a
    #: radio's link-layer retries or a queue in a relay deliver it seconds
    #: late, after the sender's own retry of it and what the sender sent next.
    late: float = 0.0
    late_s: float = 3.0
    #: Probability that a retry goes out as two exchanges, ``HEDGE_GAP_S``
    #: apart: the client's hedged copy on a lossy or new path
    #: (docs/reliability.md, "redundancy"), both run by the server.
    hedge: float = 0.0

    def __post_init__(self) -> None:
        for name in ("loss", "burst", "burst_loss", "duplicate", "late", "hedge"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be a probability, got {getattr(self, name)}")
        if self.burst >= 1 or self.burst_s <= 0:
            raise ValueError("burst must be below 1 and burst_s positive")
        if self.delay_s < 0 or self.jitter_s < 0 or self.late_s < LATE_MIN_S:
            raise ValueError("delay and jitter must not be negative")


class Link:
    """One direction between two processes; remembers its burst state."""

    def __init__(self, model: LinkModel) -> None:
        self.model = model
        #: The current or next bad period: [start, end).
        self._bad = (float("inf"), float("inf"))

    def _in_burst(self, now: float, rng: random.Random) -> bool:
        model = self.model
        if model.burst <= 0:
            return False
        start, end = self._bad
        if start == float("inf"):
            start = now + rng.expovariate(model.burst / (model.burst_s * (1 - model.burst)))
            end = start + rng.expovariate(1 / model.burst_s)
        while now >= end:  # periods alternate: good ones long enough for the share asked
            start = end + rng.expovariate(model.burst / (model.burst_s * (1 - model.burst)))
            end = start + rng.expovariate(1 / model.burst_s)
        self._bad = (start, end)
        return now >= start

    def copies(self, now: float, rng: random.Random) -> list[float]:
        """The delays of the copies of a message sent at ``now`` that arrive ([] = lost)."""
        model = self.model
        loss = model.burst_loss if self._in_burst(now, rng) else model.loss
        if loss > 0 and rng.random() < loss:
            return []
        count = 2 if model.duplicate > 0 and rng.random() < model.duplicate else 1
        # Drawn only where the model holds messages back: a seed's other draws stay as they were.
        late = rng.uniform(LATE_MIN_S, model.late_s) if model.late > 0 and rng.random() < model.late else 0.0
        return [late + model.delay_s + (rng.random() * model.jitter_s if model.jitter_s else 0.0)
                for _ in range(count)]


class SimNetwork:
    """Which process serves which endpoint, the links between processes, and partitions."""

    def __init__(self, scheduler: Scheduler, rng: random.Random, model: LinkModel,
                 trace: Callable[[str], None] | None = None) -> None:
        self.scheduler = scheduler
        self.rng = rng
        self.model = model
        self._trace = trace
        self._links: dict[tuple[str, str], Link] = {}
        self._servers: dict[Endpoint, SimServer] = {}
        #: Partitions in force, by name: the pairs of processes that cannot reach each other.
        self._partitions: dict[str, set[tuple[str, str]]] = {}
        self._cut: set[tuple[str, str]] = set()
        self._ids = itertools.count(1)
        self.sent = 0
        self.lost = 0
        #: (robot, incarnation) -> when each of its outcome reports (notification
        #: or answer) reached the feeder, and the jobs done it told.
        self.reports: dict[tuple[str, int], list[tuple[float, int]]] = {}
        #: Called with every answer a server gives (once per exchange, not per
        #: retransmission): the checker's view of what a process really said.
        self.answer_hooks: list[Callable[[Process, Request, Response], None]] = []

    # ------------------------------------------------------------- faults

    def cut(self, name: str, side: Iterable[str], other: Iterable[str]) -> None:
        """Partition ``side`` from ``other`` (process names), both ways, until ``heal(name)``."""
        pairs = {(a, b) for a in side for b in other}
        self._partitions[name] = pairs | {(b, a) for a, b in pairs}
        self._cut = set().union(*self._partitions.values())

    def isolated(self, process: str) -> bool:
        """Whether a partition in force cuts ``process`` off from anyone."""
        return any(a == process for a, _ in self._cut)

    def heal(self, name: str) -> None:
        self._partitions.pop(name, None)
        self._cut = set().union(*self._partitions.values())

    # ------------------------------------------------------------- delivery

    def _note(self, text: str) -> None:
        if self._trace is not None:
            self._trace(text)

    def carry(self, src: Process, dst: Process, what: str, deliver: Callable[[], None],
              report: bytes | None = None) -> None:
        """Send a message from ``src`` to ``dst``: ``deliver`` runs in ``dst``'s
        loop when (and as often as) it arrives.  ``report``: the payload of a
        robot's outcome on its way to the feeder (what it tells is noted)."""
        self.sent += 1
        if (src.name, dst.name) in self._cut:
            self.lost += 1
            self._note(f"cut {src.name}>{dst.name} {what}")
            return
        link = self._links.get((src.name, dst.name))
        if link is None:
            link = self._links[(src.name, dst.name)] = Link(self.model)
        delays = link.copies(self.scheduler.clock.now, self.rng)
        if not delays:
            self.lost += 1
            self._note(f"lost {src.name}>{dst.name} {what}")
            return
        self._note(f"send {src.name}>{dst.name} {what}" + (" (twice)" if len(delays) > 1 else ""))
        if report is not None and dst.name == "feeder":
            deliver = self._reported(src, report, deliver)
        for delay in delays:
            dst.loop.call_at(self.scheduler.clock.now + delay, _if_alive, dst, deliver)

    def _reported(self, robot: Process, payload: bytes, deliver: Callable[[], None]) -> Callable[[], None]:
        """``deliver``, noting when a robot's outcome reached the feeder and
        how many jobs it said were done (the checker asks whether a pick was
        reported before its robot died)."""
        try:
            done = RobotState.decode(payload).live.done
        except ValueError:
            return deliver

        def arrived() -> None:
            self.reports.setdefault((robot.name, robot.incarnation), []).append((self.scheduler.clock.now, done))
            deliver()
        return arrived

    def server_at(self, endpoint: Endpoint) -> SimServer | None:
        return self._servers.get(endpoint)

    def for_process(self, process: Process) -> ProcessNetwork:
        """The network as ``process`` sees it (its :class:`~coapkb.host.Network`)."""
        return ProcessNetwork(self, process)

    def _bind(self, server: SimServer) -> None:
        old = self._servers.get(server.endpoint)
        if old is not None and old.process.alive and not old.closed:
            raise OSError(f"{server.endpoint} is already in use")
        self._servers[server.endpoint] = server

    def next_id(self) -> int:
        return next(self._ids)


#: A confirmable message's first timeout on a path with no sample (RFC 6298).
INITIAL_RTO_S = 1.0


def _rto(estimator: RttEstimator) -> float:
    """A confirmable message's first timeout on a path."""
    return estimator.rto(k=4.0, granularity=0.01, floor=0.2, ceiling=8.0, initial=INITIAL_RTO_S)


def _if_alive(process: Process, deliver: Callable[[], None]) -> None:
    if process.alive:
        deliver()


class ProcessNetwork:
    """:class:`coapkb.host.Network` for one simulated process."""

    def __init__(self, network: SimNetwork, process: Process) -> None:
        self.network = network
        self.process = process

    async def open_client(self, scheme: str, *, reliability: Reliability | None = None,
                          security: ClientSecurity | None = None,
                          options: Mapping[str, Any] | None = None) -> SimClient:
        return SimClient(self.network, self.process)

    async def serve(self, service: Service, endpoint: Endpoint, *, reliability: Reliability | None = None,
                    security: ServerSecurity | None = None,
                    options: Mapping[str, Any] | None = None) -> SimServer:
        server = SimServer(self.network, self.process, service, endpoint,
                           confirm_every=reliability.confirm_every if reliability is not None else 1)
        self.network._bind(server)
        return server


class SimServer:
    """A service on an endpoint of the simulated network."""

    def __init__(self, network: SimNetwork, process: Process, service: Service, endpoint: Endpoint, *,
                 confirm_every: int = 1) -> None:
        self.network = network
        self.process = process
        self.service = service
        self.endpoint = endpoint
        #: Of each observation's notifications, every this many is confirmable.
        self.confirm_every = confirm_every
        self.counters = TrafficCounters()
        self.closed = False
        #: (client, exchange) -> its answer once known (None while it runs), oldest first.
        #: (client, request, try) -> when it came, and its answer once given.
        self._exchanges: OrderedDict[tuple[int, int, int], tuple[float, Response | None]] = OrderedDict()
        self._observers: dict[tuple[int, int], _Observer] = {}

    @property
    def up(self) -> bool:
        return self.process.alive and not self.closed

    def receive(self, client: SimClient, xid: int, request: Request, observe: _Observation | None,
                attempt: int = 0) -> None:
        """A copy of try ``attempt`` of request ``xid`` from ``client`` arrived
        (a negative ``attempt``: the hedged copy of that try, an exchange of its own)."""
        counters = self.counters
        counters.messages_received += 1
        counters.bytes_received += len(request.payload) + HEADER_BYTES
        key = (client.id, xid, 0 if observe is not None else attempt)
        known = self._exchanges.get(key)
        if known is not None:
            if known[1] is not None:  # answered: the answer again, not a second run
                self._reply(client, xid, request.path, known[1])
            return
        now = self.network.scheduler.clock.now
        self._exchanges[key] = (now, None)
        while self._exchanges and next(iter(self._exchanges.values()))[0] < now - EXCHANGE_LIFETIME_S:
            self._exchanges.popitem(last=False)
        self.process.hold(self.process.loop.create_task(self._serve(key, client, xid, request, observe)))

    async def _serve(self, key: tuple[int, int, int], client: SimClient, xid: int, request: Request,
                     observe: _Observation | None) -> None:
        if observe is not None and observe.key not in self._observers:
            observer = _Observer(self, client, observe, request)
            self._observers[observe.key] = observer
            observer.start()
        response = await handle_safely(self.service, request, log)
        for hook in self.network.answer_hooks:
            hook(self.process, request, response)
        if key in self._exchanges:
            self._exchanges[key] = (self._exchanges[key][0], response)
        self._reply(client, xid, request.path, response)

    def _reply(self, client: SimClient, xid: int, path: str, response: Response) -> None:
        self.counters.messages_sent += 1
        self.counters.bytes_sent += len(response.payload) + HEADER_BYTES
        self.network.carry(self.process, client.process, f"ans#{xid} {path} {response.status.dotted}",
                           lambda: client.answered(xid, response),
                           response.payload if path == OUTCOME_PATH and response.status.is_success else None)

    def forget(self, key: tuple[int, int]) -> None:
        observer = self._observers.pop(key, None)
        if observer is not None:
            observer.stop()

    async def aclose(self) -> None:
        self.closed = True
        for key in list(self._observers):
            self.forget(key)


class _Observer:
    """The server's side of one observation: notifies each change."""

    def __init__(self, server: SimServer, client: SimClient, observation: _Observation, request: Request) -> None:
        self.server = server
        self.client = client
        self.observation = observation
        self.request = request
        self.changed = asyncio.Event()
        #: Set by an acknowledgement or a change: what a notification in flight waits for.
        self.woken = asyncio.Event()
        self.acked_seq = 0
        self._unsubscribe: Callable[[], None] = lambda: None
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        def changed() -> None:
            self.changed.set()
            self.woken.set()

        self._unsubscribe = self.server.service.subscribe(self.request.path, changed)
        self._task = self.server.process.hold(self.server.process.loop.create_task(self._run()))

    def stop(self) -> None:
        self._unsubscribe()
        if self._task is not None:
            self._task.cancel()

    def ack(self, seq: int, reset: bool) -> None:
        if reset:
            self.server.forget(self.observation.key)
            return
        self.acked_seq = max(self.acked_seq, seq)
        self.woken.set()

    async def _run(self) -> None:
        server, network = self.server, self.server.network
        seq = 0
        estimator = self.client.estimator(server.endpoint)  # the path as the client measured it
        attempt = 0
        while True:
            await self.changed.wait()
            self.changed.clear()
            response = await handle_safely(server.service, self.request, log)
            for hook in network.answer_hooks:  # a notification answers the registration again
                hook(server.process, self.request, response)
            seq += 1
            if not (response.confirm or seq % server.confirm_every == 0):
                server.counters.messages_sent += 1
                server.counters.bytes_sent += len(response.payload) + HEADER_BYTES
                network.carry(server.process, self.client.process, f"ntf {self.request.path} #{seq} non",
                              functools.partial(self.observation.notified, seq, response, False),
                              response.payload if self.request.path == OUTCOME_PATH else None)
                continue
            rto = _rto(estimator)
            # RFC 7641 4.5.2: a newer state replaces a notification still in
            # flight at once, keeping its retransmission count and timeout.
            while attempt < NOTIFY_TRIES:
                server.counters.messages_sent += 1
                server.counters.bytes_sent += len(response.payload) + HEADER_BYTES
                if attempt:
                    server.counters.retransmissions += 1
                # Bound now: this datagram delivers what it carried, even if a
                # newer state replaces the notification before it lands.
                network.carry(server.process, self.client.process, f"ntf {self.request.path} #{seq}",
                              functools.partial(self.observation.notified, seq, response),
                              response.payload if self.request.path == OUTCOME_PATH else None)
                try:
                    async with asyncio.timeout(rto * 2 ** attempt):
                        while True:
                            self.woken.clear()
                            if self.acked_seq >= seq or self.changed.is_set():
                                break
                            await self.woken.wait()
                except TimeoutError:
                    attempt += 1
                    continue
                if self.acked_seq >= seq:
                    attempt = 0
                break  # acknowledged, or superseded: the newer state goes out next
            else:
                # RFC 7641 4.5: a notification never acknowledged ends the observation.
                network._note(f"drop-observer {server.process.name} {self.request.path} of {self.client.process.name}")
                self._unsubscribe()
                server._observers.pop(self.observation.key, None)
                return


class _Observation:
    """The client's side of one observation: the newest notification not yet taken."""

    def __init__(self, client: SimClient, peer: Endpoint) -> None:
        self.client = client
        self.peer = peer
        self.key = (client.id, client.network.next_id())
        self.latest_seq = 0
        self.pending: Response | None = None
        self.arrived = asyncio.Event()
        self.closed = False
        #: The registration's answer, until it comes: a notification that
        #: overtakes it completes it instead (a notification is a response
        #: with the registration's token, RFC 7641 section 3.2).
        self.registration: asyncio.Future[Response] | None = None

    def notified(self, seq: int, response: Response, confirmable: bool = True) -> None:
        client = self.client
        client.counters.messages_received += 1
        client.counters.bytes_received += len(response.payload) + HEADER_BYTES
        server = client.network.server_at(self.peer)
        # A CON is acknowledged; a NON gets a Reset only if nobody takes it.
        if server is not None and (confirmable or self.closed or client.closed):
            closed = self.closed or client.closed
            observation_key = self.key
            client.network.carry(client.process, server.process, f"{'rst' if closed else 'ack'} ntf #{seq}",
                                 lambda: _acknowledge(server, observation_key, seq, closed))
        if self.closed or seq <= self.latest_seq:
            return  # an old or repeated notification (RFC 7641 4.4: the newest wins)
        self.latest_seq = seq
        if self.registration is not None and not self.registration.done():
            self.registration.set_result(response)
            return
        self.pending = response
        self.arrived.set()


def _acknowledge(server: SimServer, key: tuple[int, int], seq: int, reset: bool) -> None:
    observer = server._observers.get(key)
    if observer is not None:
        observer.ack(seq, reset)


class SimClient:
    """The client side for one simulated process."""

    def __init__(self, network: SimNetwork, process: Process) -> None:
        self.network = network
        self.process = process
        self.id = network.next_id()
        self.counters = TrafficCounters()
        self.closed = False
        self._waiting: dict[int, asyncio.Future[Response]] = {}
        self._paths: dict[Endpoint, RttEstimator] = {}

    def estimator(self, peer: Endpoint) -> RttEstimator:
        estimator = self._paths.get(peer)
        if estimator is None:
            estimator = self._paths[peer] = RttEstimator()
        return estimator

    def answered(self, xid: int, response: Response) -> None:
        """An answer's datagram arrived.  Reading and matching it takes the
        stack another turn of the loop, as a real one's (the datagram, then
        the exchange it answers): a timeout due in the same turn as the
        arrival fires first, as on a process that got the CPU late."""
        self.counters.messages_received += 1
        self.counters.bytes_received += len(response.payload) + HEADER_BYTES
        self.process.loop.call_soon(self._settle, xid, response)

    def _settle(self, xid: int, response: Response) -> None:
        waiting = self._waiting.get(xid)
        if waiting is not None and not waiting.done():
            waiting.set_result(response)

    def _unreachable(self, xid: int, peer: Endpoint) -> None:
        waiting = self._waiting.get(xid)
        if waiting is not None and not waiting.done():
            waiting.set_exception(PeerGone(f"{peer}: port unreachable (nobody listens there)"))

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        """Send ``request`` confirmably; :class:`PeerUnreachable` after ``timeout``
        seconds without an answer, or at once if the peer's process is gone."""
        return await self._exchange(peer, request, timeout, None)

    async def _exchange(self, peer: Endpoint, request: Request, timeout: float,
                        observe: _Observation | None) -> Response:
        if self.closed:
            raise PeerUnreachable(f"{peer}: this client is closed")
        loop = asyncio.get_running_loop()
        xid = self.network.next_id()
        answer: asyncio.Future[Response] = loop.create_future()
        self._waiting[xid] = answer
        if observe is not None:
            observe.registration = answer
        deadline = loop.time() + timeout
        estimator = self.estimator(peer)
        rto = _rto(estimator)
        first_sent = loop.time()
        try:
            for attempt in itertools.count():
                self._send(peer, xid, request, observe, attempt)
                if attempt and observe is None and self._hedged():
                    loop.call_at(loop.time() + HEDGE_GAP_S, self._send_copy, peer, xid, request, answer, attempt)
                wait = min(rto * 2 ** attempt, 8.0, deadline - loop.time())
                if wait > 0:
                    await asyncio.wait([answer], timeout=wait)
                if answer.done():
                    if attempt == 0 and answer.exception() is None:  # Karn: no sample from a retried exchange
                        estimator.on_sample(loop.time() - first_sent)
                    return answer.result()
                if loop.time() >= deadline:
                    raise PeerTimeout(f"{peer}: no answer within {timeout:g}s")
            raise AssertionError("unreachable")
        finally:
            del self._waiting[xid]
            if not answer.done():
                answer.cancel()
            elif not answer.cancelled():
                answer.exception()  # an ICMP error in the same turn as a cancellation: seen, not leaked

    def _hedged(self) -> bool:
        """Whether this retry goes out twice (drawn only where the model hedges)."""
        model = self.network.model
        return model.hedge > 0 and self.network.rng.random() < model.hedge

    def _send_copy(self, peer: Endpoint, xid: int, request: Request, answer: asyncio.Future[Response],
                   attempt: int) -> None:
        """A hedged retry's second copy, a new exchange of its own, unless answered meanwhile."""
        if not answer.done() and not self.closed:
            self._send(peer, xid, request, None, attempt, hedge=True)

    def _send(self, peer: Endpoint, xid: int, request: Request, observe: _Observation | None, attempt: int,
              hedge: bool = False) -> None:
        self.counters.messages_sent += 1
        self.counters.bytes_sent += len(request.payload) + HEADER_BYTES
        if attempt:
            self.counters.retransmissions += 1
        network = self.network
        server = network.server_at(peer)
        what = (f"req#{xid} {request.method} {request.path}" + (f" try {attempt + 1}" if attempt else "")
                + (" hedge" if hedge else ""))
        if server is None or not server.up:
            # Nobody listens: the kernel there answers ICMP, which crosses the link like any message.
            target = server.process if server is not None else None
            if target is None or (self.process.name, target.name) not in network._cut:
                network._note(f"unreachable {self.process.name}>{peer} {what}")
                self.process.loop.call_at(network.scheduler.clock.now + 2 * network.model.delay_s,
                                          self._unreachable, xid, peer)
            return
        exchange = -attempt if hedge else attempt
        network.carry(self.process, server.process, what, lambda: server.receive(self, xid, request, observe, exchange))

    async def observe(self, peer: Endpoint, request: Request) -> AsyncIterator[Response]:
        """The current representation of ``request.path``, then one per change
        that reaches this client; the server may drop the observation
        silently (a notification never acknowledged), as a CoAP server does."""
        observation = _Observation(self, peer)
        try:
            yield await self._exchange(peer, request, REGISTRATION_TIMEOUT_S, observation)
            while True:
                await observation.arrived.wait()
                observation.arrived.clear()
                if self.closed:
                    raise PeerUnreachable(f"{peer}: this client is closed")
                response, observation.pending = observation.pending, None
                if response is not None:
                    yield response
        finally:
            observation.closed = True

    async def aclose(self) -> None:
        self.closed = True
