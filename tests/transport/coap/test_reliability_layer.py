"""The reliability layer (``robust``) on real sockets, through a lossy UDP relay.

A robot's resources are served in this process over CoAP on loopback; the
client reaches them through :class:`~coapkb.bench.linkemu.UdpRelay`, which
drops datagrams at random in both directions (user space, no root).  What
is checked is what the layer promises: every request is answered despite
loss, a retry never runs a query twice, answers come from the try that was
answered (so samples are clean), several requests are in flight at once,
block-wise answers survive lost blocks, notifications arrive, and a dead
peer is reported at once.
"""

from __future__ import annotations

import asyncio
import json
import socket
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from coapkb.bench.linkemu import LinkSpec, UdpRelay
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport import Endpoint, PeerUnreachable, ResourceInfo, open_client, serve
from coapkb.transport.coap import CoapClientTransport
from coapkb.transport.coap.reliability import ReliabilityLayer, ReliabilitySettings
from coapkb.transport.coap.reliability.estimator import LossEstimator, airtime
from coapkb.transport.coap.reliability.layer import PeerPath
from coapkb.transport.coap.reliability.notifications import NotificationTypes
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.router import Router
from coapkb.transport.rtt import RttEstimator

ONTOLOGIES = Path(__file__).resolve().parents[3] / "ontologies"
KB_FILES = [ONTOLOGIES / f"{n}.owl" for n in ("Object", "Location", "Capability")]


# --------------------------------------------------------------------------- estimators (pure)


def test_rtt_estimator_follows_rfc6298() -> None:
    est = RttEstimator()
    assert est.rto(k=4, granularity=0.01, floor=0.05, ceiling=8, initial=1.0) == 1.0
    est.on_sample(0.2)
    assert (est.srtt, est.rttvar) == (0.2, 0.1)
    assert est.rto(k=4, granularity=0.01, floor=0.05, ceiling=8, initial=1.0) == pytest.approx(0.6)
    est.on_sample(0.1)
    assert est.rttvar == pytest.approx(0.75 * 0.1 + 0.25 * 0.1)
    assert est.srtt == pytest.approx(0.875 * 0.2 + 0.125 * 0.1)
    assert est.min_rtt == 0.1 and est.samples == 2
    # The floor and the ceiling hold.
    assert est.rto(k=4, granularity=0.01, floor=1.0, ceiling=8, initial=1.0) == 1.0
    assert est.rto(k=400, granularity=0.01, floor=0.05, ceiling=2, initial=1.0) == 2


def test_loss_estimator_and_airtime() -> None:
    loss = LossEstimator()
    for lost in [True, False, False, False]:
        loss.on_outcome(lost)
    assert loss.rate == pytest.approx(0.25)  # plain average while few outcomes are known
    assert loss.one_way() == pytest.approx(1 - (0.75 ** 0.5))
    assert airtime(100, None) == 0.0
    assert airtime(97, 1000.0) == pytest.approx((97 + 28) * 8 / 1000)


def test_settings_are_validated() -> None:
    with pytest.raises(ValueError):
        ReliabilitySettings(link_kbps=0)
    with pytest.raises(ValueError):
        ReliabilitySettings(min_rto=2.0, initial_rto=1.0)
    with pytest.raises(ValueError):
        ReliabilitySettings(window_min=4, window_max=2)
    with pytest.raises(ValueError):
        ReliabilitySettings(silence_rto=20.0)


