"""Tests of the kernel link emulator itself (coapkb.bench.linkemu).

The namespace tests need root, iproute2 and nftables.  They skip with the
reason from ``linkemu.available()`` when those are missing -- except in CI
(``support.require``), where a missing emulator is a failure, so CI cannot go
green without having run them.

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
from support import require

from coapkb.bench import linkemu
from coapkb.bench.linkemu import LinkCounters, LinkSpec, Testbed, UdpRelay, available, cleanup_stale
from experiments import linkemu_accuracy as accuracy  # the traffic scripts, shared with the benchmark's figures

PY = sys.executable
UDP_IPV4_OVERHEAD = accuracy.UDP_IPV4_OVERHEAD


@pytest.fixture(scope="module")
def netns() -> None:
    """Skip (or, under CI, fail) when namespace emulation cannot run here."""
    ok, reason = available()
    require(ok, f"no kernel link emulation: {reason}")


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
        ({"delay_ms": 10, "jitter_ms": 11}, "jitter_ms"),
        ({"jitter_ms": -1}, "jitter_ms"),
        ({"loss_model": "gilbert"}, "loss_model"),
        ({"burst_len": 0.5}, "burst_len"),
        ({"loss_pct": 60, "loss_model": "burst", "burst_len": 1}, "burst_len"),
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
    burst = LinkSpec(loss_pct=10, loss_model="burst", burst_len=4)
    assert burst.gilbert_r == 0.25
    assert burst.gilbert_p / (burst.gilbert_p + burst.gilbert_r) == pytest.approx(0.10)  # stationary loss
    assert burst.needs_delay_line and LinkSpec(delay_ms=1).needs_delay_line
    assert not LinkSpec(loss_pct=10).needs_delay_line
    assert not LinkSpec(loss_model="burst").needs_delay_line  # no loss, no delay: nothing to do


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
def test_rate_is_never_exceeded(netns: None) -> None:
    """Saturate three links (35, 128, 512 kbit/s) at once: none carries more
    than its rate (15 % for the measurement's own error), and its shaper
    queue drops nothing (the senders' tiny buffers).  How close to the rate
    each gets is the benchmark's figure (experiments/linkemu_accuracy.py): a
    loaded machine's senders and receivers fall behind."""
    measured = accuracy.measure_rates()
    print("measured kbit/s:", {r: round(m, 2) for r, (m, _) in measured.items()})
    for r, (kbit, counters) in measured.items():
        assert 0 < kbit <= 1.15 * r, f"{r} kbit/s link measured {kbit:.1f} kbit/s"
        assert counters.queue_drops == 0


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
        rx = accuracy.start_receiver(tb, "b", idle=1.0)
        accuracy.result(accuracy.start_sender(tb, "a", "b", size=64, count=n, pace_every=50))
        got = accuracy.result(rx)
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
        rx = accuracy.start_receiver(tb, "b", idle=1.0)
        accuracy.result(accuracy.start_sender(tb, "a", "b", size=size, count=n))
        got = accuracy.result(rx)
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
    real_run = linkemu.topology._run

    def failing_run(argv, **kwargs):  # type: ignore[no-untyped-def]
        if "nft" in argv and "-f" in argv:
            raise linkemu.LinkEmulationError("injected failure")
        return real_run(argv, **kwargs)

    monkeypatch.setattr(linkemu.topology, "_run", failing_run)
    tb = Testbed(["a", "b", "c"], LinkSpec(rate_kbit=128))
    with pytest.raises(linkemu.LinkEmulationError, match="injected"):
        with tb:
            pass  # pragma: no cover
    assert _our_namespaces(tb.run_id) == []


# ---------------------------------------------------------------------------
# Delay, jitter and burst loss: the user-space delay line (NFQUEUE)
# ---------------------------------------------------------------------------

@pytest.mark.root
@pytest.mark.timeout(60)
def test_one_way_delay_is_never_short(netns: None) -> None:
    """Three links at once with delay 0, 50 and 100 ms: every datagram
    arrives, in order, and none early (the delay line holds it from the
    moment it reads it; the 10 us margin is for clock reads on different CPUs
    of a VM).  How late (median, p99) is the benchmark's figure."""
    for delays in accuracy.measure_delays((0, 50, 100), n=300):
        d, owd = delays.set_ms, delays.samples_ms
        print(f"delay {d:g} ms:", {k: round(v, 3) for k, v in delays.figures().items()})
        assert delays.seqs == list(range(300))
        assert min(owd) >= d - 0.01
        assert delays.counters.queue_drops == 0 and delays.counters.dropped == 0


@pytest.mark.root
@pytest.mark.timeout(60)
def test_rtt_is_at_least_the_sum_of_both_one_way_delays(netns: None) -> None:
    """a has 30 ms, b 70 ms: every UDP ping-pong between them comes back, after at least 100 ms."""
    rtt = accuracy.measure_rtt(30, 70, count=40)
    print("RTT 30+70 ms:", {k: round(v, 3) for k, v in rtt.figures().items()})
    assert not any(math.isnan(x) for x in rtt.samples_ms)
    assert min(rtt.samples_ms) >= 100 - 0.01


@pytest.mark.root
@pytest.mark.timeout(60)
def test_jitter_spreads_delay(netns: None) -> None:
    """delay 50 +- 20 ms, datagrams 50 ms apart (more than the 40 ms spread,
    so the no-reordering rule never holds one back): none earlier than 30 ms,
    none reordered, and the spread reaches below 40 ms (each of 80 datagrams
    does with probability 1/4: all missing it, 0.75^80 = 1e-10; a loaded
    machine only makes datagrams later).  The mean and sd against U(-20, 20)
    are the benchmark's figures."""
    n, d, j = 80, 50.0, 20.0
    jitter = accuracy.measure_jitter(d, j, n)
    owd = jitter.samples_ms
    print("jitter:", {k: round(v, 3) for k, v in jitter.figures().items()}, "(uniform sd: 11.55)")
    assert jitter.seqs == list(range(n))  # FIFO: no reordering
    assert min(owd) >= d - j and min(owd) < d - j / 2


def _loss_runs(seqs: list[int], n: int) -> list[int]:
    """Lengths of the runs of consecutive sequence numbers missing from ``seqs`` (0..n-1)."""
    runs, expected = [], 0
    for s in [*seqs, n]:
        if s > expected:
            runs.append(s - expected)
        expected = s + 1
    return runs


@pytest.mark.root
@pytest.mark.timeout(300)
def test_burst_loss_rate_and_burst_length(netns: None) -> None:
    """Gilbert burst loss, 10 % in bursts of 4, over 30000 datagrams.

    The lost count of a two-state Markov chain has variance
    n*l*(1-l)*(1+lam)/(1-lam) with lam = 1-p-r (here r = 0.25, p = 0.0278,
    lam = 0.722, so 6.2 times the binomial variance): sd = 0.43 % of n, and a
    4.5-sigma band is 10 % +- 1.9 %.  Bursts are geometric with mean 4 and sd
    sqrt(1-r)/r = 3.46; about n*l*r = 750 of them give a mean burst length
    with sd 0.13, band 4 +- 0.6.  (Independent loss at 10 % would give bursts
    of 1.11.)  Accounting is exact: received + dropped == sent.
    """
    n, loss, burst = 30_000, 10.0, 4.0
    spec = LinkSpec(loss_pct=loss, loss_model="burst", burst_len=burst)
    with Testbed(["a", "b"], {"a": LinkSpec(), "b": LinkSpec()}) as tb:
        tb.set_link("a", spec)  # also covers switching a link to the delay line
        before = tb.counters()
        # The receiver waits out 5 s of silence: the delay line may stall a second on a busy machine.
        rx = accuracy.start_receiver(tb, "b", idle=5.0, deadline=120)
        accuracy.result(accuracy.start_sender(tb, "a", "b", size=64, count=n, pace_every=50), timeout=120)
        got = accuracy.result(rx, timeout=120)
        c = {h: after - before[h] for h, after in tb.counters().items()}
    lost = n - got["n"]
    l, r = loss / 100, spec.gilbert_r
    lam = 1 - spec.gilbert_p - r
    sd_lost = math.sqrt(n * l * (1 - l) * (1 + lam) / (1 - lam))
    runs = _loss_runs(got["seqs"], n)
    mean_run = sum(runs) / len(runs)
    sd_run = math.sqrt(1 - r) / r / math.sqrt(len(runs))
    print(f"burst loss: {lost / n:.4f} lost (set {l} +- {4.5 * sd_lost / n:.4f}), "
          f"{len(runs)} bursts of mean {mean_run:.3f} (set {burst} +- {4.5 * sd_run:.3f}); "
          f"{c['a'].queue_drops} dropped by the kernel's queue")
    # Accounting first: a loss the model did not draw is the delay line's
    # falling behind, not the model's statistics.
    assert c["a"].queue_drops == 0, "the delay line fell behind: the kernel's queue dropped packets"
    assert c["a"].dropped == lost and c["a"].tx_packets == n
    assert c["a"].dropped_bytes == lost * (64 + UDP_IPV4_OVERHEAD)
    assert abs(lost - n * l) <= 4.5 * sd_lost
    assert abs(mean_run - burst) <= 4.5 * sd_run


@pytest.mark.root
@pytest.mark.timeout(60)
def test_delay_line_keeps_up_with_thousands_of_packets(netns: None) -> None:
    """10000 datagrams at up to ~5000/s through a 20 ms delay: none lost,
    none reordered, none early.  The rate reached and the delay it adds are
    the benchmark's figures."""
    n, d = 10_000, 20.0
    rate, delays = accuracy.measure_throughput(d, n)
    print(f"{rate:.0f} datagrams/s through {d} ms:", {k: round(v, 3) for k, v in delays.figures().items()})
    assert delays.seqs == list(range(n))
    assert min(delays.samples_ms) >= d - 0.01
    assert delays.counters.queue_drops == 0


@pytest.mark.root
def test_set_link_moves_a_host_in_and_out_of_the_delay_line(netns: None) -> None:
    """Delay adds an NFQUEUE rule for the host (and starts the delay line once);
    back to no delay removes it; the loss rule follows the loss model."""
    with Testbed(["a", "b"], LinkSpec(rate_kbit=128, loss_pct=1)) as tb:
        def forward_rules() -> str:
            return subprocess.run(["ip", "netns", "exec", tb.bridge_netns, "iptables", "-S", "FORWARD"],
                                  capture_output=True, text=True, check=True).stdout

        def loss_chain() -> str:
            return subprocess.run(["ip", "netns", "exec", tb.bridge_netns, "nft", "list", "chain", "bridge",
                                   "coapkb", f"loss_h{tb['a'].index}"], capture_output=True, text=True).stdout

        assert "NFQUEUE" not in forward_rules() and tb._links.delay_line is None
        tb.set_link("a", LinkSpec(rate_kbit=35, delay_ms=20, loss_pct=5, loss_model="burst", burst_len=2))
        assert f"--physdev-in {tb['a'].port} -j NFQUEUE --queue-num {tb['a'].index}" in forward_rules()
        assert "numgen" not in loss_chain()  # burst loss is the delay line's
        line = tb._links.delay_line
        assert line is not None and line.pid is not None
        tb.set_link("a", LinkSpec(rate_kbit=35, loss_pct=5))
        assert "NFQUEUE" not in forward_rules() and "numgen" in loss_chain()
        pid = line.pid
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # stopped (and reaped) at teardown


@pytest.mark.root
@pytest.mark.timeout(60)
def test_delay_line_does_not_outlive_a_killed_owner(netns: None) -> None:
    """SIGKILL of the testbed's owner: the delay line sees its control pipe
    close and exits by itself; cleanup_stale then removes the namespaces."""
    script = (
        "import time\n"
        "from coapkb.bench.linkemu import Testbed, LinkSpec\n"
        "tb = Testbed(['a', 'b'], LinkSpec(delay_ms=100))\n"
        "tb.setup()\n"
        "print(tb.run_id, tb._links.delay_line.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    p = subprocess.Popen([PY, "-c", script], stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    run_id, pid = p.stdout.readline().split()
    p.kill()
    p.wait(timeout=10)
    deadline = time.monotonic() + 10
    while os.path.exists(f"/proc/{pid}") and time.monotonic() < deadline:
        with open(f"/proc/{pid}/stat") as f:
            if f.read().split(") ")[1].startswith("Z"):
                break  # exited; its parent (killed) can no longer reap it, init will
        time.sleep(0.05)
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split(") ")[1].startswith("Z")
    assert set(cleanup_stale()) >= set(_our_namespaces(run_id)) or _our_namespaces(run_id) == []
    assert _our_namespaces(run_id) == []


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
    up: LinkSpec, down: LinkSpec, n: int, size: int, seed: int | None, paced: bool = False
) -> tuple[_Client, dict[str, LinkCounters]]:
    """``paced``: send the next ten only when the last ten are through (answered or
    lost by the relay), so that no socket buffer on loopback overflows however slow
    the loop runs (the relay's counters then see every datagram sent)."""
    loop = asyncio.get_running_loop()
    echo, _ = await loop.create_datagram_endpoint(_Echo, local_addr=("127.0.0.1", 0))
    try:
        async with UdpRelay(echo.get_extra_info("sockname"), up, down, seed=seed) as relay:
            client = _Client()
            ct, _ = await loop.create_datagram_endpoint(lambda: client, remote_addr=relay.address)
            for i in range(n):
                ct.sendto(i.to_bytes(4, "big") + bytes(size - 4))
                if i % 10 == 9 and paced:
                    through = time.monotonic() + 30
                    while len(client.times) + relay.counters()["up"].dropped < i + 1 and time.monotonic() < through:
                        await asyncio.sleep(0.001)
                elif i % 10 == 9:  # let the loop drain the loopback sockets
                    await asyncio.sleep(0.001)
            # Wait for the event, not for a quiet spell (a loaded machine pauses for
            # longer): every datagram sent is accounted for on the way there, and every
            # one forwarded has come back.  At most 30 s: a socket-buffer drop would
            # never be accounted for, and the counts below then say so.
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                c = relay.counters()
                there = c["up"].dropped + c["up"].rx_packets == n
                back = c["down"].tx_packets == c["up"].rx_packets and len(client.times) == c["down"].rx_packets
                if there and back:
                    break
                await asyncio.sleep(0.05)
            ct.close()
            return client, relay.counters()
    finally:
        echo.close()


async def test_relay_rate_is_never_exceeded() -> None:
    """512 kbit/s on the way there; replies arrive paced by it (payload + 42 B
    per datagram), never faster (15 % for the measurement's own error)."""
    n, size = 60, 1000
    client, c = await _relay_run(LinkSpec(rate_kbit=512), LinkSpec(), n, size, seed=1)
    assert len(client.times) == n
    skip = 3  # the bucket starts full
    t = client.times[skip:]
    kbit = (len(t) - 1) * (size + linkemu.UDP_IPV4_OVERHEAD) * 8 / (t[-1] - t[0]) / 1000
    print(f"relay measured {kbit:.1f} kbit/s (set 512)")
    assert 0 < kbit <= 1.15 * 512, kbit
    assert c["up"].tx_packets == n and c["up"].queue_drops == 0


async def test_relay_loss_and_counters() -> None:
    """20 % loss on the way there only: received ~ Binomial(1000, 0.8), 4.5-sigma band (+-57)."""
    n, size = 1000, 64
    client, c = await _relay_run(LinkSpec(loss_pct=20), LinkSpec(), n, size, seed=None, paced=True)
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
