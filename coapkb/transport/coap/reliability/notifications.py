"""The server's confirmable notifications (RFC 7641) on the layer's paths.

A robot's state notifications are on every task's critical path: a
teammate waits for them before it assigns the next task.  aiocoap sends
them as CON with RFC 7252's timers (2-3 s, doubling), and the server side
of a robot has few samples of its own.  :class:`NotificationPolicy` is a
:class:`~coapkb.transport.coap.aiocoap_adapter.ConPolicy` that times each
notification from the estimates the robot's own client keeps for the same
host (it queries that teammate all the time), and feeds back the clean
samples it gets (ACKs of notifications sent once; Karn's rule, since a
CON retransmission reuses its Message ID).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import aiocoap
from aiocoap.numbers.constants import TransportTuning

from .estimator import airtime
from .layer import ReliabilityLayer, _Path

#: Size of the empty ACK that answers a notification.
_ACK_BYTES = 4


class NotificationTuning(TransportTuning):  # type: ignore[misc]  # aiocoap ships no type information
    """``transport_tuning`` of a notification: more retransmissions than RFC
    7252's 4, because each one costs a round trip, not seconds."""

    MAX_RETRANSMIT = 10


def _host_of(remote: Any) -> str:
    host = str(getattr(remote, "sockaddr", ("",))[0])
    return host[7:] if host.startswith("::ffff:") else host


@dataclass
class _Notification:
    path: _Path | None
    sent_at: float
    nbytes: int
    retransmissions: int = 0


class NotificationPolicy:
    """Retransmission timers of a server's CON messages from a shared layer."""

    def __init__(self, layer: ReliabilityLayer) -> None:
        self.layer = layer

    def on_send(self, message: aiocoap.Message) -> _Notification:
        path = self.layer.path_for_host(_host_of(message.remote))
        if path is not None:
            path.stats.notifications += 1
        return _Notification(path, self.layer.clock(), len(message.payload) + 16)

    def timeout(self, record: _Notification, retransmission_counter: int) -> float:
        if record.path is None:  # a host we never asked anything: no estimate
            return self.layer.settings.initial_rto * 2 ** min(retransmission_counter, 3)
        return record.path.try_timeout(retransmission_counter, record.nbytes, None, self.layer.clock()) - airtime(
            record.path.expected_reply(None), self.layer.settings.link_bps
        ) + airtime(_ACK_BYTES, self.layer.settings.link_bps)

    def on_retransmit(self, record: _Notification) -> None:
        record.retransmissions += 1
        if record.path is not None:
            record.path.stats.notification_retransmissions += 1
            record.path.last_send = self.layer.clock()

    def on_give_up(self, record: _Notification, reason: str) -> None:
        return None

    def on_reply(self, record: _Notification, message: aiocoap.Message) -> None:
        path = record.path
        if path is None:
            return
        now = self.layer.clock()
        path.last_answer = now
        path.loss.on_outcome(record.retransmissions > 0)
        if record.retransmissions == 0:
            link = self.layer.settings.link_bps
            path.rtt.on_sample(max(0.0, now - record.sent_at - airtime(record.nbytes, link) - airtime(_ACK_BYTES, link)))

    def on_duplicate_reply(self, record: _Notification, message: aiocoap.Message) -> None:
        return None

    def max_retransmit(self, record: _Notification) -> int:
        return NotificationTuning.MAX_RETRANSMIT
