"""Text of the kernel's link rules: tbf shapers (``tc -batch``) and the
nftables loss table (``nft -f``).  Pure functions; the testbed runs them."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol

from .spec import LOSS_SCALE, LinkSpec

__all__ = ["ETH_HEADER", "NFT_TABLE", "loss_rule", "nft_table", "queue_rule", "tc_lines"]

#: nftables table (family ``bridge``) holding the loss rules, in the bridge namespace.
NFT_TABLE = "coapkb"

#: Ethernet header bytes: the bridge hook sees frames with it already pulled.
ETH_HEADER = 14


class _Port(Protocol):
    """What the rule text needs of a host: its index and its bridge port."""

    @property
    def index(self) -> int: ...

    @property
    def port(self) -> str: ...


def loss_rule(index: int, spec: LinkSpec) -> str:
    """The nft rule that drops host ``index``'s packets with ``spec.loss_pct`` ("" = none)."""
    t = spec.loss_threshold
    if t <= 0 or spec.loss_model != "random":
        return ""  # burst loss is the delay line's
    return f'numgen random mod {LOSS_SCALE} < {t} counter name "dropped_h{index}" drop'


def nft_table(hosts: Sequence[_Port], links: Mapping[int, LinkSpec]) -> str:
    """The whole loss table: one chain and one named counter per sending host
    (``links`` by host index), dispatched on the bridge port a frame came in on."""
    nft = [f"table bridge {NFT_TABLE} {{"]
    for h in hosts:
        nft += [f"  counter dropped_h{h.index} {{", "  }", f"  chain loss_h{h.index} {{"]
        rule = loss_rule(h.index, links[h.index])
        if rule:
            nft.append(f"    {rule}")
        nft.append("  }")
    vmap = ", ".join(f'"{h.port}" : jump loss_h{h.index}' for h in hosts)
    nft += [
        "  chain forward {",
        # Priority -1: before br_netfilter's hook (0), which hands packets to
        # iptables and so to the delay line; a lost packet is not delayed first.
        "    type filter hook forward priority -1; policy accept;",
        f"    iifname vmap {{ {vmap} }}",
        "  }",
        "}",
    ]
    return "\n".join(nft) + "\n"


def tc_lines(dev: str, spec: LinkSpec) -> list[str]:
    """``tc -batch`` lines for ``dev``'s root qdisc ([] = leave it unshaped)."""
    if spec.rate_bit_s is None:
        return []
    return [
        f"qdisc add dev {dev} root handle 1: tbf rate {spec.rate_bit_s}bit "
        f"burst {spec.burst_bytes} limit {spec.limit_bytes}"
    ]


def queue_rule(port: str, queue: int) -> list[str]:
    """iptables arguments (after ``-A``/``-D FORWARD``) sending what enters the
    bridge from ``port`` to netfilter queue ``queue``, i.e. to the delay line.
    Needs ``br_netfilter`` (``bridge-nf-call-iptables=1`` in the bridge namespace);
    no ``--queue-bypass``: if the delay line is gone, packets are dropped,
    never passed on undelayed."""
    return ["-m", "physdev", "--physdev-in", port, "-j", "NFQUEUE", "--queue-num", str(queue)]
