"""A testbed's hosts: names, addresses, namespaces and MACs, and the link
spec each host starts with."""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from .spec import LinkSpec

__all__ = ["BRIDGE_IF", "HOST_IF", "Host", "check_host_names", "links_per_host", "plan_hosts"]

_HOST_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")
_IFNAMSIZ = 15  # Linux interface names: at most 15 characters.

#: A host's link interface, inside its namespace.
HOST_IF = "eth0"
#: The bridge, inside the bridge namespace.
BRIDGE_IF = "br0"


@dataclass(frozen=True)
class Host:
    """One emulated host: its namespace, address and interfaces."""

    name: str
    index: int  # 1-based; also the last octet(s) of the address in the default subnet
    address: str
    prefixlen: int
    netns: str
    mac: str
    port: str  # its bridge port, in the bridge namespace

    @property
    def interface(self) -> str:
        """Name of the host's link interface inside its namespace."""
        return HOST_IF


def check_host_names(names: Sequence[str]) -> None:
    """Refuse an empty list, names unfit for namespaces and interfaces, and duplicates."""
    if not names:
        raise ValueError("Testbed needs at least one host")
    for name in names:
        if not isinstance(name, str) or not _HOST_NAME_RE.match(name):
            raise ValueError(
                f"host name {name!r} must be 1-32 characters of letters, digits, '_' or '-', "
                "starting with a letter or digit"
            )
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"duplicate host names: {', '.join(dupes)}")


def links_per_host(names: Sequence[str], links: LinkSpec | Mapping[str, LinkSpec] | None) -> dict[str, LinkSpec]:
    """One spec for every host (the default link when ``links`` is None), or
    a spec per host that names exactly the hosts."""
    if links is None:
        links = LinkSpec()
    if isinstance(links, LinkSpec):
        return {n: links for n in names}
    unknown = sorted(set(links) - set(names))
    missing = [n for n in names if n not in links]
    if unknown or missing:
        raise ValueError(
            f"links must give a LinkSpec for exactly the hosts; missing: {missing or '-'}, "
            f"unknown: {unknown or '-'}"
        )
    specs = {}
    for n in names:
        if not isinstance(links[n], LinkSpec):
            raise ValueError(f"links[{n!r}] must be a LinkSpec, got {links[n]!r}")
        specs[n] = links[n]
    return specs


def plan_hosts(names: Sequence[str], subnet: str, run_id: str) -> dict[str, Host]:
    """The hosts, in the order given: addresses from ``subnet`` in turn, and
    namespaces named after ``run_id`` (so teardown and :func:`cleanup_stale` find them)."""
    net = ipaddress.ip_network(subnet)
    if not isinstance(net, ipaddress.IPv4Network):
        raise ValueError(f"subnet must be IPv4, got {subnet!r}")
    if net.num_addresses - 2 < len(names):
        raise ValueError(f"subnet {subnet} has room for {net.num_addresses - 2} hosts, need {len(names)}")
    if len(names) > 0xFFFF:
        raise ValueError("at most 65535 hosts")
    addresses = net.hosts()
    hosts: dict[str, Host] = {}
    for i, name in enumerate(names, start=1):
        port = f"p-{name}" if len(name) + 2 <= _IFNAMSIZ else f"p{i}"
        hosts[name] = Host(
            name=name,
            index=i,
            address=str(next(addresses)),
            prefixlen=net.prefixlen,
            netns=f"{run_id}-{name}",
            mac=f"02:00:00:00:{i >> 8:02x}:{i & 0xFF:02x}",
            port=port,
        )
    return hosts
