"""What a robot or the feeder takes from the machine it runs on.

Beside the event loop's clock (:mod:`coapkb.clock`), a process of the team
takes these from outside: the network (a client transport and a server),
randomness (a robot's incarnation number), the knowledge base's files and
the disk a data folder syncs to.  A :class:`Host` hands them over.
:func:`operating_system` is the real machine: sockets through the transport
registry, the system's randomness, KB files parsed on worker threads, the
operating system's fsync.  The simulator (:mod:`coapkb.sim`) gives each
simulated process a host of its own, with a faulty in-memory network, a
seeded random generator, KBs loaded once and a disk whose power cuts lose
what was not synced, so the same protocol code runs in both.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from .kb.disk import Disk
from .transport import ClientSecurity, ClientTransport, Endpoint, Reliability, ServerTransport, Service
from .transport import open_client as _open_client
from .transport import serve as _serve
from .transport.security import ServerSecurity

if TYPE_CHECKING:
    from .kb.store import KnowledgeBase
    from .world.truth import World


class Network(Protocol):
    """Opens the transports a process talks through."""

    async def open_client(self, scheme: str, *, reliability: Reliability | None = None,
                          security: ClientSecurity | None = None,
                          options: Mapping[str, Any] | None = None) -> ClientTransport: ...

    async def serve(self, service: Service, endpoint: Endpoint, *, reliability: Reliability | None = None,
                    security: ServerSecurity | None = None,
                    options: Mapping[str, Any] | None = None) -> ServerTransport: ...


class Sockets:
    """The real network: the transport the endpoint's scheme names (:mod:`coapkb.transport`)."""

    async def open_client(self, scheme: str, *, reliability: Reliability | None = None,
                          security: ClientSecurity | None = None,
                          options: Mapping[str, Any] | None = None) -> ClientTransport:
        return await _open_client(scheme, reliability=reliability, security=security, options=options)

    async def serve(self, service: Service, endpoint: Endpoint, *, reliability: Reliability | None = None,
                    security: ServerSecurity | None = None,
                    options: Mapping[str, Any] | None = None) -> ServerTransport:
        return await _serve(service, endpoint, reliability=reliability, security=security, options=options)


def _load_kb(files: Sequence[Path], index_dir: Path | None) -> KnowledgeBase:
    from .kb.store import KnowledgeBase

    return KnowledgeBase.load(files, index_dir=index_dir)


@dataclass(frozen=True)
class Host:
    """The seams between a process's protocol code and its machine."""

    network: Network = field(default_factory=Sockets)
    #: Draws a robot's incarnation number (nonzero, different after a restart).
    rng: random.Random = field(default_factory=random.SystemRandom)
    #: Loads a robot's KB modules (``files``, the on-disk index directory or None).
    load_kb: Callable[[Sequence[Path], Path | None], KnowledgeBase] = _load_kb
    #: May blocking work (a SPARQL query) go to a worker thread?  Not in the
    #: simulator: its processes share one thread and replay from a seed.
    threads: bool = True
    #: Wall-clock milliseconds: a KB write's timestamp (virtual in the simulator).
    wall_ms: Callable[[], int] = field(default=lambda: time.time_ns() // 1_000_000)
    #: What a robot finds at the shelf (the simulator's one world); None:
    #: the robot's ``world`` socket if configured, else the KB's word.
    world: World | None = None
    #: How a data folder's writes are made durable (fsync); the simulator's
    #: notes what each sync covered, for its power cuts.
    disk: Disk = field(default_factory=Disk)


def operating_system() -> Host:
    """The real machine."""
    return Host()
