"""How closely the kernel link emulator (coapkb.bench.linkemu) gives the
rate, delay and jitter it is set to: the figures its tests do not assert
(they depend on how loaded the machine is), measured and written down.

    sudo .venv/bin/python -m experiments.linkemu_accuracy [--repeat 3]

Each measurement runs tiny Python UDP senders and receivers inside the
testbed's namespaces (only to the 10.77.0.0/24 addresses of the namespaces it
creates).  All namespaces share CLOCK_MONOTONIC, so the sender's timestamp in
each datagram gives its one-way delay at the receiver.

* **rate**: three links (35, 128, 512 kbit/s) saturated at once for 5 s;
  goodput is the slope of the arrival times after the first packets (the
  token bucket starts full), counting Ethernet frames as tbf does;
* **delay**: links with 0, 50 and 100 ms one-way delay at once, 300
  datagrams each at 500/s: min, median, p99, max;
* **rtt**: a ping-pong between a host with 30 ms and one with 70 ms;
* **jitter**: 50 +- 20 ms, 80 datagrams 50 ms apart: spread, mean and sd
  (that of U(-20, 20) is 11.55 ms);
* **throughput**: 10,000 datagrams at ~5,000/s through a 20 ms delay:
  datagrams per second, median and p99 one-way delay.

Prints a table and writes ``experiments/results/linkemu_accuracy.csv``
(one row per measurement and repetition).  The test suite
(tests/bench/test_linkemu.py) runs the same measurements and asserts what
does not depend on the machine's load: nothing early, nothing faster than
the set rate, no reordering, exact counts.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from coapkb.bench.linkemu import LinkCounters, LinkSpec, Testbed
from experiments.common import prepare_link_emulation, write_csv

ROOT = Path(__file__).resolve().parent.parent

PY = sys.executable
PORT = 47000
UDP_IPV4_OVERHEAD = 14 + 20 + 8  # Ethernet + IPv4 + UDP headers: what tbf counts on top of the payload

# Receiver: bind, say "ready", record (arrival time, size, sequence number and
# one-way delay) of every datagram, stop after `idle` s without traffic or at
# `deadline` s, print JSON.
RECEIVER = r"""
import json, socket, struct, sys, time
port, idle, deadline = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, 33, 8 << 20)  # 33 = SO_RCVBUFFORCE: as root, no socket-buffer drops
s.bind(("0.0.0.0", port))
print("ready", flush=True)
times, sizes, seqs, owd = [], [], [], []
end = time.monotonic() + deadline
while (left := end - time.monotonic()) > 0:
    s.settimeout(min(left, idle) if times else left)
    try:
        data = s.recv(65536)
    except socket.timeout:
        break
    now = time.monotonic()
    times.append(now)
    sizes.append(len(data))
    if len(data) >= 12:
        seqs.append(int.from_bytes(data[:4], "big"))
        owd.append(now - struct.unpack("d", data[4:12])[0])
print(json.dumps({"n": len(times), "times": times, "sizes": sizes, "seqs": seqs, "owd": owd}), flush=True)
"""

# Sender: send `count` datagrams of `size` bytes (or as many as fit in
# `duration` s when count is 0) as fast as the blocking socket allows, or with
# a pause of `pace_s` after every `pace_every` datagrams.  Each carries its
# sequence number and (from 12 bytes on) its send time.  A tiny send buffer
# keeps at most ~3 datagrams queued in the shaper, so the link stays
# saturated but drains within a second after the sender stops.
SENDER = r"""
import json, socket, struct, sys, time
host, port, size, count = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
duration, pace_every, pace_s = float(sys.argv[5]), int(sys.argv[6]), float(sys.argv[7])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
payload = bytearray(size)
sent, end = 0, time.monotonic() + duration
while (count and sent < count) or (not count and time.monotonic() < end):
    payload[:4] = sent.to_bytes(4, "big")
    if size >= 12:
        payload[4:12] = struct.pack("d", time.monotonic())
    s.sendto(payload, (host, port))
    sent += 1
    if pace_every and sent % pace_every == 0:
        time.sleep(pace_s)
print(json.dumps({"sent": sent}), flush=True)
"""

#: Echo for the RTT measurement: send back every datagram to its sender.
ECHO = r"""
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("0.0.0.0", int(sys.argv[1])))
print("ready", flush=True)
while True:
    data, addr = s.recvfrom(2048)
    s.sendto(data, addr)
