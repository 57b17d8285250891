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

Delay and jitter need the kernel's ``sch_netem``.  Where the kernel has it,
``delay_ms`` is applied with netem under the uplink shaper; where it lacks it
(as on the machine this was written on), a spec with ``delay_ms > 0`` is
refused with a clear error rather than approximated.

Everything here needs root (``CAP_NET_ADMIN``) and the Debian packages
``iproute2`` (``ip``, ``tc``, ``bridge``) and ``nftables`` (``nft``); call
:func:`available` first and print its reason when it says no.  Without root,
CoAP-only runs can use :class:`UdpRelay`, a user-space relay whose results
must be labelled as such (it emulates a path, not a host's link).
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import ctypes
import ipaddress
import json
import math
import os
import random
import re
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from types import FrameType, TracebackType
from typing import Any, cast

from ..errors import CoapkbError

__all__ = [
    "ETH_FRAME_MAX",
    "DEFAULT_QUEUE_BYTES",
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

#: Prefix of every namespace this module creates: ``<prefix><pid>-<tok>[-host]``.
DEFAULT_PREFIX = "ckb"

#: Largest frame on the emulated link: 1500-byte MTU plus the 14-byte Ethernet
#: header (``tc`` sees frames without preamble or FCS).
ETH_FRAME_MAX = 1514

#: Token-bucket depth floor.  It must hold one full frame (tbf cannot send a
#: packet larger than its bucket) with margin for tc's rounding to timer
#: ticks, and stay below two full frames so back-to-back frames are already
#: paced: after an idle period a link sends at most ~2 KiB at "line rate",
#: which is 0.47 s worth of credit at 35 kbit/s but invisible in the
#: long-run rate.
MIN_BURST_BYTES = 2048

#: Above ~4 Mbit/s the bucket grows to 4 ms of traffic so the shaper's timer
#: does not have to fire for every single frame.
BURST_SECONDS = 0.004

#: Default tbf queue: 1000 full frames, i.e. what a real NIC queues with
#: Linux's default ``txqueuelen`` of 1000.  Bursty query traffic (nine robots
#: answering the central at once, a ZeroMQ/TCP window) fits without queue
#: drops, which would otherwise confound the loss setting; drops that do
#: happen are reported separately as :attr:`LinkCounters.queue_drops`.
DEFAULT_QUEUE_BYTES = 1000 * ETH_FRAME_MAX

#: Loss is drawn as ``numgen random mod LOSS_SCALE < threshold``: 0.01 % steps.
LOSS_SCALE = 10_000

_HOST_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")
_ETH_HEADER = 14
_V6_DEFAULT = "/proc/sys/net/ipv6/conf/default/disable_ipv6"
_IFNAMSIZ = 15  # Linux interface names: at most 15 characters.
_HOST_IF = "eth0"
_BRIDGE_IF = "br0"
_NFT_TABLE = "coapkb"


class LinkEmulationError(CoapkbError, RuntimeError):
    """Setting up, changing or tearing down the emulated network failed."""


# --------------------------------------------------------------------------
# Link specification and counters
# --------------------------------------------------------------------------


def _check_number(field: str, value: object, *, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"LinkSpec.{field} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"LinkSpec.{field} must be finite, got {value!r}")


@dataclass(frozen=True)
class LinkSpec:
    """How one host's link behaves (applied to both directions unless noted).

    ``rate_kbit``
        Link rate in kbit/s (1 kbit = 1000 bit, as in ``tc``), counted in
        Ethernet frames without preamble/FCS (UDP payload + 42 bytes for
        IPv4).  ``None`` = unshaped (as fast as veth goes).
    ``loss_pct``
        Percent (0..100, 0.01 % steps) of the packets *this host sends* that
        are lost after having used its link.
    ``delay_ms``
        One-way delay added to packets this host sends.  Needs ``sch_netem``
        in the kernel; refused otherwise (see :func:`Testbed.set_link`).
    ``queue_bytes``
        Shaper queue limit in bytes; ``None`` = :data:`DEFAULT_QUEUE_BYTES`.
    """

    rate_kbit: float | None = None
    loss_pct: float = 0.0
    delay_ms: float = 0.0
    queue_bytes: int | None = None

    def __post_init__(self) -> None:
        _check_number("rate_kbit", self.rate_kbit, allow_none=True)
        if self.rate_kbit is not None and not 1.0 <= self.rate_kbit <= 10_000_000:
            raise ValueError(
                f"LinkSpec.rate_kbit must be None (unshaped) or 1..10000000 kbit/s, got {self.rate_kbit!r}"
            )
        _check_number("loss_pct", self.loss_pct)
        if not 0.0 <= self.loss_pct <= 100.0:
            raise ValueError(f"LinkSpec.loss_pct must be within 0..100, got {self.loss_pct!r}")
        _check_number("delay_ms", self.delay_ms)
        if not 0.0 <= self.delay_ms <= 60_000:
            raise ValueError(f"LinkSpec.delay_ms must be within 0..60000, got {self.delay_ms!r}")
        if self.queue_bytes is not None:
            if isinstance(self.queue_bytes, bool) or not isinstance(self.queue_bytes, int):
                raise ValueError(f"LinkSpec.queue_bytes must be an int or None, got {self.queue_bytes!r}")
            if self.queue_bytes < 2 * ETH_FRAME_MAX:
                raise ValueError(
                    f"LinkSpec.queue_bytes must be at least {2 * ETH_FRAME_MAX} (two full frames), "
                    f"got {self.queue_bytes!r}"
                )

    @property
    def rate_bit_s(self) -> int | None:
        """The rate in bit/s as given to ``tc`` (``None`` = unshaped)."""
        return None if self.rate_kbit is None else max(1, round(self.rate_kbit * 1000))

    @property
    def burst_bytes(self) -> int:
        """Token-bucket depth (see :data:`MIN_BURST_BYTES`)."""
        if self.rate_bit_s is None:
            return MIN_BURST_BYTES
        return max(MIN_BURST_BYTES, math.ceil(self.rate_bit_s / 8 * BURST_SECONDS))

    @property
    def limit_bytes(self) -> int:
        """Shaper queue limit in bytes."""
        return DEFAULT_QUEUE_BYTES if self.queue_bytes is None else self.queue_bytes

    @property
    def loss_threshold(self) -> int:
        """``numgen random mod LOSS_SCALE < loss_threshold`` drops a packet."""
        return round(self.loss_pct * LOSS_SCALE / 100)

    def __str__(self) -> str:
        rate = "unshaped" if self.rate_kbit is None else f"{self.rate_kbit:g} kbit/s"
        extra = f", {self.delay_ms:g} ms delay" if self.delay_ms else ""
        return f"{rate}, {self.loss_pct:g} % loss{extra}"


@dataclass(frozen=True)
class LinkCounters:
    """Traffic on one host's link, counted where the host puts it on the link.

    ``tx_*`` are frames the host's ``eth0`` handed to the link (after its
    uplink shaper, *before* the loss rule, so lost packets are included);
    ``rx_*`` are frames delivered to it.  ``dropped``/``dropped_bytes`` are
    the host's transmitted frames removed by the loss rule; ``queue_drops``
    counts frames the shapers' queues (uplink and downlink) discarded because
    they were full -- it should stay 0 in a benchmark.
    """

    tx_bytes: int = 0
    tx_packets: int = 0
    rx_bytes: int = 0
    rx_packets: int = 0
    dropped: int = 0
    dropped_bytes: int = 0
    queue_drops: int = 0

    def __sub__(self, other: LinkCounters) -> LinkCounters:
        """Difference between two readings (``after - before``)."""
        return LinkCounters(
            self.tx_bytes - other.tx_bytes,
            self.tx_packets - other.tx_packets,
            self.rx_bytes - other.rx_bytes,
            self.rx_packets - other.rx_packets,
            self.dropped - other.dropped,
            self.dropped_bytes - other.dropped_bytes,
            self.queue_drops - other.queue_drops,
        )


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
# Small command helpers
# --------------------------------------------------------------------------


def _run(
    argv: Sequence[str],
    *,
    input: str | None = None,
    check: bool = True,
    timeout: float = 30.0,
) -> subprocess.CompletedProcess[str]:
    """Run one setup command; failures become :class:`LinkEmulationError` with stderr."""
    try:
        cp = subprocess.run(
            list(argv), input=input, capture_output=True, text=True, timeout=timeout, check=False
        )
    except FileNotFoundError as e:
        raise LinkEmulationError(f"{argv[0]!r} not found ({e}); install iproute2 and nftables") from e
    except subprocess.TimeoutExpired as e:
        raise LinkEmulationError(f"`{shlex.join(argv)}` timed out after {timeout} s") from e
    if check and cp.returncode != 0:
        detail = (cp.stderr or cp.stdout).strip()
        raise LinkEmulationError(f"`{shlex.join(argv)}` failed (exit {cp.returncode}): {detail}")
    return cp


def _list_netns() -> list[str]:
    """Names of all named network namespaces (``ip netns list``)."""
    cp = _run(["ip", "netns", "list"], check=False)
    if cp.returncode != 0:
        return []
    return [line.split()[0] for line in cp.stdout.splitlines() if line.strip()]


def _netns_pids(ns: str) -> list[int]:
    """Processes living in namespace ``ns`` (zombies are not listed)."""
    cp = _run(["ip", "netns", "pids", ns], check=False)
    if cp.returncode != 0:
        return []
    me = os.getpid()
    return [int(tok) for tok in cp.stdout.split() if tok.isdigit() and int(tok) != me]


def _kill_netns_processes(namespaces: Iterable[str], grace_s: float) -> list[int]:
    """SIGTERM everything in ``namespaces``, SIGKILL what survives ``grace_s``.

    Returns the pids still alive at the end (normally none).
    """
    namespaces = list(namespaces)

    def alive() -> list[int]:
        return [pid for ns in namespaces for pid in _netns_pids(ns)]

    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        pids = alive()
        if not pids:
            return []
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            time.sleep(0.05)
            if not alive():
                return []
    return alive()


def _delete_netns(ns: str) -> None:
    cp = _run(["ip", "netns", "delete", ns], check=False)
    if cp.returncode != 0 and ns in _list_netns():
        raise LinkEmulationError(f"could not delete namespace {ns}: {cp.stderr.strip()}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:
        return False
    return True


def _stale_re(prefix: str) -> re.Pattern[str]:
    return re.compile(rf"^{re.escape(prefix)}(\d+)-[0-9a-f]{{4}}(?:-.+)?$")


def cleanup_stale(prefix: str = DEFAULT_PREFIX, *, grace_s: float = 1.0) -> list[str]:
    """Remove namespaces left behind by crashed runs (e.g. after SIGKILL).

    A namespace is stale when its name has the form ``<prefix><pid>-<tok>...``
    and process ``pid`` no longer exists.  Namespaces of live runs are kept.
    Processes still running inside a stale namespace are killed first.
    (A pid reused by an unrelated process keeps its namespaces until that
    process exits too; that errs on the safe side.)  Returns the names removed.
    """
    if os.geteuid() != 0:
        return []
    pattern = _stale_re(prefix)
    stale = [
        ns
        for ns in _list_netns()
        if (m := pattern.match(ns)) is not None and not _pid_alive(int(m.group(1)))
    ]
    if not stale:
        return []
    _kill_netns_processes(stale, grace_s)
    removed = []
    for ns in stale:
        try:
            _delete_netns(ns)
        except LinkEmulationError:
            continue
        removed.append(ns)
    return removed


def available() -> tuple[bool, str]:
    """Whether namespace link emulation can run here, with the reason if not.

    Checks root, the tools (``ip``, ``tc``, ``bridge``, ``nft``) and then
    actually builds a throw-away namespace with a veth pair, a tbf shaper and
    an nftables bridge table using ``numgen`` -- the kernel features the
    testbed needs -- and removes it again.  Takes ~50 ms.
    """
    if not sys.platform.startswith("linux"):
        return False, f"link emulation needs Linux network namespaces (this is {sys.platform})"
    if os.geteuid() != 0:
        return False, "link emulation needs root (network namespaces, tc and nftables need CAP_NET_ADMIN)"
    missing = [tool for tool in ("ip", "tc", "bridge", "nft") if shutil.which(tool) is None]
    if missing:
        return False, (
            f"missing {', '.join(missing)}: install the Debian packages iproute2 (ip, tc, bridge) "
            "and nftables (nft)"
        )
    ns = f"{DEFAULT_PREFIX}{os.getpid()}-{secrets.token_hex(2)}-probe"
    steps: list[tuple[str, list[str], str | None]] = [
        ("create a network namespace", ["ip", "netns", "add", ns], None),
        ("create a bridge", ["ip", "-n", ns, "link", "add", "br0", "type", "bridge"], None),
        (
            "create a veth pair",
            ["ip", "-n", ns, "link", "add", "pa", "type", "veth", "peer", "name", "pb"],
            None,
        ),
        (
            "add a tbf shaper (CONFIG_NET_SCH_TBF)",
            ["tc", "-n", ns, "qdisc", "add", "dev", "pa", "root", "tbf", "rate", "35kbit",
             "burst", "2048", "limit", "100000"],
            None,
        ),
        (
            "load an nftables bridge table with numgen (CONFIG_NF_TABLES_BRIDGE, CONFIG_NFT_NUMGEN)",
            ["ip", "netns", "exec", ns, "nft", "-f", "-"],
            "table bridge ckbprobe {\n chain forward {\n  type filter hook forward priority 0; policy accept;\n"
            "  numgen random mod 10000 < 1 counter drop\n }\n}\n",
        ),
    ]
    try:
        for what, argv, stdin in steps:
            try:
                _run(argv, input=stdin, timeout=10)
            except LinkEmulationError as e:
                return False, f"cannot {what}: {e}"
        return True, "network namespaces, veth, bridge, tbf and nftables bridge loss are available"
    finally:
        if ns in _list_netns():
            _run(["ip", "netns", "delete", ns], check=False)


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
        self._netem: bool | None = None  # probed on first use of delay_ms
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
        nft = [f"table bridge {_NFT_TABLE} {{"]
        for h in hosts:
            nft += [f"  counter dropped_h{h.index} {{", "  }", f"  chain loss_h{h.index} {{"]
            rule = self._loss_rule(h, self._links[h.name])
            if rule:
                nft.append(f"    {rule}")
            nft.append("  }")
        vmap = ", ".join(f'"{h.port}" : jump loss_h{h.index}' for h in hosts)
        nft += [
            "  chain forward {",
            "    type filter hook forward priority 0; policy accept;",
            f"    iifname vmap {{ {vmap} }}",
            "  }",
            "}",
        ]
        _run(["ip", "netns", "exec", br, "nft", "-f", "-"], input="\n".join(nft) + "\n")

        self._require_netem(self._links.values())
        for h in hosts:
            self._apply_shaping(h, self._links[h.name], fresh=True)

    @staticmethod
    def _loss_rule(h: Host, spec: LinkSpec) -> str:
        t = spec.loss_threshold
        if t <= 0:
            return ""
        return f'numgen random mod {LOSS_SCALE} < {t} counter name "dropped_h{h.index}" drop'

    def _apply_shaping(self, h: Host, spec: LinkSpec, *, fresh: bool) -> None:
        """(Re)install uplink and downlink qdiscs for ``h``."""
        for ns, dev, uplink in ((h.netns, _HOST_IF, True), (self.bridge_netns, h.port, False)):
            if not fresh:
                # Deleting a root that is not there (noqueue) fails harmlessly.
                _run(["tc", "-n", ns, "qdisc", "del", "dev", dev, "root"], check=False)
            lines = []
            delay = spec.delay_ms if uplink else 0.0
            if spec.rate_bit_s is not None:
                lines.append(
                    f"qdisc add dev {dev} root handle 1: tbf rate {spec.rate_bit_s}bit "
                    f"burst {spec.burst_bytes} limit {spec.limit_bytes}"
                )
                if delay:
                    lines.append(f"qdisc add dev {dev} parent 1:1 handle 10: netem delay {delay:g}ms limit 100000")
            elif delay:
                lines.append(f"qdisc add dev {dev} root handle 1: netem delay {delay:g}ms limit 100000")
            if not lines:
                continue
            _run(["tc", "-n", ns, "-batch", "-"], input="\n".join(lines) + "\n")

    def _require_netem(self, specs: Iterable[LinkSpec]) -> None:
        """Refuse delay up front (before touching any link) when the kernel lacks netem."""
        delays = [s.delay_ms for s in specs if s.delay_ms > 0]
        if not delays:
            return
        if self._netem is None:
            probe = ["tc", "-n", self.bridge_netns, "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms"]
            self._netem = _run(probe, check=False).returncode == 0
            _run(["tc", "-n", self.bridge_netns, "qdisc", "del", "dev", "lo", "root"], check=False)
        if not self._netem:
            raise LinkEmulationError(
                f"delay_ms={max(delays):g} needs the kernel's sch_netem (CONFIG_NET_SCH_NETEM), "
                "which this kernel lacks; use delay_ms=0 (delay is not emulated without netem)"
            )

    def set_link(self, name: str, spec: LinkSpec) -> None:
        """Change ``name``'s link in place (between runs; counters keep counting).

        The loss rule is swapped atomically; the shapers are replaced, so
        packets queued in them at that moment are discarded.
        """
        if not isinstance(spec, LinkSpec):
            raise ValueError(f"spec must be a LinkSpec, got {spec!r}")
        h = self.host(name)
        self._require_up()
        self._require_netem([spec])
        self._apply_shaping(h, spec, fresh=False)
        rule = self._loss_rule(h, spec)
        script = f"flush chain bridge {_NFT_TABLE} loss_h{h.index}\n"
        if rule:
            script += f"add rule bridge {_NFT_TABLE} loss_h{h.index} {rule}\n"
        _run(["ip", "netns", "exec", self.bridge_netns, "nft", "-f", "-"], input=script)
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
                   "table", "bridge", _NFT_TABLE])
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
        out: dict[str, LinkCounters] = {}
        for h in self._hosts.values():
            cp = _run(["ip", "-n", h.netns, "-s", "-j", "link", "show", "dev", _HOST_IF])
            stats = json.loads(cp.stdout)[0]["stats64"]
            cp = _run(["tc", "-n", h.netns, "-s", "-j", "qdisc", "show", "dev", _HOST_IF])
            up_drops = sum(int(q.get("drops", 0)) for q in json.loads(cp.stdout or "[]") if q.get("root"))
            dp, db = dropped.get(f"dropped_h{h.index}", (0, 0))
            out[h.name] = LinkCounters(
                tx_bytes=int(stats["tx"]["bytes"]),
                tx_packets=int(stats["tx"]["packets"]),
                rx_bytes=int(stats["rx"]["bytes"]),
                rx_packets=int(stats["rx"]["packets"]),
                dropped=dp,
                # The bridge hook sees frames with the Ethernet header already
                # pulled; add it back so dropped_bytes compares with tx_bytes.
                dropped_bytes=db + dp * _ETH_HEADER,
                queue_drops=up_drops + down_drops.get(h.port, 0),
            )
        return out

    async def acounters(self) -> dict[str, LinkCounters]:
        """:meth:`counters` off the event loop (it runs a few short commands per host)."""
        return await asyncio.to_thread(self.counters)


# --------------------------------------------------------------------------
# Running code of *this* process inside a host's namespace
# --------------------------------------------------------------------------

#: ``CLONE_NEWNET`` from <sched.h>: the namespace type argument of setns(2).
CLONE_NEWNET = 0x40000000


def _setns(fd: int, what: str) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise LinkEmulationError(f"setns into {what} failed: {os.strerror(err)}")


@contextlib.contextmanager
def enter_netns(name: str) -> Iterator[None]:
    """Move the **calling thread** into network namespace ``name`` (as listed
    by ``ip netns``, e.g. ``testbed["feeder"].netns``) and back on exit.

    Why: a benchmark's task feeder runs in the benchmark process itself
    (:meth:`coapkb.harness.team.Team.run`), yet its traffic must cross an emulated
    link like every other host's.  A socket belongs to the namespace of the
    thread that *creates* it, for its whole life, so code that opens its
    sockets inside this block talks from ``name`` even while an event loop
    interleaves it with other work; sockets created before stay where they
    were.  Threads started inside the block (a ZeroMQ context's I/O threads,
    executor threads) inherit ``name`` and keep it after the block ends.

    The original namespace is the calling thread's own
    (``/proc/thread-self/ns/net``, not ``/proc/self``, which is the main
    thread's), kept open as a file descriptor so the way back works even if
    ``name`` is deleted meanwhile.  Needs ``CAP_SYS_ADMIN``; failures raise
    :class:`LinkEmulationError`.
    """
    if "/" in name or not name:
        raise ValueError(f"not a namespace name: {name!r}")
    try:
        original = os.open("/proc/thread-self/ns/net", os.O_RDONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise LinkEmulationError(f"cannot open this thread's network namespace: {exc.strerror}") from None
    try:
        try:
            target = os.open(f"/run/netns/{name}", os.O_RDONLY | os.O_CLOEXEC)
        except OSError as exc:
            raise LinkEmulationError(f"no network namespace {name!r}: {exc.strerror}") from None
        try:
            _setns(target, f"namespace {name!r}")
        finally:
            os.close(target)
        try:
            yield
        finally:
            _setns(original, "the original namespace")
    finally:
        os.close(original)


# --------------------------------------------------------------------------
# Fallback without root: a user-space UDP relay (labelled, CoAP only)
# --------------------------------------------------------------------------

#: Bytes a UDP/IPv4 datagram occupies on an Ethernet link beyond its payload
#: (14 Ethernet + 20 IPv4 + 8 UDP).  The relay charges it so its rates mean
#: the same as the kernel testbed's.
UDP_IPV4_OVERHEAD = 42


class _Direction:
    """One direction of a relayed path: FIFO, token bucket, then loss, then delay.

    Same order as the kernel testbed: a datagram waits for tokens, "uses the
    link" (counted in ``tx``), and only then may be lost.  Timing comes from
    the event loop's timers, so it is only as precise as the loop is idle.
    """

    def __init__(self, spec: LinkSpec, rng: random.Random, loop: asyncio.AbstractEventLoop, overhead: int) -> None:
        self.spec = spec
        self._rng = rng
        self._loop = loop
        self._overhead = overhead
        self._queue: deque[tuple[bytes, Callable[[bytes], None]]] = deque()
        self._queued_bytes = 0
        self._tokens = float(spec.burst_bytes)
        self._stamp = loop.time()
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False
        self.tx_bytes = self.tx_packets = self.rx_bytes = self.rx_packets = 0
        self.dropped = self.dropped_bytes = self.queue_drops = 0

    def counters(self) -> LinkCounters:
        return LinkCounters(
            self.tx_bytes, self.tx_packets, self.rx_bytes, self.rx_packets,
            self.dropped, self.dropped_bytes, self.queue_drops,
        )

    def push(self, data: bytes, deliver: Callable[[bytes], None]) -> None:
        if self._closed:
            return
        frame = len(data) + self._overhead
        if self.spec.rate_bit_s is not None and self._queued_bytes + frame > self.spec.limit_bytes:
            self.queue_drops += 1
            return
        self._queue.append((data, deliver))
        self._queued_bytes += frame
        if self._timer is None:
            self._pump()

    def _pump(self) -> None:
        self._timer = None
        rate = self.spec.rate_bit_s
        burst = self.spec.burst_bytes
        while self._queue and not self._closed:
            data, deliver = self._queue[0]
            frame = len(data) + self._overhead
            if rate is not None:
                now = self._loop.time()
                self._tokens = min(float(burst), self._tokens + (now - self._stamp) * rate / 8)
                self._stamp = now
                # A datagram larger than the bucket goes once the bucket is
                # full and leaves a debt, so the long-run rate stays exact.
                need = min(frame, burst)
                if self._tokens < need:
                    self._timer = self._loop.call_later((need - self._tokens) * 8 / rate, self._pump)
                    return
                self._tokens -= frame
            self._queue.popleft()
            self._queued_bytes -= frame
            self._transmit(data, frame, deliver)

    def _transmit(self, data: bytes, frame: int, deliver: Callable[[bytes], None]) -> None:
        self.tx_bytes += frame
        self.tx_packets += 1
        if self.spec.loss_pct and self._rng.random() * 100 < self.spec.loss_pct:
            self.dropped += 1
            self.dropped_bytes += frame
            return
        self.rx_bytes += frame
        self.rx_packets += 1
        if self.spec.delay_ms:
            self._loop.call_later(self.spec.delay_ms / 1000, self._deliver, data, deliver)
        else:
            deliver(data)

    def _deliver(self, data: bytes, deliver: Callable[[bytes], None]) -> None:
        if not self._closed:
            deliver(data)

    def close(self) -> None:
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._queue.clear()


class _Listener(asyncio.DatagramProtocol):
    def __init__(self, relay: UdpRelay) -> None:
        self._relay = relay

    def datagram_received(self, data: bytes, addr: tuple[Any, ...]) -> None:
        self._relay._from_client(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP errors: the path is lossy anyway
        pass


class _Upstream(asyncio.DatagramProtocol):
    """The relay's socket towards the target for one client (NAT-style)."""

    def __init__(self, relay: UdpRelay, client: tuple[Any, ...]) -> None:
        self._relay = relay
        self._client = client
        self.transport: asyncio.DatagramTransport | None = None
        self.pending: list[bytes] = []

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = dgram = cast(asyncio.DatagramTransport, transport)
        for data in self.pending:
            dgram.sendto(data)
        self.pending.clear()

    def send(self, data: bytes) -> None:
        if self.transport is None:
            self.pending.append(data)
        elif not self.transport.is_closing():
            self.transport.sendto(data)

    def datagram_received(self, data: bytes, addr: tuple[Any, ...]) -> None:
        self._relay._from_target(data, self._client)

    def error_received(self, exc: Exception) -> None:
        pass


class UdpRelay:
    """**Fallback, user space, UDP only**: one lossy, slow path without root.

    Where :class:`Testbed` cannot run (no root, no namespaces), a CoAP-only
    benchmark can put one relay in front of each server: clients send to
    :attr:`address`, the relay forwards to ``target`` through ``up`` (client
    -> server) and sends the replies back through ``down``.  Each direction
    has a FIFO of ``limit_bytes``, a token bucket at ``rate_kbit`` (charging
    :data:`UDP_IPV4_OVERHEAD` per datagram like the kernel shaper), then loss,
    then ``delay_ms`` -- which, unlike the kernel path, works here, since
    holding a datagram in user space *is* a real delay.

    Results from the relay must be labelled as such: it emulates a path, not
    a host's link (two clients of one server do not share a downlink), its
    timing is only as good as the event loop's timers, it cannot carry TCP
    (ZeroMQ), and the client's and server's own kernels see a loopback link.

    ``counters()`` gives one :class:`LinkCounters` per direction: ``tx`` what
    entered the path (after the bucket, lost datagrams included), ``rx`` what
    was delivered, ``dropped`` the losses, ``queue_drops`` FIFO overflows.
    """

    def __init__(
        self,
        target: tuple[str, int],
        up: LinkSpec,
        down: LinkSpec | None = None,
        *,
        listen: tuple[str, int] = ("127.0.0.1", 0),
        seed: int | None = None,
        overhead_bytes: int = UDP_IPV4_OVERHEAD,
    ) -> None:
        if not isinstance(up, LinkSpec) or not isinstance(down, (LinkSpec, type(None))):
            raise ValueError("up and down must be LinkSpec (down=None: same as up)")
        self.target = target
        self.up_spec = up
        self.down_spec = up if down is None else down
        self._listen = listen
        self._rng = random.Random(seed)
        self._overhead = overhead_bytes
        self._transport: asyncio.DatagramTransport | None = None
        self._sessions: dict[tuple[Any, ...], _Upstream] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._up: _Direction | None = None
        self._down: _Direction | None = None

    @property
    def address(self) -> tuple[str, int]:
        """Where clients send to (host, port), once started."""
        if self._transport is None:
            raise LinkEmulationError("relay not started")
        host, port = self._transport.get_extra_info("sockname")[:2]
        return host, port

    async def start(self) -> tuple[str, int]:
        loop = asyncio.get_running_loop()
        self._up = _Direction(self.up_spec, self._rng, loop, self._overhead)
        self._down = _Direction(self.down_spec, self._rng, loop, self._overhead)
        transport, _ = await loop.create_datagram_endpoint(lambda: _Listener(self), local_addr=self._listen)
        self._transport = transport
        return self.address

    async def __aenter__(self) -> UdpRelay:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        for d in (self._up, self._down):
            if d is not None:
                d.close()
        for task in self._tasks:
            task.cancel()
        for s in self._sessions.values():
            if s.transport is not None:
                s.transport.close()
        self._sessions.clear()
        if self._transport is not None:
            self._transport.close()

    def counters(self) -> dict[str, LinkCounters]:
        """``{"up": ..., "down": ...}`` since start."""
        if self._up is None or self._down is None:
            raise LinkEmulationError("relay not started")
        return {"up": self._up.counters(), "down": self._down.counters()}

    def _from_client(self, data: bytes, client: tuple[Any, ...]) -> None:
        assert self._up is not None
        session = self._sessions.get(client)
        if session is None:
            session = self._sessions[client] = _Upstream(self, client)
            loop = asyncio.get_running_loop()
            upstream = session
            task = loop.create_task(loop.create_datagram_endpoint(lambda: upstream, remote_addr=self.target))
            self._tasks.add(task)
            task.add_done_callback(lambda t: self._session_done(t, client))
        self._up.push(data, session.send)

    def _session_done(self, task: asyncio.Task[Any], client: tuple[Any, ...]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            # Could not open a socket towards the target: forget the session
            # (its datagrams are lost, as on a broken path); the next datagram retries.
            self._sessions.pop(client, None)

    def _from_target(self, data: bytes, client: tuple[Any, ...]) -> None:
        assert self._down is not None
        transport = self._transport
        if transport is None:
            return

        def deliver(d: bytes) -> None:
            if not transport.is_closing():
                transport.sendto(d, client)

        self._down.push(data, deliver)
