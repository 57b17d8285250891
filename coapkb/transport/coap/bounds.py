"""How much state a CoAP server keeps, and for how long.

Every bound on what aiocoap would keep without limit -- duplicate memory,
block-wise transfers, observers -- is one field of :class:`StateBounds`,
handed to :meth:`~.server.CoapServerTransport.start`; tests shrink them
through it instead of patching module constants.  docs/flood.md measures
what the defaults hold under a flood.
"""

from __future__ import annotations

from dataclasses import dataclass

from aiocoap.numbers.constants import TransportTuning

__all__ = ["MESSAGE_OVERHEAD", "StateBounds"]

#: What a kept message costs beyond its payload (its object, options and
#: key), roughly: the unit of every byte bound on kept messages.
MESSAGE_OVERHEAD = 512


@dataclass(frozen=True)
class StateBounds:
    """The bounds of one server's state (its client's duplicate memory takes
    the defaults)."""

    #: How often the server forgets the state that has aged out (duplicate
    #: memory, block-wise transfers), so an idle robot gives it back too.
    sweep_every_s: float = 10.0
    #: When a sweep forgot at least this much, the freed memory goes back to
    #: the system (:mod:`.heap`): a flood's state leaves no lasting RSS.
    trim_after_bytes: int = 256 * 1024
    #: Observations a resource keeps (RFC 7641): each costs a CON
    #: notification per change.  A robot's state is observed by its cluster
    #: mates and the feeder; past this many, a registration is answered
    #: without Observe (section 4.1: the client is told it is not observing).
    observers: int = 64
    #: A block transfer unused this long is forgotten: a CON block request is
    #: retried for at most MAX_TRANSMIT_WAIT (93 s with RFC 7252's defaults).
    transfer_idle_s: float = TransportTuning().MAX_TRANSMIT_WAIT
    #: Multi-block answers kept for their follow-ups: a robot's largest answer
    #: (1,000 rows) is 21 kB in compact CBOR, 236 kB in SPARQL JSON, so this
    #: holds about a hundred, or eight, in transfer at once.
    block2_bytes: int = 2 * 1024 * 1024
    block2_keys: int = 1024
    #: Requests being received block by block (Block1): a SPARQL text is a
    #: few kB at most.
    block1_bytes: int = 1024 * 1024
    block1_assemblies: int = 256
    #: The requests a context remembers to recognise a duplicate (and answer
    #: it again), at most this many and none for longer than
    #: ``duplicate_horizon_s``.  aiocoap keeps each for RFC 7252's
    #: EXCHANGE_LIFETIME, 247 s, with a timer and the answer: a robot
    #: deciding tasks quickly, or anyone sending it garbage requests, grew its
    #: memory by kilobytes per task for four minutes.  Duplicates come from a
    #: CON sender's retransmissions, which end within MAX_TRANSMIT_SPAN (45 s
    #: with RFC 7252's defaults); the reliability layer's own tries are new
    #: messages and never duplicates.  A duplicate arriving after its entry
    #: went is handled again: every robot resource is idempotent or keyed by
    #: task (docs/reliability.md).
    duplicates: int = 4096
    duplicate_horizon_s: float = 60.0
    #: ... and while what they keep stays under this many bytes: the answers
    #: to send again, and what each entry costs by itself
    #: (:data:`MESSAGE_OVERHEAD`).  4,096 block-wise answers would be 10 MiB
    #: and more.
    duplicate_answer_bytes: int = 1024 * 1024

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if value <= 0 and name != "duplicate_horizon_s" or value < 0:
                raise ValueError(f"StateBounds.{name} must be positive, got {value}")
