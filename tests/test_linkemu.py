"""Tests of the kernel link emulator itself (coapkb.bench.linkemu).

The namespace tests need root, iproute2 and nftables.  They skip with the
reason from ``linkemu.available()`` when those are missing -- except under CI
(environment variable ``CI`` set), where a missing emulator is a failure, so
CI cannot go green without having run them.

Traffic comes from tiny Python UDP sender/receiver scripts started inside the
namespaces with ``ip netns exec``.  Everything is sent only to addresses of
the namespaces the tests create (10.77.0.0/24 inside them).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from coapkb.bench import linkemu
from coapkb.bench.linkemu import LinkCounters, LinkSpec, Testbed, UdpRelay, available, cleanup_stale

PY = sys.executable
PORT = 47000
UDP_IPV4_OVERHEAD = 14 + 20 + 8  # Ethernet + IPv4 + UDP headers: what tbf counts on top of the payload

# Receiver: bind, say "ready", record (arrival time, size) of every datagram,
# stop after `idle` s without traffic or at `deadline` s, print JSON.
RECEIVER = r"""
import json, socket, sys, time
port, idle, deadline = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, 33, 8 << 20)  # 33 = SO_RCVBUFFORCE: as root, no socket-buffer drops
s.bind(("0.0.0.0", port))
print("ready", flush=True)
times, sizes = [], []
end = time.monotonic() + deadline
while (left := end - time.monotonic()) > 0:
    s.settimeout(min(left, idle) if times else left)
    try:
        data = s.recv(65536)
    except socket.timeout:
        break
    times.append(time.monotonic())
    sizes.append(len(data))
print(json.dumps({"n": len(times), "times": times, "sizes": sizes}), flush=True)
"""

# Sender: send `count` datagrams of `size` bytes (or as many as fit in
# `duration` s when count is 0) as fast as the blocking socket allows.  A tiny
# send buffer keeps at most ~3 datagrams queued in the shaper, so the link
# stays saturated but drains within a second after the sender stops.
SENDER = r"""
import json, socket, sys, time
host, port, size, count = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
duration, pace_every = float(sys.argv[5]), int(sys.argv[6])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
payload = bytearray(size)
sent, end = 0, time.monotonic() + duration
while (count and sent < count) or (not count and time.monotonic() < end):
    payload[:4] = sent.to_bytes(4, "big")
    s.sendto(payload, (host, port))
    sent += 1
    if pace_every and sent % pace_every == 0:
        time.sleep(0.001)