"""

#: Ping: `count` datagrams `gap` s apart to an echo; print each round-trip time (null = lost).
PING = r"""
import json, socket, sys, time
host, port, count, gap = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.settimeout(3.0)
rtts = []
for i in range(count):
    start = time.monotonic()
    s.sendto(i.to_bytes(4, "big"), (host, port))
    rtt = None
    while rtt is None:
        try:
            data = s.recv(64)
        except socket.timeout:
            break
        if int.from_bytes(data[:4], "big") == i:
            rtt = time.monotonic() - start
    rtts.append(rtt)
    time.sleep(gap)
print(json.dumps(rtts), flush=True)
"""


def start_receiver(tb: Testbed, host: str, *, idle: float = 1.0, deadline: float = 20.0) -> subprocess.Popen[str]:
    p = tb.popen(host, [PY, "-c", RECEIVER, str(PORT), str(idle), str(deadline)], stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    if p.stdout.readline().strip() != "ready":
        raise RuntimeError(f"the receiver on {host} did not start")
    return p


def start_sender(
    tb: Testbed, host: str, to: str, *, size: int, count: int = 0, duration: float = 0.0, pace_every: int = 0,
    pace_s: float = 0.001,
) -> subprocess.Popen[str]:
    argv = [PY, "-c", SENDER, tb.address(to), str(PORT), str(size), str(count), str(duration), str(pace_every),
            str(pace_s)]
    return tb.popen(host, argv, stdout=subprocess.PIPE, text=True)


def result(p: subprocess.Popen[str], timeout: float = 30.0) -> dict:
    out, _ = p.communicate(timeout=timeout)
    if p.returncode != 0:
        raise RuntimeError(f"exit {p.returncode}: {out}")
    return json.loads(out.strip().splitlines()[-1])


def quantile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


@dataclass(frozen=True)
class Delays:
    """One-way delays (or round trips) of one link in ms, and what arrived."""

    set_ms: float
    samples_ms: list[float]
    seqs: list[int]
    counters: LinkCounters

    def figures(self) -> dict[str, float]:
        s = self.samples_ms
        mean = sum(s) / len(s)
        sd = math.sqrt(sum((x - mean) ** 2 for x in s) / (len(s) - 1)) if len(s) > 1 else 0.0
        return {"n": len(s), "min_ms": min(s), "p50_ms": quantile(s, 0.5), "p99_ms": quantile(s, 0.99),
                "max_ms": max(s), "mean_ms": mean, "sd_ms": sd}


RATES = {35: 500, 128: 1000, 512: 1000}  # kbit/s -> UDP payload bytes


def measure_rates(duration: float = 5.0) -> dict[int, tuple[float, LinkCounters]]:
    """Goodput (kbit/s, frames counted as tbf does) of three saturated links at once, and the sender's counters."""
    links = {}
    for r in RATES:
        links[f"s{r}"] = links[f"r{r}"] = LinkSpec(rate_kbit=r)
    with Testbed(list(links), links) as tb:
        receivers = {r: start_receiver(tb, f"r{r}") for r in RATES}
        senders = {r: start_sender(tb, f"s{r}", f"r{r}", size=size, duration=duration) for r, size in RATES.items()}
        measured = {}
        for r, size in RATES.items():
            result(senders[r])
            times = result(receivers[r])["times"][3:]  # the bucket starts full: the first packets leave at once
            if len(times) < 10:
                raise RuntimeError(f"{r} kbit/s: only {len(times)} datagrams arrived")
            measured[r] = (len(times) - 1) * 8 * (size + UDP_IPV4_OVERHEAD) / (times[-1] - times[0]) / 1000
        counters = tb.counters()
    return {r: (measured[r], counters[f"s{r}"]) for r in RATES}


def measure_delays(delays: tuple[float, ...] = (0, 50, 100), n: int = 300) -> list[Delays]:
    """Links with these one-way delays at once, ``n`` datagrams each, 2 ms apart."""
    links = {}
    for d in delays:
        links[f"s{d}"] = LinkSpec(delay_ms=d)
        links[f"r{d}"] = LinkSpec()
    with Testbed(list(links), links) as tb:
        receivers = {d: start_receiver(tb, f"r{d}", idle=1.0) for d in delays}
        senders = {d: start_sender(tb, f"s{d}", f"r{d}", size=64, count=n, pace_every=1, pace_s=0.002)
                   for d in delays}
        got = {}
        for d in delays:
            result(senders[d])
            got[d] = result(receivers[d])
        counters = tb.counters()
    return [Delays(d, [x * 1000 for x in got[d]["owd"]], got[d]["seqs"], counters[f"s{d}"]) for d in delays]


