"""Each host's :class:`LinkSpec` applied to the live testbed: tbf shapers on
both ends of its link, its nftables loss rule, and, for delay, jitter and
burst loss, its packets routed through the delay line."""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Mapping

from .delayline import DelayLine, QueueStats
from .hosts import HOST_IF, Host
from .netns import _run
from .shaping import NFT_TABLE, loss_rule, queue_rule, tc_lines
from .spec import LinkEmulationError, LinkSpec

__all__ = ["LinkControl", "require_delay_tools"]


def require_delay_tools(specs: Iterable[LinkSpec]) -> None:
    """Refuse delay, jitter and burst loss up front (before touching any
    link) when ``iptables`` is missing: it puts packets in the delay line's queue."""
    if any(s.needs_delay_line for s in specs) and shutil.which("iptables") is None:
        raise LinkEmulationError(
            "delay, jitter and burst loss need iptables (its NFQUEUE target feeds the delay line); "
            "install the Debian package iptables"
        )


class LinkControl:
    """The links of a wired testbed (:mod:`.topology`) and the spec each one runs.

    The delay line (``delay_line``) is started when a link first needs it
    and runs until :meth:`close`."""

    def __init__(self, bridge_netns: str, hosts: Mapping[str, Host], specs: dict[str, LinkSpec]) -> None:
        self.bridge_netns = bridge_netns
        self._hosts = hosts
        self._specs = specs
        self.delay_line: DelayLine | None = None
        self._queued: set[str] = set()  # hosts whose packets go to the delay line

    def spec(self, name: str) -> LinkSpec:
        """The spec currently applied to host ``name``."""
        return self._specs[name]

    def install(self) -> None:
        """Apply every host's spec to its freshly wired link."""
        hosts = list(self._hosts.values())
        for h in hosts:
            self._apply_shaping(h, self._specs[h.name], fresh=True)
        for h in hosts:
            self._apply_delay(h, self._specs[h.name])

    def set_link(self, h: Host, spec: LinkSpec) -> None:
        """Change ``h``'s link in place; see :meth:`Testbed.set_link`."""
        require_delay_tools([spec])
        self._apply_shaping(h, spec, fresh=False)
        rule = loss_rule(h.index, spec)
        script = f"flush chain bridge {NFT_TABLE} loss_h{h.index}\n"
        if rule:
            script += f"add rule bridge {NFT_TABLE} loss_h{h.index} {rule}\n"
        _run(["ip", "netns", "exec", self.bridge_netns, "nft", "-f", "-"], input=script)
        self._apply_delay(h, spec)
        self._specs[h.name] = spec

    def delay_stats(self) -> dict[int, QueueStats]:
        """The delay line's per-host losses and overflows ({} when it never ran);
        raises if it died, rather than leaving silent gaps in the counters."""
        return self.delay_line.stats() if self.delay_line is not None else {}

    def close(self) -> None:
        """Stop the delay line: closing its control pipe stops it; what it still holds is dropped."""
        if self.delay_line is not None:
            self.delay_line.close()
            self.delay_line = None

    def _apply_shaping(self, h: Host, spec: LinkSpec, *, fresh: bool) -> None:
        """(Re)install uplink and downlink qdiscs for ``h``."""
        for ns, dev in ((h.netns, HOST_IF), (self.bridge_netns, h.port)):
            if not fresh:
                # Deleting a root that is not there (noqueue) fails harmlessly.
                _run(["tc", "-n", ns, "qdisc", "del", "dev", dev, "root"], check=False)
            lines = tc_lines(dev, spec)
            if not lines:
                continue
            _run(["tc", "-n", ns, "-batch", "-"], input="\n".join(lines) + "\n")

    def _ensure_delay_line(self) -> DelayLine:
        if self.delay_line is None:
            # br_netfilter hands bridged IPv4 packets to iptables' FORWARD
            # chain; on by default in a new namespace, but say so.
            knob = "/proc/sys/net/bridge/bridge-nf-call-iptables"
            _run(["ip", "netns", "exec", self.bridge_netns, "sh", "-c", f"echo 1 > {knob}"])
            line = DelayLine(self.bridge_netns, [h.index for h in self._hosts.values()])
            self.delay_line = line  # before start: close() must stop a half-started one too
            line.start()
        return self.delay_line

    def _apply_delay(self, h: Host, spec: LinkSpec) -> None:
        """Route ``h``'s packets through the delay line if ``spec`` needs it, or stop doing so.

        The queue is configured before packets are sent to it; packets held at
        a change keep the release time they were given."""
        iptables = ["ip", "netns", "exec", self.bridge_netns, "iptables", "-w"]
        if spec.needs_delay_line:
            self._ensure_delay_line().configure(h.index, spec)
            if h.name not in self._queued:
                _run([*iptables, "-A", "FORWARD", *queue_rule(h.port, h.index)])
                self._queued.add(h.name)
        elif h.name in self._queued:
            _run([*iptables, "-D", "FORWARD", *queue_rule(h.port, h.index)])
            self._queued.discard(h.name)
