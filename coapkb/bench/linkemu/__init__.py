"""Kernel link emulation for benchmarks: one network namespace per host.

Every host of a benchmark (``robot1`` .. ``robotN``, ``central``, the
feeder) gets its own Linux network namespace with one interface, ``eth0``,
whose other end is a port of a bridge in a namespace of its own; nothing is
added to the root namespace.  A :class:`LinkSpec` sets a host's link: a
``tbf`` shaper on each direction, a random-loss rule in the bridge's forward
hook *after* the sender's shaper (a lost packet has used the air time), and
for delay, jitter and burst loss a user-space NFQUEUE delay line
(:mod:`.delayline`).  :class:`Testbed` sets it up, changes it, runs
processes in it, reads the counters and tears it down.

The modules, by concern: :mod:`.spec` (``LinkSpec``, ``LinkCounters``),
:mod:`.netns` (namespace commands, ``available``, ``cleanup_stale``,
``enter_netns``), :mod:`.shaping` (rule text), :mod:`.hosts`,
:mod:`.topology`, :mod:`.link_control`, :mod:`.counters`, :mod:`.testbed`,
:mod:`.delayline`, :mod:`.capture` (``PacketCapture``) and :mod:`.relay`
(``UdpRelay``, the labelled user-space fallback).

Everything here needs root and the Debian packages ``iproute2``,
``nftables`` and, for delay, ``iptables``: call :func:`available` first and
print its reason when it says no.  docs/link-emulation.md specifies the
topology, why the loss comes after the shaper, the delay line, what keeps
the counters exact, the tbf parameters and the limits.
"""

from __future__ import annotations

from .hosts import Host
from .netns import DEFAULT_PREFIX, available, cleanup_stale, enter_netns
from .relay import UDP_IPV4_OVERHEAD, UdpRelay
from .spec import (
    DEFAULT_QUEUE_BYTES,
    ETH_FRAME_MAX,
    MIN_BURST_BYTES,
    LinkCounters,
    LinkEmulationError,
    LinkSpec,
)
from .testbed import Testbed

__all__ = [
    "ETH_FRAME_MAX",
    "DEFAULT_QUEUE_BYTES",
    "MIN_BURST_BYTES",
    "LinkEmulationError",
    "LinkSpec",
    "LinkCounters",
    "Host",
    "Testbed",
    "available",
    "cleanup_stale",
    "DEFAULT_PREFIX",
    "UDP_IPV4_OVERHEAD",
    "UdpRelay",
    "enter_netns",
]