def measure_rtt(a_ms: float = 30, b_ms: float = 70, count: int = 40) -> Delays:
    """Round trips between a host with ``a_ms`` and one with ``b_ms`` of one-way delay (None: lost)."""
    with Testbed(["a", "b"], {"a": LinkSpec(delay_ms=a_ms), "b": LinkSpec(delay_ms=b_ms)}) as tb:
        echo = tb.popen("b", [PY, "-c", ECHO, str(PORT)], stdout=subprocess.PIPE, text=True)
        assert echo.stdout is not None
        if echo.stdout.readline().strip() != "ready":
            raise RuntimeError("the echo did not start")
        ping = tb.run("a", [PY, "-c", PING, tb.address("b"), str(PORT), str(count), "0.01"],
                      capture_output=True, text=True, timeout=30)
        counters = tb.counters()["a"]
    rtts = json.loads(ping.stdout)
    return Delays(a_ms + b_ms, [x * 1000 if x is not None else math.nan for x in rtts], list(range(count)), counters)


def measure_jitter(d: float = 50.0, j: float = 20.0, n: int = 80) -> Delays:
    """``d`` +- ``j`` ms, ``n`` datagrams 50 ms apart (more than the spread: the
    no-reordering rule never holds one back)."""
    with Testbed(["a", "b"], {"a": LinkSpec(delay_ms=d, jitter_ms=j), "b": LinkSpec()}) as tb:
        rx = start_receiver(tb, "b", idle=1.0)
        result(start_sender(tb, "a", "b", size=64, count=n, pace_every=1, pace_s=0.05))
        got = result(rx)
        counters = tb.counters()["a"]
    return Delays(d, [x * 1000 for x in got["owd"]], got["seqs"], counters)


def measure_throughput(d: float = 20.0, n: int = 10_000) -> tuple[float, Delays]:
    """``n`` datagrams at ~5,000/s through a ``d`` ms delay: datagrams per second sent, and the delays."""
    with Testbed(["a", "b"], {"a": LinkSpec(delay_ms=d), "b": LinkSpec()}) as tb:
        rx = start_receiver(tb, "b", idle=1.0)
        t0 = time.monotonic()
        result(start_sender(tb, "a", "b", size=64, count=n, pace_every=5, pace_s=0.001))
        rate = n / (time.monotonic() - t0)
        got = result(rx)
        counters = tb.counters()["a"]
    return rate, Delays(d, [x * 1000 for x in got["owd"]], got["seqs"], counters)


CSV_FIELDS = ["measurement", "round", "set", "measured", "unit", "n", "min_ms", "p50_ms", "p99_ms", "max_ms", "mean_ms",
              "sd_ms"]


def one_round(round_no: int) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []

    def add(measurement: str, set_: str, measured: float | None = None, unit: str = "",
            delays: Delays | None = None) -> None:
        figures = {k: round(v, 3) for k, v in delays.figures().items()} if delays else {}
        rounded = round(measured, 1) if measured is not None else ""
        rows.append({"measurement": measurement, "round": round_no, "set": set_, "measured": rounded, "unit": unit,
                     **figures})
        print(f"{measurement:10} {set_:>14} {rounded:>8} {unit:12} " + " ".join(f"{k} {v}" for k, v in figures.items()),
              flush=True)

    for r, (kbit, _) in measure_rates().items():
        add("rate", f"{r} kbit/s", kbit, "kbit/s")
    for delays in measure_delays():
        add("delay", f"{delays.set_ms:g} ms", delays=delays)
    rtt = measure_rtt()
    add("rtt", f"{rtt.set_ms:g} ms", delays=Delays(rtt.set_ms, [x for x in rtt.samples_ms if not math.isnan(x)],
                                                   rtt.seqs, rtt.counters))
    add("jitter", "50 +- 20 ms", delays=measure_jitter())
    rate, delays = measure_throughput()
    add("throughput", "20 ms", rate, "datagrams/s", delays)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.linkemu_accuracy",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=3, help="rounds of every measurement")
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "linkemu_accuracy.csv")
    args = p.parse_args(argv)
    why = prepare_link_emulation()
    if why is not None:
        p.error(f"no kernel link emulation here: {why}")
    rows = [row for round_no in range(1, args.repeat + 1) for row in one_round(round_no)]
    write_csv(args.out, CSV_FIELDS, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
