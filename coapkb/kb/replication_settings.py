"""What every part of a robot's replication shares (:mod:`.replication`):
the resource holders sync at, the holders this robot knows, its settings
and what it counts."""

from __future__ import annotations

from dataclasses import dataclass

from ..transport.base import Endpoint

__all__ = ["SYNC_PATH", "Holder", "ReplicationSettings", "ReplicationStats"]

SYNC_PATH = "/kb/sync"


@dataclass(frozen=True)
class Holder:
    """Another robot holding some of this robot's modules."""

    name: str
    endpoint: Endpoint
    modules: tuple[str, ...]
    #: In another cluster: a write pushed to it is passed on there.
    remote: bool = False
    #: Asked only when the module's usual holders do not answer (never
    #: pushed to, not waited for by compaction): what keeps a robot in
    #: step once the ring over the clusters lost its neighbours.
    standby: bool = False


@dataclass(frozen=True)
class ReplicationSettings:
    #: Seconds between two anti-entropy rounds (each with one holder), jittered by a third.
    sync_every_s: float = 5.0
    #: How long a push or an exchange may take (the transport retransmits within it).
    request_timeout_s: float = 10.0
    #: How long a write waits for a second holder before it is answered anyway.
    ack_timeout_s: float = 10.0
    #: How long a read waits, after a start, for the catch-up with every
    #: holder before it is answered anyway: a holder that answered at once
    #: would answer without the writes it missed while it was down (the
    #: catch-up takes one exchange, a round trip, unless holders are down).
    read_after_catch_up_s: float = 3.0
    #: Bytes of changes one answer carries at most (four CoAP blocks: on a
    #: lossy link a short exchange that times out wastes little); the rest
    #: follows at once, in the next exchange.
    max_answer_bytes: int = 4096

    def __post_init__(self) -> None:
        for name in ("sync_every_s", "request_timeout_s", "ack_timeout_s", "read_after_catch_up_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass
class ReplicationStats:
    """What one robot's replication did, counted since it started."""

    #: Pushes of new writes sent to a holder, and those that failed.
    pushed: int = 0
    push_failed: int = 0
    #: Anti-entropy rounds run.
    rounds: int = 0
    #: Deltas and whole states taken from holders.
    deltas_in: int = 0
    states_in: int = 0
    #: Sync messages refused: not decodable, from a sender not allowed, or
    #: deltas not taken at the replica's bound (they come again at catch-up).
    malformed: int = 0
    forbidden: int = 0
    not_taken: int = 0
