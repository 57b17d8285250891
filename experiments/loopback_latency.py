"""Query latency and answer sizes on loopback: one robot serving the three
warehouse KBs in its own process, one client asking the seed's four queries.

Prints a table and writes ``experiments/results/loopback_latency.csv``.

    .venv/bin/python -m experiments.loopback_latency [--requests 300] [--transports coap,zmq,zenoh]

For each transport (CoAP, ZeroMQ; Zenoh with ``--transports``), wire form (named query vs the whole SPARQL
text by FETCH/POST) and answer format (compact CBOR, SPARQL-JSON) it
measures the request and answer payload sizes and the round-trip latency
(p50, p99) of sequential requests after a warm-up.
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import statistics
import time
from pathlib import Path

from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.transport import open_client
from coapkb.transport.messages import ContentFormat, Method, Request
from experiments.common import start_loopback_kb_server

ROOT = Path(__file__).resolve().parent.parent

QUERIES = {
    "Query_1 object-exists": ("object-exists", {"name": "Gucci_bag_14"}),
    "Query_2 object-location": ("object-location", {"name": "Gucci_bag_14"}),
    "Query_3 object-features": ("object-features", {"name": "Gucci_bag_14"}),
    "Query_4 robots-for-grip": ("robots-for-grip", {"grip": "gripping"}),
}
FORMATS = {"cbor": ContentFormat.CBOR, "json": ContentFormat.JSON}


def _requests(name: str, params: dict[str, str], accept: int) -> dict[str, Request]:
    text = NAMED_QUERIES[name].render(params).encode()
    return {
        "named GET": Request(Method.GET, f"/kb/q/{name}", params, accept=accept),
        "SPARQL FETCH": Request(Method.FETCH, "/kb/sparql", payload=text, content_format=0, accept=accept),
    }


async def measure(transport: str, requests: int, warmup: int) -> list[dict]:
    proc, peer = await start_loopback_kb_server(transport)
    client = await open_client(transport)
    rows = []
    try:
        for label, (name, params) in QUERIES.items():
            for fmt, accept in FORMATS.items():
                for wire, request in _requests(name, params, accept).items():
                    for _ in range(warmup):
                        await client.request(peer, request, timeout=10)
                    sent_before = client.counters.bytes_sent
                    received_before = client.counters.bytes_received
                    latencies = []
                    for _ in range(requests):
                        started = time.perf_counter()
                        response = await client.request(peer, request, timeout=10)
                        latencies.append(time.perf_counter() - started)
                        assert response.status.is_success, response
                    latencies.sort()
                    rows.append(
                        {
                            "transport": transport,
                            "query": label,
                            "wire": wire,
                            "format": fmt,
                            "request_payload_B": len(request.payload) + sum(
                                len(k) + len(v) + 1 for k, v in request.query.items()
                            ),
                            "answer_payload_B": len(response.payload),
                            "bytes_per_exchange": round(
                                (client.counters.bytes_sent - sent_before
                                 + client.counters.bytes_received - received_before) / requests
                            ),
                            "p50_ms": round(statistics.median(latencies) * 1000, 3),
                            "p99_ms": round(latencies[int(0.99 * (len(latencies) - 1))] * 1000, 3),
                        }
                    )
    finally:
        await client.aclose()
        proc.terminate()
        await proc.wait()
    return rows


async def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.loopback_latency",
                                     description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=30)
    parser.add_argument("--out", default=str(ROOT / "experiments" / "results" / "loopback_latency.csv"))
    parser.add_argument("--transports", default="coap,zmq", help="comma-separated: coap, zmq, zenoh, zenoh+udp")
    args = parser.parse_args()
    rows = []
    for transport in args.transports.split(","):
        rows += await measure(transport, args.requests, args.warmup)
    header = list(rows[0])
    print(" | ".join(header))
    for row in rows:
        print(" | ".join(str(row[h]) for h in header))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    asyncio.run(main())
