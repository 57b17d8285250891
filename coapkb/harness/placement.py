"""Where a team's processes run and the ports they bind: on this machine's
loopback, each server on a free port held for it until its process starts
(:class:`Placement`, :class:`PortReservation`).

The benchmark's link emulator subclasses :class:`Placement` to put every
process in its own network namespace (:mod:`coapkb.bench.run`).
"""

from __future__ import annotations

import random
import socket
from pathlib import Path
from typing import TYPE_CHECKING

from ..transport import transport_for
from ..transport.base import Endpoint

if TYPE_CHECKING:
    from .team_spec import TeamSpec


class PortReservation:
    """Free ports for the team's servers on one host, each held bound until
    its process is about to start.

    The robots' configurations name every teammate's port, so ports are
    chosen before any robot starts, and a robot binds its own (a bound socket
    cannot be handed to the child: aiocoap, ZeroMQ and Zenoh bind their own).
    Asking the OS for port 0 and closing the socket again lets a later ask, or
    a robot's client socket, get the same port before its server binds it: a
    team of 99 then fails to start now and then.  So the ports are taken
    below the kernel's ephemeral range (no client socket is ever given one
    there) and each stays bound here -- no second team member, and no other
    team started meanwhile, can take it -- until :meth:`release` just before
    its process starts."""

    #: Where the search starts: above the well-known and most registered
    #: services' ports (and below Linux's default ephemeral range, 32768-60999).
    LOWEST = 20000

    def __init__(self, host: str) -> None:
        self.host = host
        self._held: dict[str, socket.socket] = {}
        low, _ = _ephemeral_range()
        self._candidates = list(range(self.LOWEST, low)) if low - self.LOWEST >= 1000 else []
        # A random order: two teams allocating at once try different ports first.
        random.SystemRandom().shuffle(self._candidates)

    def take(self, name: str, kind: int) -> int:
        """A port held for process ``name`` (``kind``: SOCK_DGRAM or SOCK_STREAM)."""
        self.release(name)
        while self._candidates:
            port = self._candidates.pop()
            held = socket.socket(socket.AF_INET, kind)
            try:
                held.bind((self.host, port))
            except OSError:  # in use by something else
                held.close()
                continue
            self._held[name] = held
            return port
        # No range below the ephemeral one (a tuned kernel): an OS-chosen port, still held.
        held = socket.socket(socket.AF_INET, kind)
        held.bind((self.host, 0))
        self._held[name] = held
        return int(held.getsockname()[1])

    def release(self, name: str) -> None:
        """Let ``name``'s process bind its port (no-op if none is held)."""
        held = self._held.pop(name, None)
        if held is not None:
            held.close()

    def close(self) -> None:
        for name in list(self._held):
            self.release(name)


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range of ports for client sockets (Linux; its default elsewhere)."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999


class Placement:
    """Where each process of the team runs: here, on loopback, each on a free
    port held for it until it starts (:class:`PortReservation`).

    The benchmark's link emulator subclasses this to put every robot in its
    own network namespace behind an emulated link."""

    def __init__(self) -> None:
        self._ports: PortReservation | None = None

    def endpoint(self, name: str, spec: TeamSpec) -> Endpoint:
        kind = socket.SOCK_DGRAM if transport_for(spec.transport).datagram else socket.SOCK_STREAM
        if self._ports is None:
            self._ports = PortReservation(spec.host)
        return Endpoint(spec.transport, spec.host, self._ports.take(name, kind))

    def starting(self, name: str) -> None:
        """Process ``name`` is about to start and bind its endpoint."""
        if self._ports is not None:
            self._ports.release(name)

    def close(self) -> None:
        """Let go of whatever is still held for processes that never started."""
        if self._ports is not None:
            self._ports.close()

    def command(self, name: str, argv: list[str]) -> list[str]:
        """The command line that starts ``argv`` for process ``name``."""
        return argv