print(json.dumps({"sent": sent}), flush=True)
"""


@pytest.fixture(scope="module")
def netns() -> None:
    """Skip (or, under CI, fail) when namespace emulation cannot run here."""
    ok, reason = available()
    if not ok:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the link-emulation tests, but: {reason}", pytrace=False)
        pytest.skip(reason)


def _start_receiver(tb: Testbed, host: str, *, idle: float = 1.0, deadline: float = 20.0) -> subprocess.Popen[str]:
    p = tb.popen(host, [PY, "-c", RECEIVER, str(PORT), str(idle), str(deadline)], stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    assert p.stdout.readline().strip() == "ready"
    return p


def _start_sender(
    tb: Testbed, host: str, to: str, *, size: int, count: int = 0, duration: float = 0.0, pace_every: int = 0
) -> subprocess.Popen[str]:
    argv = [PY, "-c", SENDER, tb.address(to), str(PORT), str(size), str(count), str(duration), str(pace_every)]
    return tb.popen(host, argv, stdout=subprocess.PIPE, text=True)


def _result(p: subprocess.Popen[str], timeout: float = 30.0) -> dict:
    out, _ = p.communicate(timeout=timeout)
    assert p.returncode == 0, out
    return json.loads(out.strip().splitlines()[-1])


def _our_namespaces(run_id: str) -> list[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return [line.split()[0] for line in out.splitlines() if line.startswith(run_id)]


# ---------------------------------------------------------------------------
# LinkSpec validation (no root needed)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"rate_kbit": 0}, "rate_kbit"),
        ({"rate_kbit": -5}, "rate_kbit"),
        ({"rate_kbit": float("nan")}, "rate_kbit"),
        ({"rate_kbit": "128"}, "rate_kbit"),
        ({"loss_pct": 101}, "loss_pct"),
        ({"loss_pct": -0.1}, "loss_pct"),
        ({"loss_pct": True}, "loss_pct"),
        ({"delay_ms": -1}, "delay_ms"),
        ({"queue_bytes": 100}, "queue_bytes"),
        ({"queue_bytes": 1.5e6}, "queue_bytes"),
    ],
)
def test_linkspec_rejects_bad_values_naming_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"LinkSpec.{field}"):
        LinkSpec(**kwargs)


def test_linkspec_derived_parameters() -> None:
    slow = LinkSpec(rate_kbit=35, loss_pct=12.345)
    assert slow.rate_bit_s == 35_000
    assert slow.burst_bytes == linkemu.MIN_BURST_BYTES >= linkemu.ETH_FRAME_MAX
    assert slow.limit_bytes == linkemu.DEFAULT_QUEUE_BYTES
    assert slow.loss_threshold == 1234  # of 10000: 0.01 % steps
    assert LinkSpec(rate_kbit=100_000).burst_bytes == 50_000  # 4 ms of traffic at 100 Mbit/s
    assert LinkSpec().rate_bit_s is None


def test_testbed_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="duplicate"):
        Testbed(["a", "a"])
    with pytest.raises(ValueError, match="host name"):
        Testbed(["bad name"])
    with pytest.raises(ValueError, match="missing"):
        Testbed(["a", "b"], {"a": LinkSpec()})
    with pytest.raises(ValueError, match="room for"):
        Testbed([f"h{i}" for i in range(7)], subnet="10.77.0.0/29")


def test_counters_subtract() -> None:
    a = LinkCounters(10, 2, 5, 1, 1, 3, 0)
    assert a - a == LinkCounters()
    assert LinkCounters(30, 5, 5, 1, 2, 6, 0) - a == LinkCounters(20, 3, 0, 0, 1, 3, 0)


# ---------------------------------------------------------------------------
# The emulator in namespaces
# ---------------------------------------------------------------------------


@pytest.mark.root
@pytest.mark.timeout(60)
def test_rate_is_within_15_percent(netns: None) -> None:
    """Saturate three links (35, 128, 512 kbit/s) at once; goodput at the receiver.

    The rate is the slope of the receiver's arrival times after the first few
    packets (the token bucket starts full, so the first ~2 KiB leave at veth
    speed -- a one-off burst, not the rate).  tbf counts Ethernet frames, so
    each datagram counts as payload + 42 bytes.
    """
    rates = {35: 500, 128: 1000, 512: 1000}  # kbit/s -> UDP payload bytes
    links = {}
    for r in rates:
        links[f"s{r}"] = links[f"r{r}"] = LinkSpec(rate_kbit=r)
    duration = 5.0
    with Testbed(list(links), links) as tb:
        receivers = {r: _start_receiver(tb, f"r{r}") for r in rates}
        senders = {
            r: _start_sender(tb, f"s{r}", f"r{r}", size=size, duration=duration) for r, size in rates.items()
        }
        measured = {}
        for r, size in rates.items():
            _result(senders[r])
            got = _result(receivers[r])
            skip = 3
            times = got["times"][skip:]
            assert len(times) >= 10, got["n"]
            frame_bits = 8 * (size + UDP_IPV4_OVERHEAD)
            measured[r] = (len(times) - 1) * frame_bits / (times[-1] - times[0]) / 1000
        counters = tb.counters()
    print("measured kbit/s:", {r: round(m, 2) for r, m in measured.items()})
    for r, m in measured.items():
        assert abs(m - r) <= 0.15 * r, f"{r} kbit/s link measured {m:.1f} kbit/s"
        assert counters[f"s{r}"].queue_drops == 0


@pytest.mark.root
@pytest.mark.timeout(60)
def test_loss_rate_is_statistically_sound(netns: None) -> None:
    """2000 datagrams through a 10 % loss link (set with set_link).

    Each datagram is lost independently with p = 0.10, so the received count R
    is Binomial(n=2000, q=0.90): mean n*q = 1800, sd sqrt(n*q*(1-q)) = 13.4.
    With n*q*(1-q) = 180 the normal approximation is excellent; a 4.5-sigma
    band, |R - 1800| <= 60.4 (received fraction 0.870..0.930), is exceeded by
    a correct emulator with probability 2*Phi(-4.5) ~ 7e-6 per run.  On top,
    the accounting must be exact: received + dropped-by-the-loss-rule == sent.
    """
    n, loss = 2000, 10.0
    with Testbed(["a", "b"]) as tb:  # starts unshaped and lossless
        tb.set_link("a", LinkSpec(loss_pct=loss))
        assert tb.link("a").loss_pct == loss
        before = tb.counters()
        rx = _start_receiver(tb, "b", idle=1.0)
        _result(_start_sender(tb, "a", "b", size=64, count=n, pace_every=50))
        got = _result(rx)
        c = {h: after - before[h] for h, after in tb.counters().items()}
    q = 1 - loss / 100
    sd = math.sqrt(n * q * (1 - q))
    print(f"received {got['n']}/{n} = {got['n'] / n:.4f} (expected {q:.2f} +- {4.5 * sd / n:.4f})")
    assert abs(got["n"] - n * q) <= 4.5 * sd
    assert got["n"] + c["a"].dropped == n
    assert c["a"].tx_packets == n
    assert c["b"].rx_packets == got["n"]
    assert c["a"].queue_drops == 0


@pytest.mark.root
@pytest.mark.timeout(60)
def test_counters_count_sender_bytes_including_lost(netns: None) -> None:
    """The sender's tx counters include packets the loss rule dropped; nothing else is on the link."""
    n, size = 300, 200
    frame = size + UDP_IPV4_OVERHEAD
    with Testbed(["a", "b"], LinkSpec(rate_kbit=512, loss_pct=25)) as tb:
        before = tb.counters()
        rx = _start_receiver(tb, "b", idle=1.0)
        _result(_start_sender(tb, "a", "b", size=size, count=n))
        got = _result(rx)
        c = {h: after - before[h] for h, after in tb.counters().items()}
    assert 0 < got["n"] < n
    assert c["a"] == LinkCounters(
        tx_bytes=n * frame,
        tx_packets=n,
        rx_bytes=0,
        rx_packets=0,
        dropped=n - got["n"],
        dropped_bytes=(n - got["n"]) * frame,
        queue_drops=0,
    )
    assert c["b"] == LinkCounters(rx_bytes=got["n"] * frame, rx_packets=got["n"])


