"""Reading a testbed's per-host link counters from the kernel: interface
statistics, qdisc drops, the loss rules' nftables counters, and the delay
line's own losses."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping

from .delayline import QueueStats
from .hosts import HOST_IF, Host
from .netns import _run
from .shaping import ETH_HEADER, NFT_TABLE
from .spec import LinkCounters

__all__ = ["read_counters"]


def read_counters(
    bridge_netns: str, hosts: Iterable[Host], delay_stats: Callable[[], Mapping[int, QueueStats]]
) -> dict[str, LinkCounters]:
    """Per-host counters since the testbed was set up, by host name."""
    cp = _run(["ip", "netns", "exec", bridge_netns, "nft", "-j", "list", "counters",
               "table", "bridge", NFT_TABLE])
    dropped: dict[str, tuple[int, int]] = {}
    for item in json.loads(cp.stdout).get("nftables", []):
        c = item.get("counter")
        if c:
            dropped[c["name"]] = (int(c["packets"]), int(c["bytes"]))
    down_drops: dict[str, int] = {}
    cp = _run(["tc", "-n", bridge_netns, "-s", "-j", "qdisc", "show"])
    for q in json.loads(cp.stdout or "[]"):
        if q.get("root"):
            down_drops[q.get("dev", "")] = int(q.get("drops", 0))
    # Burst losses and kernel-queue overflows of the delay line.
    delayed = delay_stats()
    out: dict[str, LinkCounters] = {}
    for h in hosts:
        cp = _run(["ip", "-n", h.netns, "-s", "-j", "link", "show", "dev", HOST_IF])
        stats = json.loads(cp.stdout)[0]["stats64"]
        cp = _run(["tc", "-n", h.netns, "-s", "-j", "qdisc", "show", "dev", HOST_IF])
        up_drops = sum(int(q.get("drops", 0)) for q in json.loads(cp.stdout or "[]") if q.get("root"))
        dp, db = dropped.get(f"dropped_h{h.index}", (0, 0))
        dl = delayed.get(h.index, QueueStats())
        out[h.name] = LinkCounters(
            tx_bytes=int(stats["tx"]["bytes"]),
            tx_packets=int(stats["tx"]["packets"]),
            rx_bytes=int(stats["rx"]["bytes"]),
            rx_packets=int(stats["rx"]["packets"]),
            dropped=dp + dl.dropped,
            # The bridge hook sees frames with the Ethernet header already
            # pulled; add it back so dropped_bytes compares with tx_bytes.
            dropped_bytes=db + dp * ETH_HEADER + dl.dropped_bytes,
            queue_drops=up_drops + down_drops.get(h.port, 0) + dl.kernel_drops,
        )
    return out