def test_silence_backs_off_to_a_second_and_a_queue_to_the_ceiling() -> None:
    """Random loss leaves a live peer silent for a second now and then: its
    tries then wait at most ``silence_rto``.  A rising round trip (a queue),
    or a silence past ``long_silence_s``, doubles them up to ``max_rto``."""
    settings = ReliabilitySettings(link_kbps=35.0)
    path = PeerPath(settings)
    for _ in range(8):
        path.on_sample(0.1, 200)
    path.on_send(0.0)  # sent at t=0, unanswered since
    timeouts = [path.try_timeout(n, 60, None, now=3.0) - path.extra_airtime(60 + 128) for n in range(6)]
    assert path.silent(3.0) and not path.congested()
    assert timeouts[0] == pytest.approx(path.rto())
    assert max(timeouts) == pytest.approx(settings.silence_rto)
    assert path.stats.backoffs == 5
    # A queue: the round trip is up from 0.1 s to over a second.
    for _ in range(30):
        path.on_sample(1.5, 200)
    assert path.congested()
    assert path.try_timeout(6, 60, None, now=3.0) == pytest.approx(settings.max_rto + path.extra_airtime(188))
    # A path never answered (on a link of known rate) waits half a second
    # first, then a second a try while the silence is short...
    fresh = PeerPath(settings)
    fresh.on_send(0.0)
    assert fresh.silent(3.0)
    waits = [fresh.try_timeout(n, 60, None, now=3.0) - fresh.extra_airtime(188) for n in range(6)]
    assert waits == pytest.approx([settings.initial_rto_known_link] + [settings.silence_rto] * 5)
    # ...and doubling to the ceiling once it lasts past long_silence_s (a
    # queue: a server a whole team keeps busy), with no hedge copies.
    waits = [fresh.try_timeout(n, 60, None, now=10.0) - fresh.extra_airtime(188) for n in range(6)]
    assert waits == pytest.approx([0.5, 1.0, 2.0, 4.0, 8.0, 8.0])
    assert fresh.copies(1, now=10.0) == 1
    assert PeerPath(ReliabilitySettings()).rto() == 1.0  # nothing known of the link: RFC 6298


def test_a_try_with_a_long_answer_goes_out_as_one_copy() -> None:
    """Hedge copies pay for a short answer, not a long one: both copies
    reach the server more often than not and each is answered, so a block
    of a catch-up crossed a lossy link twice."""
    settings = ReliabilitySettings(link_kbps=35)
    path = PeerPath(settings)
    assert path.copies(1, now=0.0) == 2  # a new path's retry: two copies
    assert path.copies(1, now=0.0, reply_bytes=1100) == 1
    assert path.copies(1, now=0.0, reply_bytes=settings.hedge_reply_bytes_max) == 2


def test_a_peer_asked_seldom_is_not_silent_when_asked_again() -> None:
    """Silence counts from the oldest unanswered send, not from the last
    answer: a holder whose facts came pushed for a minute, then asked, gets
    the path's usual timeouts and copies, not a long silence's backoff."""
    settings = ReliabilitySettings(link_kbps=35.0)
    path = PeerPath(settings)
    for _ in range(8):
        path.on_sample(0.2, 200)
    path.on_send(0.0)
    path.on_answer()
    path.on_send(60.0)  # asked again a minute later; its first try went unanswered
    assert not path.silent(60.5)
    waits = [path.try_timeout(n, 60, None, now=60.5) for n in range(3)]
    assert waits == pytest.approx([waits[0]] * 3) and path.stats.backoffs == 0
    assert path.silent(62.5)  # unanswered for two seconds now: silent


# --------------------------------------------------------------------------- a served robot


class _Slow:
    """``/slow``: answers after a fixed delay, counting calls (concurrency)."""

    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s
        self.running = 0
        self.most_running = 0

    async def __call__(self, request: Request) -> Response:
        self.running += 1
        self.most_running = max(self.most_running, self.running)
        try:
            await asyncio.sleep(self.delay_s)
        finally:
            self.running -= 1
        return Response(Status.CONTENT, b"done")


class Served:
    def __init__(self, router: Router, resources: KBResources, slow: _Slow, counter: list[int]) -> None:
        self.router, self.resources, self.slow, self.counter = router, resources, slow, counter
        self.port = 0


@pytest_asyncio.fixture
async def served() -> AsyncIterator[Served]:
    router = Router()
    resources = KBResources(KnowledgeBase.load(KB_FILES))
    resources.mount(router)
    slow = _Slow(0.3)
    router.add(ResourceInfo("/slow"), slow)
    counter = [0]

    async def get_counter(request: Request) -> Response:
        # 10 is the last value the tests set: a final state, sent confirmed.
        return Response(Status.CONTENT, str(counter[0]).encode(), ContentFormat.TEXT, confirm=counter[0] == 10)

    router.add(ResourceInfo("/counter", obs=True), get_counter)
    server = await serve(router, Endpoint("coap", "127.0.0.1", 0), reliability=ReliabilityLayer())
    s = Served(router, resources, slow, counter)
    s.port = server.endpoint.port
    yield s
    await server.aclose()