@pytest.mark.root
def test_set_link_changes_the_shaper(netns: None) -> None:
    with Testbed(["a", "b"], LinkSpec(rate_kbit=128)) as tb:
        def tbf_rates() -> list[int]:
            rates = []
            for ns, dev in ((tb["a"].netns, "eth0"), (tb.bridge_netns, tb["a"].port)):
                out = subprocess.run(["tc", "-n", ns, "-j", "qdisc", "show", "dev", dev],
                                     capture_output=True, text=True, check=True).stdout
                rates += [q["options"]["rate"] for q in json.loads(out) if q["kind"] == "tbf"]
            return rates

        assert tbf_rates() == [16000, 16000]  # bytes/s, both directions
        tb.set_link("a", LinkSpec(rate_kbit=35, loss_pct=5))
        assert tbf_rates() == [4375, 4375]
        tb.set_link("a", LinkSpec())
        assert tbf_rates() == []
        with pytest.raises(KeyError):
            tb.set_link("zz", LinkSpec())


@pytest.mark.root
def test_hosts_have_lo_and_addresses(netns: None) -> None:
    names = [f"robot{i}" for i in range(1, 10)] + ["central"]
    with Testbed(names, LinkSpec(rate_kbit=35, loss_pct=5)) as tb:
        assert tb["central"].address == "10.77.0.10"
        assert tb.exec_args("robot1", ["true"])[:4] == ["ip", "netns", "exec", tb["robot1"].netns]
        out = tb.run("robot3", ["ip", "-j", "addr"], capture_output=True, text=True, check=True).stdout
        addrs = {a["ifname"]: [i["local"] for i in a["addr_info"]] for a in json.loads(out)}
        assert addrs["lo"] == ["127.0.0.1", "::1"]
        assert addrs["eth0"] == ["10.77.0.3"]
        assert all(len(h.port) <= 15 for h in tb.hosts.values())


