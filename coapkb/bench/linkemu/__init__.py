"""Kernel link emulation for benchmarks: one network namespace per robot.

Every host of a benchmark (``robot1`` .. ``robot9``, ``central``) gets its own
Linux network namespace with one interface, ``eth0``, on a private subnet
(``10.77.0.N/24`` by default).  The other end of each ``eth0`` is a port of a
bridge that lives in a namespace of its own, so nothing is ever added to the
root namespace and deleting the namespaces removes every interface, queue
and nftables rule with them::

    ns ckb<pid>-<tok>-robot1          ns ckb<pid>-<tok>  (bridge)
    +----------------------+          +----------------------------------+
    | eth0 10.77.0.1       |  veth    | p-robot1 --+                     |
    | egress: tbf (uplink) |<-------->| egress: tbf (downlink)           |
    +----------------------+          |            |                     |
                                      |  br0 + nft bridge forward hook:  |
    ns ckb<pid>-<tok>-central         |  "from p-X: drop with prob. p_X" |
    +----------------------+  veth    |            |                     |
    | eth0 10.77.0.10      |<-------->| p-central -+                     |
    +----------------------+          +----------------------------------+

How a :class:`LinkSpec` is applied to host X (see ``docs/link-emulation.md``):

* **rate** -- a token-bucket filter (``tbf``) on X's ``eth0`` egress shapes
  what X sends (uplink) and one on the bridge port's egress shapes what X
  receives (downlink), so both directions of X's link run at the set rate.
* **loss** -- packets X sends are dropped with probability ``loss_pct`` in
  the bridge's ``forward`` hook, i.e. *after* X's shaper: a lost packet has
  used X's link time, as on a real radio.  Loss is applied once per packet,
  at the sender's link, so with one spec for all hosts every host pair sees
  exactly ``loss_pct`` one-way loss (not ``1-(1-p)^2``).
* **counters** -- bytes and packets are read from X's ``eth0`` statistics,
  i.e. where X puts them on the link (after its shaper, before the loss),
  plus the nftables counter of X's packets that the loss rule dropped.

The testbed is deterministic on purpose: IPv6 is off on ``eth0`` (no router
solicitations or MLD reports in the counters; ``lo`` keeps ``::1``), ARP
entries and the bridge's forwarding table are static (no ARP to lose, no
flooding of unknown unicast into other hosts' downlinks), and ``eth0`` hands
at most one segment per packet to the link (``gso_max_segs 1``) so TCP is
counted and shaped in real frames.

* **delay, jitter, burst loss** -- the kernel has no ``sch_netem``, so X's
  packets go (after its shaper and the random-loss rule) through iptables'
  ``NFQUEUE`` to a user-space delay line in the bridge namespace, which
  releases them after ``delay_ms +- jitter_ms`` (FIFO) and drops Gilbert
  bursts for ``loss_model="burst"`` (:mod:`.delayline`).

The package's modules, by concern: :mod:`.spec` (``LinkSpec``,
``LinkCounters``, validation), :mod:`.netns` (namespace commands,
``available``, ``cleanup_stale``, ``enter_netns``), :mod:`.shaping` (tbf,
nftables and iptables rule text), :mod:`.delayline` (NFQUEUE delay line),
:mod:`.hosts` (``Host``: names, addresses), :mod:`.topology` (namespaces,
bridge, veth pairs), :mod:`.link_control` (a live link's shapers, loss rule
and delay line), :mod:`.counters` (reading the kernel's counters),
:mod:`.testbed` (``Testbed``: set up, change, run processes, tear down),
:mod:`.capture` (``PacketCapture``: every frame crossing the bridge) and
:mod:`.relay` (``UdpRelay``).

Everything here needs root (``CAP_NET_ADMIN``) and the Debian packages
``iproute2`` (``ip``, ``tc``, ``bridge``) and ``nftables`` (``nft``), plus
``iptables`` for delay, jitter and burst loss; call
:func:`available` first and print its reason when it says no.  Without root,
CoAP-only runs can use :class:`UdpRelay`, a user-space relay whose results
must be labelled as such (it emulates a path, not a host's link).
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
