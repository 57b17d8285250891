"""The testbed: namespaces, bridge, shapers and loss rules for a set of hosts."""

from __future__ import annotations

import asyncio
import atexit
import ipaddress
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import FrameType, TracebackType
from typing import Any

from .netns import DEFAULT_PREFIX, _delete_netns, _kill_netns_processes, _list_netns, _run
from .delayline import DelayLine, QueueStats
from .shaping import ETH_HEADER, NFT_TABLE, loss_rule, nft_table, queue_rule, tc_lines
from .spec import LinkCounters, LinkEmulationError, LinkSpec

__all__ = ["Host", "Testbed"]

_HOST_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")
_V6_DEFAULT = "/proc/sys/net/ipv6/conf/default/disable_ipv6"
_IFNAMSIZ = 15  # Linux interface names: at most 15 characters.
_HOST_IF = "eth0"
_BRIDGE_IF = "br0"


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
        return _HOST_IF


# --------------------------------------------------------------------------
# The testbed
# --------------------------------------------------------------------------


def _sigterm_to_exit(signum: int, frame: FrameType | None) -> None:
    """SIGTERM handler: unwind like an exception so ``finally``/``__exit__`` clean up."""
    raise SystemExit(128 + signum)


class Testbed:
    """Namespaces, bridge, shapers and loss rules for a set of hosts.

    Use as a context manager (``with`` or ``async with``); teardown always
    runs -- after exceptions, Ctrl-C, SIGTERM (turned into ``SystemExit``
    while the testbed lives, if nothing else handles SIGTERM) and at
    interpreter exit (``atexit``).  Only SIGKILL escapes; for that, names
    carry the owner's pid and :func:`cleanup_stale` removes them later.

    Example::

        ok, why = available()
        if not ok:
            sys.exit(f"no link emulation: {why}")
        with Testbed(["robot1", "central"], LinkSpec(rate_kbit=128, loss_pct=10)) as tb:
            server = tb.popen("central", [sys.executable, "server.py", tb["central"].address])
            before = tb.counters()
            tb.run("robot1", [sys.executable, "client.py", tb.address("central")], check=True)
            used = tb.counters()["robot1"] - before["robot1"]
            tb.set_link("robot1", LinkSpec(rate_kbit=35))   # next run, same testbed

    Setup and teardown run synchronously (about 20 ms per host); the async
    context manager runs them in-line too, since they are not hot paths and
    a teardown that cannot be interrupted half-way is the point.
    """

    __test__ = False  # not a pytest test class despite the name

    def __init__(
        self,
        hosts: Iterable[str],
        links: LinkSpec | Mapping[str, LinkSpec] | None = None,
        *,
        subnet: str = "10.77.0.0/24",
        prefix: str = DEFAULT_PREFIX,
        kill_grace_s: float = 2.0,
    ) -> None:
        names = list(hosts)
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
        if not re.match(r"^[a-z]{1,8}$", prefix):
            raise ValueError(f"prefix must be 1-8 lowercase letters (the pid follows it), got {prefix!r}")

        if links is None:
            links = LinkSpec()
        if isinstance(links, LinkSpec):
            specs = {n: links for n in names}
        else:
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

        net = ipaddress.ip_network(subnet)
        if not isinstance(net, ipaddress.IPv4Network):
            raise ValueError(f"subnet must be IPv4, got {subnet!r}")
        if net.num_addresses - 2 < len(names):
            raise ValueError(f"subnet {subnet} has room for {net.num_addresses - 2} hosts, need {len(names)}")
        if len(names) > 0xFFFF:
            raise ValueError("at most 65535 hosts")

        self.run_id = f"{prefix}{os.getpid()}-{secrets.token_hex(2)}"
        self.bridge_netns = self.run_id
        self._kill_grace_s = kill_grace_s
        self._links: dict[str, LinkSpec] = specs
        addresses = net.hosts()
        self._hosts: dict[str, Host] = {}
        for i, name in enumerate(names, start=1):
            port = f"p-{name}" if len(name) + 2 <= _IFNAMSIZ else f"p{i}"
            self._hosts[name] = Host(
                name=name,
                index=i,
                address=str(next(addresses)),
                prefixlen=net.prefixlen,
                netns=f"{self.run_id}-{name}",
                mac=f"02:00:00:00:{i >> 8:02x}:{i & 0xFF:02x}",
                port=port,
            )
        self._created: list[str] = []
        self._popen: list[subprocess.Popen[Any]] = []
        self._aproc: list[asyncio.subprocess.Process] = []
        self._state = "new"  # new -> up -> closed
        self._prev_sigterm: Any = None
        self._installed_sigterm = False
        self._delay_line: DelayLine | None = None  # started when a link first needs it
        self._queued: set[str] = set()  # hosts whose packets go to the delay line
        self._owner_pid = os.getpid()

    # ---- lookup -----------------------------------------------------------

    @property
    def hosts(self) -> Mapping[str, Host]:
        """The hosts by name, in the order given."""
        return dict(self._hosts)

    def __getitem__(self, name: str) -> Host:
        return self.host(name)

    def host(self, name: str) -> Host:
        try:
            return self._hosts[name]
        except KeyError:
            raise KeyError(f"no host {name!r} in this testbed (hosts: {', '.join(self._hosts)})") from None

    def address(self, name: str) -> str:
        """The host's IPv4 address on the emulated link."""
        return self.host(name).address

    def link(self, name: str) -> LinkSpec:
        """The link spec currently applied to ``name``."""
        self.host(name)
        return self._links[name]

    @property
    def namespaces(self) -> list[str]:
        """Every namespace this testbed owns (bridge first)."""
        return [self.bridge_netns, *(h.netns for h in self._hosts.values())]

    def __repr__(self) -> str:
        return f"Testbed({self.run_id!r}, hosts={list(self._hosts)}, state={self._state})"

    # ---- lifecycle --------------------------------------------------------

    def __enter__(self) -> Testbed:
        self.setup()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    async def __aenter__(self) -> Testbed:
        self.setup()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    def setup(self) -> None:
        """Build everything; on any failure remove what was built and re-raise."""
        if self._state != "new":
            raise LinkEmulationError(f"testbed {self.run_id} was already set up")
        if os.geteuid() != 0:
            raise LinkEmulationError("link emulation needs root; see coapkb.bench.linkemu.available()")
        self._state = "up"
        atexit.register(self.close)
        self._install_sigterm()
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def _install_sigterm(self) -> None:
        # Only the main thread may set handlers; only take over SIGTERM when
        # nobody else handles it (an asyncio app's loop.add_signal_handler or
        # a benchmark's own handler stays in charge).
        if threading.current_thread() is not threading.main_thread():
            return
        current = signal.getsignal(signal.SIGTERM)
        if current is signal.SIG_DFL:
            self._prev_sigterm = current
            signal.signal(signal.SIGTERM, _sigterm_to_exit)
            self._installed_sigterm = True

    def _restore_sigterm(self) -> None:
        if not self._installed_sigterm:
            return
        self._installed_sigterm = False
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGTERM) in (_sigterm_to_exit, signal.SIG_IGN):
                signal.signal(signal.SIGTERM, self._prev_sigterm)

    def _add_netns(self, ns: str) -> None:
        _run(["ip", "netns", "add", ns])
        self._created.append(ns)
        # New interfaces in this namespace get IPv6 off (no RS/MLD/DAD noise on
        # the link); `lo` exists already and keeps ::1.
        # (Written with sh rather than sysctl(8): procps is not always installed.)
        _run(["ip", "netns", "exec", ns, "sh", "-c", f"[ ! -e {_V6_DEFAULT} ] || echo 1 > {_V6_DEFAULT}"])

    def _build(self) -> None:
        self._require_delay_tools(self._links.values())
        br = self.bridge_netns
        self._add_netns(br)
        hosts = list(self._hosts.values())
        for h in hosts:
            self._add_netns(h.netns)

        # Bridge namespace: the bridge and one veth pair per host, created
        # here with the peer end placed straight into the host's namespace.
        lines = [f"link add {_BRIDGE_IF} type bridge stp_state 0 mcast_snooping 0", f"link set {_BRIDGE_IF} up"]
        for h in hosts:
            lines.append(
                f"link add {h.port} address 02:00:00:01:{h.index >> 8:02x}:{h.index & 0xFF:02x} "
                f"type veth peer name {_HOST_IF} netns {h.netns} address {h.mac}"
            )
            lines.append(f"link set {h.port} master {_BRIDGE_IF} up")
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
                f"link set {_HOST_IF} gso_max_segs 1",
                f"addr add {h.address}/{h.prefixlen} dev {_HOST_IF}",
                f"link set {_HOST_IF} up",
            ]
            lines += [
                f"neigh replace {o.address} lladdr {o.mac} dev {_HOST_IF} nud permanent"
                for o in hosts
                if o is not h
            ]
            _run(["ip", "-n", h.netns, "-batch", "-"], input="\n".join(lines) + "\n")

        # Loss: one chain and one named counter per sending host.
        specs = {h.index: self._links[h.name] for h in hosts}
        _run(["ip", "netns", "exec", br, "nft", "-f", "-"], input=nft_table(hosts, specs))

        for h in hosts:
            self._apply_shaping(h, self._links[h.name], fresh=True)
        for h in hosts:
            self._apply_delay(h, self._links[h.name])

    def _apply_shaping(self, h: Host, spec: LinkSpec, *, fresh: bool) -> None:
        """(Re)install uplink and downlink qdiscs for ``h``."""
        for ns, dev in ((h.netns, _HOST_IF), (self.bridge_netns, h.port)):
            if not fresh:
                # Deleting a root that is not there (noqueue) fails harmlessly.
                _run(["tc", "-n", ns, "qdisc", "del", "dev", dev, "root"], check=False)
            lines = tc_lines(dev, spec)
            if not lines:
                continue
            _run(["tc", "-n", ns, "-batch", "-"], input="\n".join(lines) + "\n")

    @staticmethod
    def _require_delay_tools(specs: Iterable[LinkSpec]) -> None:
        """Refuse delay, jitter and burst loss up front (before touching any
        link) when ``iptables`` is missing: it puts packets in the delay line's queue."""
        if any(s.needs_delay_line for s in specs) and shutil.which("iptables") is None:
            raise LinkEmulationError(
                "delay, jitter and burst loss need iptables (its NFQUEUE target feeds the delay line); "
                "install the Debian package iptables"
            )

    def _ensure_delay_line(self) -> DelayLine:
        if self._delay_line is None:
            # br_netfilter hands bridged IPv4 packets to iptables' FORWARD
            # chain; on by default in a new namespace, but say so.
            knob = "/proc/sys/net/bridge/bridge-nf-call-iptables"
            _run(["ip", "netns", "exec", self.bridge_netns, "sh", "-c", f"echo 1 > {knob}"])
            line = DelayLine(self.bridge_netns, [h.index for h in self._hosts.values()])
            self._delay_line = line  # before start: close() must stop a half-started one too
            line.start()
        return self._delay_line

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

    def set_link(self, name: str, spec: LinkSpec) -> None:
        """Change ``name``'s link in place (between runs; counters keep counting).

        The loss rule is swapped atomically; the shapers are replaced, so
        packets queued in them at that moment are discarded.
        """
        if not isinstance(spec, LinkSpec):
            raise ValueError(f"spec must be a LinkSpec, got {spec!r}")
        h = self.host(name)
        self._require_up()
        self._require_delay_tools([spec])
        self._apply_shaping(h, spec, fresh=False)
        rule = loss_rule(h.index, spec)
        script = f"flush chain bridge {NFT_TABLE} loss_h{h.index}\n"
        if rule:
            script += f"add rule bridge {NFT_TABLE} loss_h{h.index} {rule}\n"
        _run(["ip", "netns", "exec", self.bridge_netns, "nft", "-f", "-"], input=script)
        self._apply_delay(h, spec)
        self._links[name] = spec

    def _require_up(self) -> None:
        if self._state != "up":
            raise LinkEmulationError(f"testbed {self.run_id} is {self._state}, not set up")

    def close(self) -> None:
        """Kill the hosts' processes and delete every namespace. Idempotent.

        Raises :class:`LinkEmulationError` only if something could not be
        removed (after trying to remove everything else).
        """
        if self._state == "closed" or os.getpid() != self._owner_pid:
            return  # a forked child (inheriting atexit hooks) must not tear down its parent's testbed
        self._state = "closed"
        if self._installed_sigterm and threading.current_thread() is threading.main_thread():
            # A second SIGTERM must not cut the teardown short.
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            atexit.unregister(self.close)
            for p in self._popen:
                if p.poll() is None:
                    try:
                        p.terminate()
                    except ProcessLookupError:
                        pass
            for ap in self._aproc:
                if ap.returncode is None:
                    try:
                        ap.terminate()
                    except ProcessLookupError:
                        pass
            if self._delay_line is not None:
                # Closing its control pipe stops it; what it still holds is dropped.
                self._delay_line.close()
                self._delay_line = None
            mine = self._owned_namespaces()
            survivors = _kill_netns_processes(mine, self._kill_grace_s)
            for p in self._popen:
                try:
                    p.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    p.kill()
            problems = [f"processes {survivors} survived SIGKILL"] if survivors else []
            # Hosts first, the bridge namespace last.
            for ns in sorted(mine, key=lambda n: n == self.bridge_netns):
                try:
                    _delete_netns(ns)
                except LinkEmulationError as e:
                    problems.append(str(e))
            if problems:
                raise LinkEmulationError(f"teardown of {self.run_id} incomplete: {'; '.join(problems)}")
        finally:
            self._popen.clear()
            self._restore_sigterm()

    async def aclose(self) -> None:
        """Async teardown: lets the event loop reap :meth:`spawn`'ed processes first."""
        if self._state == "closed":
            return
        live = [p for p in self._aproc if p.returncode is None]
        for p in live:
            try:
                p.terminate()
            except ProcessLookupError:
                pass
        if live:
            await asyncio.wait(
                [asyncio.ensure_future(p.wait()) for p in live], timeout=self._kill_grace_s
            )
        for p in live:
            if p.returncode is None:
                try:
                    p.kill()
                except ProcessLookupError:
                    pass
        self.close()
        for p in live:
            if p.returncode is None:
                try:
                    await asyncio.wait_for(p.wait(), 2.0)
                except TimeoutError:
                    pass
        self._aproc.clear()

    def _owned_namespaces(self) -> list[str]:
        """What we created plus anything carrying our run id (partial setups)."""
        names = list(dict.fromkeys(self._created))
        for ns in _list_netns():
            if (ns == self.run_id or ns.startswith(self.run_id + "-")) and ns not in names:
                names.append(ns)
        return names

    # ---- processes --------------------------------------------------------

    def exec_args(self, name: str, argv: Sequence[str]) -> list[str]:
        """``argv`` prefixed so that it runs inside host ``name``'s namespace."""
        if isinstance(argv, str):
            raise TypeError("argv must be a sequence of arguments, not a string")
        return ["ip", "netns", "exec", self.host(name).netns, *argv]

    def popen(self, name: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` in host ``name``; it is killed at teardown if still running.

        ``ip netns exec`` execs the command, so the returned process *is* the
        command (same pid), not a wrapper.
        """
        self._require_up()
        p = subprocess.Popen(self.exec_args(name, argv), **kwargs)
        self._popen.append(p)
        return p

    def run(self, name: str, argv: Sequence[str], **kwargs: Any) -> subprocess.CompletedProcess[Any]:
        """``subprocess.run`` of ``argv`` inside host ``name``."""
        self._require_up()
        return subprocess.run(self.exec_args(name, argv), **kwargs)

    async def spawn(self, name: str, argv: Sequence[str], **kwargs: Any) -> asyncio.subprocess.Process:
        """Async :meth:`popen` (``asyncio.create_subprocess_exec``); killed at teardown."""
        self._require_up()
        p = await asyncio.create_subprocess_exec(*self.exec_args(name, argv), **kwargs)
        self._aproc.append(p)
        return p

    # ---- counters ---------------------------------------------------------

    def counters(self) -> dict[str, LinkCounters]:
        """Per-host link counters since setup (subtract two readings for a run)."""
        self._require_up()
        cp = _run(["ip", "netns", "exec", self.bridge_netns, "nft", "-j", "list", "counters",
                   "table", "bridge", NFT_TABLE])
        dropped: dict[str, tuple[int, int]] = {}
        for item in json.loads(cp.stdout).get("nftables", []):
            c = item.get("counter")
            if c:
                dropped[c["name"]] = (int(c["packets"]), int(c["bytes"]))
        down_drops: dict[str, int] = {}
        cp = _run(["tc", "-n", self.bridge_netns, "-s", "-j", "qdisc", "show"])
        for q in json.loads(cp.stdout or "[]"):
            if q.get("root"):
                down_drops[q.get("dev", "")] = int(q.get("drops", 0))
        # Burst losses and kernel-queue overflows of the delay line; a delay
        # line that died raises here rather than leaving silent gaps.
        delayed = self._delay_line.stats() if self._delay_line is not None else {}
        out: dict[str, LinkCounters] = {}
        for h in self._hosts.values():
            cp = _run(["ip", "-n", h.netns, "-s", "-j", "link", "show", "dev", _HOST_IF])
            stats = json.loads(cp.stdout)[0]["stats64"]
            cp = _run(["tc", "-n", h.netns, "-s", "-j", "qdisc", "show", "dev", _HOST_IF])
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

    async def acounters(self) -> dict[str, LinkCounters]:
        """:meth:`counters` off the event loop (it runs a few short commands per host)."""
        return await asyncio.to_thread(self.counters)