async def _relayed(served: Served, loss_pct: float, seed: int) -> tuple[UdpRelay, Endpoint]:
    relay = UdpRelay(("127.0.0.1", served.port), LinkSpec(loss_pct=loss_pct), seed=seed)
    host, port = await relay.start()
    return relay, Endpoint("coap", host, port)


def _named(query: str, **params: str) -> Request:
    return Request(Method.GET, f"/kb/q/{query}", params, accept=ContentFormat.CBOR)


# --------------------------------------------------------------------------- behaviour


async def test_every_request_is_answered_at_20_percent_loss_and_no_query_runs_twice(served: Served) -> None:
    relay, peer = await _relayed(served, 20, seed=3)
    layer = ReliabilityLayer()
    client = await open_client("coap", reliability=layer)
    try:
        names = [f"Gucci_bag_{i}" for i in range(14, 54)]
        answers = [await client.request(peer, _named("object-exists", name=n), timeout=20) for n in names]
        assert all(a.status == Status.CONTENT for a in answers)
        # Retries were needed, yet every query ran exactly once: the server
        # answered the repeats from its answer cache, or joined the run.
        (stats,) = layer.stats().values()
        assert stats.retries > 0 and stats.completed == len(names) and stats.failed == 0
        assert served.resources.answers.misses == len(names)
        # One clean sample per answered request: the answer names its try.
        assert stats.samples == len(names)
        assert relay.counters()["up"].dropped + relay.counters()["down"].dropped > 0
    finally:
        await client.aclose()
        relay.close()


async def test_several_exchanges_in_flight_per_peer(served: Served) -> None:
    """NSTART=1 would serialise eight 0.3 s requests into 2.4 s."""
    layer = ReliabilityLayer(ReliabilitySettings(initial_rto=2.0))
    client = await open_client("coap", reliability=layer)
    peer = Endpoint("coap", "127.0.0.1", served.port)
    try:
        answers = await asyncio.gather(*(client.request(peer, Request(Method.GET, "/slow"), timeout=10) for _ in range(8)))
        assert all(a.payload == b"done" for a in answers)
        assert served.slow.most_running == 8
    finally:
        await client.aclose()


async def test_window_bounds_requests_in_flight(served: Served) -> None:
    layer = ReliabilityLayer(ReliabilitySettings(initial_rto=2.0, window_min=2, window_max=3))
    client = await open_client("coap", reliability=layer)
    peer = Endpoint("coap", "127.0.0.1", served.port)
    try:
        await asyncio.gather(*(client.request(peer, Request(Method.GET, "/slow"), timeout=10) for _ in range(7)))
        assert served.slow.most_running == 3
        (stats,) = layer.stats().values()
        assert stats.window_waits > 0
    finally:
        await client.aclose()


async def test_late_answer_to_an_earlier_try_completes_the_request_and_counts_spurious_retransmissions(served: Served) -> None:
    """A timeout far below the server's 0.3 s makes the layer retry; the answer
    to the first try still completes the request, and the retries sent after
    that try left count as spurious (exactly, thanks to the tokens)."""
    layer = ReliabilityLayer(ReliabilitySettings(min_rto=0.05, min_rto_unknown_link=0.05, initial_rto=0.05))
    client = await open_client("coap", reliability=layer)
    peer = Endpoint("coap", "127.0.0.1", served.port)
    try:
        answer = await client.request(peer, Request(Method.GET, "/slow"), timeout=10)
        assert answer.payload == b"done"
        (stats,) = layer.stats().values()
        assert stats.retries >= 2
        assert stats.answered_by_earlier_try == 1
        # Every retry and its hedge copy (a new path's retries go out twice).
        assert stats.spurious_retransmissions == stats.retries + stats.hedge_copies
        # The sample is the first try's true round trip, not the last retry's.
        assert stats.srtt is not None and stats.srtt >= 0.25
    finally:
        await client.aclose()


