"""The confirmable messages of RFC 7641 on the layer's paths: a server's
notifications and a client's registrations.

A robot's state notifications are on every task's critical path: a
teammate waits for them before it assigns the next task.  aiocoap sends
them as CON with RFC 7252's timers (2-3 s, doubling), and the server side
of a robot has few samples of its own.  :class:`NotificationPolicy` is a
:class:`~coapkb.transport.coap.aiocoap_adapter.ConPolicy` that times each
notification from the estimates the robot's own client keeps for the same
host (it queries that teammate all the time), and feeds back the clean
samples it gets (ACKs of notifications sent once; Karn's rule, since a
CON retransmission reuses its Message ID).  A client's Observe
registration is confirmable for the same reason it keeps one Message ID:
the server registers it once, however many times it is sent.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import aiocoap
from aiocoap.numbers.constants import TransportTuning

from .layer import PeerPath, ReliabilityLayer

#: Size of the empty ACK that answers a notification.
_ACK_BYTES = 4
#: Retransmissions of a notification at the path's timeout before it doubles.
FAST_RETRANSMISSIONS = 3


class NotificationTuning(TransportTuning):  # type: ignore[misc]  # aiocoap ships no type information
    """``transport_tuning`` of a notification: confirmable, with more
    retransmissions than RFC 7252's 4, because each costs a round trip, not
    seconds.

    ``reliability`` must be set: aiocoap otherwise sends a notification NON
    whenever the registration was NON (as the layer's tries are), and a lost
    NON notification is never repeated."""

    MAX_RETRANSMIT = 10
    reliability = True


def _host_of(remote: Any) -> str:
    host = str(getattr(remote, "sockaddr", ("",))[0])
    return host[7:] if host.startswith("::ffff:") else host


@dataclass
class _Notification:
    path: PeerPath
    sent_at: float
    nbytes: int
    #: Link time of what was queued ahead of the first transmission.
    queued: float = 0.0
    retransmissions: int = 0


class NotificationPolicy:
    """Retransmission timers of a server's CON messages from a shared layer."""

    def __init__(self, layer: ReliabilityLayer) -> None:
        self.layer = layer

    def on_send(self, message: aiocoap.Message) -> _Notification:
        path = self.layer.path_for_host(_host_of(message.remote))
        path.stats.notifications += 1
        # Called just before the datagram is handed to the socket: what is
        # queued on the link now goes first.
        return _Notification(path, self.layer.clock(), len(message.payload) + 16,
                             queued=self.layer.uplink.wait(self.layer.clock()))

    def timeout(self, record: _Notification, retransmission_counter: int) -> float:
        """The path's timeout for the first few transmissions, then doubling:
        a notification is never abandoned for want of patience (the server
        would drop the observation, and the teammate would wait for a
        refresh), but a peer that stays silent is not flooded either."""
        path = record.path
        backoff = 2 ** max(0, retransmission_counter - FAST_RETRANSMISSIONS)
        queued = record.queued if retransmission_counter == 0 else self.layer.uplink.wait(self.layer.clock())
        return path.exchange_timeout(path.rto() * backoff, record.nbytes + _ACK_BYTES) + queued

    def on_retransmit(self, record: _Notification) -> None:
        record.retransmissions += 1
        record.path.stats.notification_retransmissions += 1
        record.path.last_send = self.layer.clock()

    def on_give_up(self, record: _Notification, reason: str) -> None:
        return None

    def on_reply(self, record: _Notification, message: aiocoap.Message) -> None:
        path = record.path
        now = self.layer.clock()
        path.last_answer = now
        if record.retransmissions == 0:  # Karn: a retransmitted CON says nothing certain
            path.loss.on_outcome(False)
            path.on_sample(now - record.sent_at - record.queued, record.nbytes + _ACK_BYTES)

    def on_duplicate_reply(self, record: _Notification, message: aiocoap.Message) -> None:
        return None

    def max_retransmit(self, record: _Notification) -> int:
        return NotificationTuning.MAX_RETRANSMIT
