"""RFC 7641 on the layer's paths: which of a server's notifications are
confirmable, their timers, and a client's registrations.

Most notifications go NON (:class:`NotificationTypes`): each one of the
team's states is awaited by a process that asks again when it is late
(``ObservedStates.wait``), so an empty ACK per notification, and a
retransmission of every notification whose ACK was lost, bought nothing
the waiter does not already do, at 46 bytes and more per notification.

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

The host's round trip is not always how late an observer acknowledges: a
feeder observing 99 robots on a busy machine answers a notification later
than the robots answer each other's queries, and every CON notification
to it went out three or four times.  So each observer's own ACK delay is
kept too (:class:`AckDelays`), from the clean samples and from the
notifications a duplicate ACK proves were sent again needlessly (two
copies reached the observer: the first ACK came that long after the first
transmission, RFC 3708's reasoning for TCP), and a notification waits the
longer of the two timeouts.  An observer not heard from yet has no such
estimate, and its first ACK can come a second late: its notification waits
at least the timeout of a path with no sample, and doubles from the first
retransmission.
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

import aiocoap
from aiocoap.numbers.constants import TransportTuning

from ...rtt import RttEstimator
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


#: The tuning of an answer that is not a notification (piggybacked, or NON
#: answering a NON try) and of an unconfirmed notification.
_UNCONFIRMED = TransportTuning()
_UNCONFIRMED.reliability = False


class NotificationTypes:
    """Which answers of an observation go confirmable (RFC 7641 §4.5).

    Every ``confirm_every``-th notification of an observation, so the server
    learns that an observer is gone (RFC 7641 asks for one a day at least;
    an unacknowledged one ends the observation), and every one the service
    marks ``confirm`` (a final state: nobody waits for a later one that
    would repair its loss); the rest NON.  ``confirm_every`` 1: all CON."""

    def __init__(self, confirm_every: int) -> None:
        if confirm_every < 1:
            raise ValueError("confirm_every must be at least 1")
        self.confirm_every = confirm_every
        self._confirmed = NotificationTuning()
        self._answer = TransportTuning()
        #: Answers sent so far per observation (its registration's request).
        self._sent: weakref.WeakKeyDictionary[aiocoap.Message, int] = weakref.WeakKeyDictionary()

    def tuning_for(self, request: aiocoap.Message, confirm: bool) -> TransportTuning:
        if request.opt.observe != 0:
            return self._answer
        sent = self._sent.get(request, 0)
        self._sent[request] = sent + 1
        # The first is the registration's answer: piggybacked on its ACK, whatever the tuning.
        if sent == 0 or confirm or sent % self.confirm_every == 0:
            return self._confirmed
        return _UNCONFIRMED


def _host_of(remote: Any) -> str:
    host = str(getattr(remote, "sockaddr", ("",))[0])
    return host[7:] if host.startswith("::ffff:") else host


def _endpoint_of(remote: Any) -> Hashable:
    """An observer's address and port (its client's socket)."""
    sockaddr = getattr(remote, "sockaddr", None)
    return (_host_of(remote), sockaddr[1]) if sockaddr else remote


class AckDelays:
    """How late each observer acknowledges a notification, per endpoint:
    an RFC 6298 estimate of its own, for the ``kept`` endpoints heard from
    most lately."""

    def __init__(self, kept: int = 256) -> None:
        self._kept = kept
        self._delays: OrderedDict[Hashable, RttEstimator] = OrderedDict()

    def of(self, endpoint: Hashable) -> RttEstimator:
        delay = self._delays.get(endpoint)
        if delay is None:
            delay = self._delays[endpoint] = RttEstimator()
            while len(self._delays) > self._kept:
                self._delays.popitem(last=False)
        self._delays.move_to_end(endpoint)
        return delay


@dataclass
class _Notification:
    path: PeerPath
    #: The observer's own ACK delay.
    observer: RttEstimator
    sent_at: float
    nbytes: int
    #: Link time of what was queued ahead of the first transmission.
    queued: float = 0.0
    retransmissions: int = 0
    #: A retransmitted one's first ACK, that long after its first
    #: transmission: a sample of the observer's once a duplicate ACK
    #: shows that an earlier copy had reached it.
    first_ack_after: float | None = None


class NotificationPolicy:
    """Retransmission timers of a server's CON messages from a shared layer."""

    def __init__(self, layer: ReliabilityLayer, ack_delays: AckDelays | None = None) -> None:
        self.layer = layer
        self.ack_delays = AckDelays() if ack_delays is None else ack_delays

    def on_send(self, message: aiocoap.Message) -> _Notification:
        path = self.layer.path_for_host(_host_of(message.remote))
        path.stats.notifications += 1
        # Called just before the datagram is handed to the socket: what is
        # queued on the link now goes first.
        return _Notification(path, self.ack_delays.of(_endpoint_of(message.remote)), self.layer.clock(),
                             len(message.payload) + 16, queued=self.layer.uplink.wait(self.layer.clock()))

    def timeout(self, record: _Notification, retransmission_counter: int) -> float:
        """The path's timeout, or the observer's own if its ACKs come later,
        for the first few transmissions, then doubling (an observer not
        heard from yet: at least a path's first timeout, doubling at once):
        a notification is never abandoned for want of patience (the server
        would drop the observation, and the teammate would wait for a
        refresh), but a peer that stays silent is not flooded either."""
        path = record.path
        queued = record.queued if retransmission_counter == 0 else self.layer.uplink.wait(self.layer.clock())
        base = path.rto()
        fast = FAST_RETRANSMISSIONS
        if record.observer.samples:
            s = path.settings
            base = max(base, record.observer.rto(k=s.rto_k, granularity=s.granularity, floor=path.floor(),
                                                 ceiling=s.max_rto, initial=base))
        else:
            # An observer not heard from yet is a path with no sample (RFC
            # 6298 2.1, 5.5): the host's round trip is its teammates', and a
            # busy feeder's first ACKs came 0.2-1.2 s late, after three
            # retransmissions at that round trip.
            base = max(base, path.initial_rto())
            fast = 0
        backoff = 2 ** max(0, retransmission_counter - fast)
        return path.exchange_timeout(base * backoff, record.nbytes + _ACK_BYTES) + queued

    def on_retransmit(self, record: _Notification) -> None:
        record.retransmissions += 1
        record.path.stats.notification_retransmissions += 1
        record.path.on_send(self.layer.clock())

    def on_give_up(self, record: _Notification, reason: str) -> None:
        return None

    def on_reply(self, record: _Notification, message: aiocoap.Message) -> None:
        path = record.path
        now = self.layer.clock()
        path.on_answer()
        delay = now - record.sent_at - record.queued
        if record.retransmissions == 0:  # Karn: a retransmitted CON says nothing certain
            path.loss.on_outcome(False)
            path.on_sample(delay, record.nbytes + _ACK_BYTES)
            record.observer.on_sample(delay)
        else:
            record.first_ack_after = delay

    def on_duplicate_reply(self, record: _Notification, message: aiocoap.Message) -> None:
        if record.first_ack_after is not None:
            # Two copies reached the observer: one was sent again too soon,
            # and its ACKs come at least this late (an upper estimate if the
            # first copy was lost: the timer errs long, never short).
            record.observer.on_sample(record.first_ack_after)
            record.first_ack_after = None
            record.path.stats.needless_notification_retransmissions += 1

    def max_retransmit(self, record: _Notification) -> int:
        return NotificationTuning.MAX_RETRANSMIT
