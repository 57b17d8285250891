"""What one exchange, a session's set-up and an idle minute cost on the wire,
per transport: bytes and packets the loopback interface of a private network
namespace carried (so nothing else on the machine is counted).

    sudo unshare -n .venv/bin/python -m experiments.wire_cost [--queries 100] [--idle 20]

One ``coapkb serve`` process holds the three warehouse KBs; this process is
its client.  For each transport it measures, from ``lo``'s transmit counters
(both directions of the exchange: on loopback every packet is sent once;
lengths include a 14-byte Ethernet header, as on the benchmark's veths):

* ``setup``: the first named query, which also opens the connection or
  session (TCP handshake, ZMTP greeting, Zenoh's Init/Open and declarations);
* ``per_query``: the mean of ``--queries`` sequential named queries after it
  (Query_2 object-location, compact CBOR answer);
* ``idle_per_min``: what the open connection costs while nobody asks
  (keep-alives), scaled to a minute.

Writes ``experiments/results/wire_cost.csv`` (``--out``).
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import subprocess
from pathlib import Path

from coapkb.transport import open_client
from coapkb.transport.messages import ContentFormat, Method, Request
from experiments.common import start_loopback_kb_server

ROOT = Path(__file__).resolve().parent.parent

NAMED = Request(Method.GET, "/kb/q/object-location", {"name": "Gucci_bag_14"}, accept=ContentFormat.CBOR)


def lo_counters() -> tuple[int, int]:
    """(bytes, packets) sent on lo so far, from ``/proc/net/dev``: it follows
    the reader's network namespace (``/sys/class/net`` shows the namespace
    sysfs was mounted in, the machine's own after ``unshare -n``)."""
    for line in Path("/proc/net/dev").read_text().splitlines():
        name, _, fields = line.partition(":")
        if name.strip() == "lo":
            values = fields.split()
            return int(values[8]), int(values[9])  # transmit bytes, packets
    raise SystemExit("no lo in /proc/net/dev")


async def measure(transport: str, queries: int, idle_s: float) -> dict[str, object]:
    proc, peer = await start_loopback_kb_server(transport)
    client = await open_client(transport)
    try:
        start = lo_counters()
        await client.request(peer, NAMED, timeout=10)
        after_setup = lo_counters()
        for _ in range(queries):
            await client.request(peer, NAMED, timeout=10)
        after_queries = lo_counters()
        await asyncio.sleep(idle_s)  # the measured idle period itself
        after_idle = lo_counters()
    finally:
        await client.aclose()
        proc.terminate()
        await proc.wait()
    scale = 60.0 / idle_s
    return {
        "transport": transport,
        "setup_B": after_setup[0] - start[0],
        "setup_pkts": after_setup[1] - start[1],
        "per_query_B": round((after_queries[0] - after_setup[0]) / queries, 1),
        "per_query_pkts": round((after_queries[1] - after_setup[1]) / queries, 2),
        "idle_per_min_B": round((after_idle[0] - after_queries[0]) * scale),
        "idle_per_min_pkts": round((after_idle[1] - after_queries[1]) * scale),
    }


async def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.wire_cost",
                                     description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--queries", type=int, default=100)
    parser.add_argument("--idle", type=float, default=20.0, metavar="SECONDS")
    parser.add_argument("--transports", default="coap,zmq,zenoh,zenoh+udp")
    parser.add_argument("--out", default=str(ROOT / "experiments" / "results" / "wire_cost.csv"))
    args = parser.parse_args()
    # A private namespace's lo starts down and carries only what this script causes.
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    rows = [await measure(t, args.queries, args.idle) for t in args.transports.split(",")]
    header = list(rows[0])
    print(" | ".join(header))
    for row in rows:
        print(" | ".join(str(row[h]) for h in header))
    with open(args.out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    asyncio.run(main())