async def test_blockwise_answer_through_loss(served: Served) -> None:
    relay, peer = await _relayed(served, 15, seed=5)
    client = await open_client("coap")
    text = "SELECT * WHERE { ?s ?p ?o } LIMIT 60"
    try:
        for _ in range(3):
            response = await client.request(
                peer, Request(Method.FETCH, "/kb/sparql", payload=text.encode(), content_format=ContentFormat.TEXT,
                              accept=ContentFormat.JSON), timeout=30)
            assert response.status == Status.CONTENT and len(response.payload) > 3 * 1024
            assert len(json.loads(response.payload)["results"]["bindings"]) == 60
    finally:
        await client.aclose()
        relay.close()


async def test_a_final_notification_arrives_through_loss(served: Served) -> None:
    """The others go NON and may be lost; the one marked ``confirm`` is
    retransmitted until acknowledged, and nothing arrives out of order."""
    relay, peer = await _relayed(served, 20, seed=11)
    layer = ReliabilityLayer()
    client = await open_client("coap", reliability=layer)
    seen: list[int] = []
    try:
        # Warm the path up, so notifications are timed from real samples.
        for _ in range(5):
            await client.request(peer, Request(Method.GET, "/counter"), timeout=10)

        async def watch() -> None:
            async for response in client.observe(peer, Request(Method.GET, "/counter")):
                seen.append(int(response.payload))
                if seen[-1] == 10:
                    return

        watcher = asyncio.create_task(watch())
        while not seen:
            await asyncio.sleep(0.01)
        for value in range(1, 11):
            served.counter[0] = value
            served.router.notify("/counter")
            await asyncio.sleep(0.05)
        await asyncio.wait_for(watcher, 15)
        assert seen[-1] == 10 and seen == sorted(seen)
    finally:
        await client.aclose()
        relay.close()


async def test_dead_peer_is_reported_at_once() -> None:
    """A closed port answers with ICMP: no waiting for the timeout."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    client = await open_client("coap")
    assert isinstance(client, CoapClientTransport)
    try:
        with pytest.raises(PeerUnreachable):  # not a timeout
            await client.request(Endpoint("coap", "127.0.0.1", port), Request(Method.GET, "/kb"), timeout=20)
    finally:
        await client.aclose()


def test_notifications_go_non_but_every_nth_and_the_final_ones() -> None:
    import aiocoap

    types = NotificationTypes(confirm_every=4)
    registration = aiocoap.Message(code=aiocoap.GET, observe=0)
    plain = aiocoap.Message(code=aiocoap.GET)
    # The registration's own answer (piggybacked), then notifications 1-8.
    sent = [types.tuning_for(registration, confirm=False).reliability for _ in range(9)]
    assert sent == [True, False, False, False, True, False, False, False, True]
    assert types.tuning_for(registration, confirm=True).reliability is True
    assert types.tuning_for(plain, confirm=False).reliability is None  # NON for a NON try, as asked
    assert [NotificationTypes(1).tuning_for(registration, False).reliability for _ in range(3)] == [True] * 3
    with pytest.raises(ValueError):
        ReliabilitySettings(confirm_every=0)


async def test_a_notification_of_an_observation_given_up_is_reset() -> None:
    """aiocoap ignores an unexpected NON response; a NON notification of an
    observation the client gave up is answered with a Reset, so the server
    ends it at once instead of sending every state twice until its next CON."""
    router = Router()
    counter = [0]

    async def get_counter(request: Request) -> Response:
        return Response(Status.CONTENT, str(counter[0]).encode(), ContentFormat.TEXT)

    router.add(ResourceInfo("/counter", obs=True), get_counter)
    server = await serve(router, Endpoint("coap", "127.0.0.1", 0), reliability=ReliabilityLayer())
    client = await open_client("coap", reliability=ReliabilityLayer())
    (resource,) = [r for r in server._resources if r.info.path == "/counter"]  # type: ignore[attr-defined]
    try:
        for _ in range(2):  # the first observation is given up after one answer
            stream = client.observe(server.endpoint, Request(Method.GET, "/counter"))
            await anext(stream)
            await stream.aclose()  # type: ignore[attr-defined]
        kept = client.observe(server.endpoint, Request(Method.GET, "/counter"))
        await anext(kept)
        for value in range(1, 4):
            counter[0] = value
            router.notify("/counter")
            assert int((await asyncio.wait_for(anext(kept), 5)).payload) == value
        assert len(resource._observations) == 1
        await kept.aclose()  # type: ignore[attr-defined]
    finally:
        await client.aclose()
        await server.aclose()
