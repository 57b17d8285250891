"""The testbed's wiring: one namespace per host and one for the bridge,
a veth pair per host, addresses, static ARP and forwarding, and the
nftables table that carries the loss rules and their counters."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from .hosts import BRIDGE_IF, HOST_IF, Host
from .netns import _run
from .shaping import nft_table
from .spec import LinkSpec

__all__ = ["add_netns", "wire_hosts"]

_V6_DEFAULT = "/proc/sys/net/ipv6/conf/default/disable_ipv6"


def add_netns(ns: str, created: list[str]) -> None:
    """Create namespace ``ns`` and note it in ``created`` (what teardown deletes)."""
    _run(["ip", "netns", "add", ns])
    created.append(ns)
    # New interfaces in this namespace get IPv6 off (no RS/MLD/DAD noise on
    # the link); `lo` exists already and keeps ::1.
    # (Written with sh rather than sysctl(8): procps is not always installed.)
    _run(["ip", "netns", "exec", ns, "sh", "-c", f"[ ! -e {_V6_DEFAULT} ] || echo 1 > {_V6_DEFAULT}"])


def wire_hosts(bridge_netns: str, hosts: Sequence[Host], specs: Mapping[int, LinkSpec]) -> None:
    """Connect the hosts' namespaces (created already) to a bridge in
    ``bridge_netns`` and load the loss rules of ``specs`` (by host index)."""
    br = bridge_netns
    # Bridge namespace: the bridge and one veth pair per host, created
    # here with the peer end placed straight into the host's namespace.
    lines = [f"link add {BRIDGE_IF} type bridge stp_state 0 mcast_snooping 0", f"link set {BRIDGE_IF} up"]
    for h in hosts:
        lines.append(
            f"link add {h.port} address 02:00:00:01:{h.index >> 8:02x}:{h.index & 0xFF:02x} "
            f"type veth peer name {HOST_IF} netns {h.netns} address {h.mac}"
        )
        lines.append(f"link set {h.port} master {BRIDGE_IF} up")
    _run(["ip", "-n", br, "-batch", "-"], input="\n".join(lines) + "\n")
    # Static forwarding: every host's MAC is known, so the bridge never
    # floods unicast into other hosts' (shaped) downlinks.
    blines = []
    for h in hosts:
        blines.append(f"link set dev {h.port} learning off flood off")
        blines.append(f"fdb add {h.mac} dev {h.port} master static")
    _run(["bridge", "-n", br, "-batch", "-"], input="\n".join(blines) + "\n")

    # Host namespaces: lo up, address, static ARP for every other host.
    for h in hosts:
        lines = [
            "link set lo up",
            f"link set {HOST_IF} gso_max_segs 1",
            f"addr add {h.address}/{h.prefixlen} dev {HOST_IF}",
            f"link set {HOST_IF} up",
        ]
        lines += [
            f"neigh replace {o.address} lladdr {o.mac} dev {HOST_IF} nud permanent"
            for o in hosts
            if o is not h
        ]
        _run(["ip", "-n", h.netns, "-batch", "-"], input="\n".join(lines) + "\n")

    # Loss: one chain and one named counter per sending host.
    _run(["ip", "netns", "exec", br, "nft", "-f", "-"], input=nft_table(hosts, specs))