@pytest.mark.root
def test_teardown_after_exception_kills_processes(netns: None) -> None:
    tb = Testbed(["a", "b"], LinkSpec(rate_kbit=128, loss_pct=1))
    sigterm_before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(RuntimeError, match="boom"):
        with tb:
            assert len(_our_namespaces(tb.run_id)) == 3
            sleeper = tb.popen("a", ["sleep", "60"])
            # A grandchild that nobody tracks: found through `ip netns pids`.
            tb.popen("b", ["sh", "-c", "sleep 60 & wait"])
            raise RuntimeError("boom")
    assert _our_namespaces(tb.run_id) == []
    assert sleeper.poll() is not None
    assert signal.getsignal(signal.SIGTERM) is sigterm_before
    tb.close()  # idempotent


@pytest.mark.root
async def test_async_teardown_kills_spawned(netns: None) -> None:
    async with Testbed(["a"]) as tb:
        proc = await tb.spawn("a", ["sleep", "60"])
        run_id = tb.run_id
    assert proc.returncode is not None
    assert _our_namespaces(run_id) == []


@pytest.mark.root
@pytest.mark.timeout(60)
def test_sigterm_tears_down(netns: None) -> None:
    script = (
        "import sys, time\n"
        "from coapkb.bench.linkemu import Testbed, LinkSpec\n"
        "with Testbed(['a', 'b'], LinkSpec(rate_kbit=64)) as tb:\n"
        "    tb.popen('a', ['sleep', '60'])\n"
        "    print(tb.run_id, flush=True)\n"
        "    time.sleep(60)\n"
    )
    p = subprocess.Popen([PY, "-c", script], stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    run_id = p.stdout.readline().strip()
    assert run_id and len(_our_namespaces(run_id)) == 3
    p.send_signal(signal.SIGTERM)
    assert p.wait(timeout=20) == 128 + signal.SIGTERM
    assert _our_namespaces(run_id) == []


@pytest.fixture
def fake_namespaces() -> Iterator[list[str]]:
    made: list[str] = []
    yield made
    for ns in made:
        subprocess.run(["ip", "netns", "delete", ns], capture_output=True)


@pytest.mark.root
def test_cleanup_stale_removes_dead_runs_only(netns: None, fake_namespaces: list[str]) -> None:
    with open("/proc/sys/kernel/pid_max") as f:
        dead_pid = int(f.read()) + 1  # can never be a live process
    stale = f"ckb{dead_pid}-dead-x"
    live = f"ckb{os.getpid()}-beef-y"
    for ns in (stale, live):
        subprocess.run(["ip", "netns", "add", ns], check=True)
        fake_namespaces.append(ns)
    subprocess.run(["ip", "-n", stale, "link", "add", "v0", "type", "veth", "peer", "name", "v1"], check=True)
    sleeper = subprocess.Popen(["ip", "netns", "exec", stale, "sleep", "60"])
    time.sleep(0.2)
    removed = cleanup_stale()
    assert stale in removed
    names = _our_namespaces("ckb")
    assert stale not in names and live in names
    assert sleeper.wait(timeout=5) is not None


@pytest.mark.root
def test_partial_setup_failure_leaves_nothing(netns: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """A failure half-way through setup (here: loading the nft table) removes what was built."""
    real_run = linkemu.testbed._run

    def failing_run(argv, **kwargs):  # type: ignore[no-untyped-def]
        if "nft" in argv and "-f" in argv:
            raise linkemu.LinkEmulationError("injected failure")
        return real_run(argv, **kwargs)

    monkeypatch.setattr(linkemu.testbed, "_run", failing_run)
    tb = Testbed(["a", "b", "c"], LinkSpec(rate_kbit=128))
    with pytest.raises(linkemu.LinkEmulationError, match="injected"):
        with tb:
            pass  # pragma: no cover
    assert _our_namespaces(tb.run_id) == []


@pytest.mark.root
def test_delay_needs_netem(netns: None) -> None:
    """Delay is applied with netem where the kernel has it, and refused (not faked) where not."""
    with Testbed(["a", "b"], LinkSpec(rate_kbit=128, loss_pct=1)) as tb:
        probe = subprocess.run(["tc", "-n", tb.bridge_netns, "qdisc", "add", "dev", "lo", "root", "netem"],
                               capture_output=True)
        if probe.returncode != 0:
            with pytest.raises(linkemu.LinkEmulationError, match="netem"):
                tb.set_link("a", LinkSpec(rate_kbit=35, delay_ms=20))
            assert tb.link("a") == LinkSpec(rate_kbit=128, loss_pct=1)  # refused before touching the link
            out = subprocess.run(["tc", "-n", tb["a"].netns, "-j", "qdisc", "show", "dev", "eth0"],
                                 capture_output=True, text=True, check=True).stdout
            assert [q["options"]["rate"] for q in json.loads(out) if q["kind"] == "tbf"] == [16000]
        else:  # pragma: no cover - kernels with sch_netem
            tb.set_link("a", LinkSpec(rate_kbit=35, delay_ms=20))
            out = subprocess.run(["tc", "-n", tb["a"].netns, "qdisc", "show", "dev", "eth0"],
                                 capture_output=True, text=True, check=True).stdout
            assert "netem" in out and "tbf" in out


# ---------------------------------------------------------------------------
# User-space fallback relay (no root; loopback only)
# ---------------------------------------------------------------------------


class _Echo(asyncio.DatagramProtocol):
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: tuple) -> None:  # type: ignore[type-arg]
        self.transport.sendto(data, addr)  # type: ignore[attr-defined]


class _Client(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.times: list[float] = []

    def datagram_received(self, data: bytes, addr: tuple) -> None:  # type: ignore[type-arg]
        self.times.append(time.monotonic())


async def _relay_run(
    up: LinkSpec, down: LinkSpec, n: int, size: int, seed: int | None
) -> tuple[_Client, dict[str, LinkCounters]]:
    loop = asyncio.get_running_loop()
    echo, _ = await loop.create_datagram_endpoint(_Echo, local_addr=("127.0.0.1", 0))
    try:
        async with UdpRelay(echo.get_extra_info("sockname"), up, down, seed=seed) as relay:
            client = _Client()
            ct, _ = await loop.create_datagram_endpoint(lambda: client, remote_addr=relay.address)
            for i in range(n):
                ct.sendto(i.to_bytes(4, "big") + bytes(size - 4))
                if i % 10 == 9:  # let the loop drain the loopback sockets (no socket-buffer drops)
                    await asyncio.sleep(0.001)
            # Wait until replies stop coming (0.3 s without one), at most 10 s.
            deadline = time.monotonic() + 10
            seen = -1
            while len(client.times) != seen and time.monotonic() < deadline:
                seen = len(client.times)
                await asyncio.sleep(0.3)
            ct.close()
            return client, relay.counters()
    finally:
        echo.close()


async def test_relay_rate_within_15_percent() -> None:
    """512 kbit/s on the way there; replies arrive paced by it (payload + 42 B per datagram)."""
    n, size = 60, 1000
    client, c = await _relay_run(LinkSpec(rate_kbit=512), LinkSpec(), n, size, seed=1)
    assert len(client.times) == n
    skip = 3  # the bucket starts full
    t = client.times[skip:]
    kbit = (len(t) - 1) * (size + linkemu.UDP_IPV4_OVERHEAD) * 8 / (t[-1] - t[0]) / 1000
    print(f"relay measured {kbit:.1f} kbit/s (set 512)")
    assert abs(kbit - 512) <= 0.15 * 512, kbit
    assert c["up"].tx_packets == n and c["up"].queue_drops == 0


async def test_relay_loss_and_counters() -> None:
    """20 % loss on the way there only: received ~ Binomial(1000, 0.8), 4.5-sigma band (+-57)."""
    n, size = 1000, 64
    client, c = await _relay_run(LinkSpec(loss_pct=20), LinkSpec(), n, size, seed=None)
    sd = math.sqrt(n * 0.8 * 0.2)
    print(f"relay received {len(client.times)}/{n} (expected 800 +- {4.5 * sd:.0f})")
    assert abs(len(client.times) - 0.8 * n) <= 4.5 * sd
    frame = size + linkemu.UDP_IPV4_OVERHEAD
    assert c["up"].tx_packets == n and c["up"].tx_bytes == n * frame
    assert c["up"].dropped + c["up"].rx_packets == n
    assert c["down"] == LinkCounters(
        tx_bytes=len(client.times) * frame, tx_packets=len(client.times),
        rx_bytes=len(client.times) * frame, rx_packets=len(client.times),
    )
