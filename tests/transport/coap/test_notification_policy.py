"""The timers of a server's CON notifications: the host's path, and each
observer's own ACK delay (a busy feeder acknowledges later than teammates
answer each other)."""

from __future__ import annotations

from types import SimpleNamespace

import aiocoap
import pytest

from coapkb.transport.coap.reliability import ReliabilityLayer
from coapkb.transport.coap.reliability.notifications import AckDelays, NotificationPolicy


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _notification(port: int) -> aiocoap.Message:
    message = aiocoap.Message(code=aiocoap.CONTENT, payload=b"x" * 40)
    message.remote = SimpleNamespace(sockaddr=("127.0.0.1", port))  # only its address is read
    return message


def _teammate_path(layer: ReliabilityLayer) -> None:
    """The host's path, trained by the robot's own queries: 20 ms round trips."""
    path = layer.path_for_host("127.0.0.1")
    for _ in range(8):
        path.on_sample(0.02, 100)


def test_a_clean_ack_trains_the_host_path_and_the_observer() -> None:
    clock = Clock()
    layer = ReliabilityLayer(clock=clock)
    policy = NotificationPolicy(layer)
    record = policy.on_send(_notification(5001))
    clock.now += 0.05
    policy.on_reply(record, aiocoap.Message())
    assert record.observer.samples == 1 and record.path.rtt.samples == 1
    assert record.observer.srtt == pytest.approx(0.05)


def test_needless_retransmissions_to_a_slow_observer_lengthen_its_timer_only() -> None:
    clock = Clock()
    layer = ReliabilityLayer(clock=clock)
    _teammate_path(layer)
    policy = NotificationPolicy(layer)
    teammate = policy.on_send(_notification(5001))
    clock.now += 0.02
    policy.on_reply(teammate, aiocoap.Message())  # the teammate's port is heard from
    fast = policy.timeout(policy.on_send(_notification(5001)), 0)
    assert fast < 0.3  # the host's path: the teammates answer in 20 ms
    # The feeder's port acknowledges 0.9 s late: the notification went out
    # again, and both copies were acknowledged.
    record = policy.on_send(_notification(6000))
    for _ in range(3):
        policy.on_retransmit(record)
    clock.now += 0.9
    policy.on_reply(record, aiocoap.Message())
    assert record.observer.samples == 0  # one ACK of a retransmitted CON: ambiguous (Karn)
    policy.on_duplicate_reply(record, aiocoap.Message())
    assert record.observer.srtt == pytest.approx(0.9)
    assert record.path.stats.needless_notification_retransmissions == 1
    assert policy.timeout(policy.on_send(_notification(6000)), 0) >= 0.9
    # A teammate's notifications keep the host's timer.
    assert policy.timeout(policy.on_send(_notification(5001)), 0) == pytest.approx(fast)


def test_a_notification_lost_on_the_way_teaches_nothing() -> None:
    """Sent again and acknowledged once: the retransmission was needed (a
    lossy link), and the observer's estimate stays as it was."""
    clock = Clock()
    layer = ReliabilityLayer(clock=clock)
    _teammate_path(layer)
    policy = NotificationPolicy(layer)
    before = policy.timeout(policy.on_send(_notification(6000)), 0)
    record = policy.on_send(_notification(6000))
    policy.on_retransmit(record)
    clock.now += 0.5
    policy.on_reply(record, aiocoap.Message())
    assert record.observer.samples == 0
    assert policy.timeout(policy.on_send(_notification(6000)), 0) == pytest.approx(before)


def test_the_ack_delays_kept_are_bounded() -> None:
    delays = AckDelays(kept=2)
    first = delays.of(("10.0.0.1", 1))
    delays.of(("10.0.0.2", 1))
    assert delays.of(("10.0.0.1", 1)) is first  # heard from lately: kept
    delays.of(("10.0.0.3", 1))  # the one heard from least lately goes
    assert list(delays._delays) == [("10.0.0.1", 1), ("10.0.0.3", 1)]


def test_an_observer_not_heard_from_waits_a_first_timeout_and_doubles_at_once() -> None:
    """The host's path is trained by 20 ms round trips to the teammates; the
    feeder's port, never heard from, gets the timeout of a path with no
    sample, doubled at each retransmission (no fast ones at 20 ms)."""
    clock = Clock()
    layer = ReliabilityLayer(clock=clock)
    _teammate_path(layer)
    policy = NotificationPolicy(layer)
    record = policy.on_send(_notification(6000))
    first = policy.timeout(record, 0)
    assert first >= layer.path_for_host("127.0.0.1").initial_rto()
    assert policy.timeout(record, 1) >= 2 * layer.path_for_host("127.0.0.1").initial_rto()
    clock.now += 0.3
    policy.on_reply(record, aiocoap.Message())
    assert record.observer.samples == 1
    assert policy.timeout(policy.on_send(_notification(6000)), 0) < first  # heard from: its own estimate
