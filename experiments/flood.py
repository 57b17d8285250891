"""What a flood leaves behind in a robot's KB server, on loopback, in one run.

    .venv/bin/python -m experiments.flood [--storm-clients 16] [--storm-queries 150]
        [--garbage 100000] [--settle 100] [--rounds 5]

Two ``coapkb serve`` processes of the three warehouse KBs (plain CoAP, as a
robot's port is before any OSCORE check): the **stormed** one and a **twin**
that nobody floods, so the machine's own noise shows in the twin's figures
and can be divided out.

1. **fresh**: RSS of both, then the named-query rate (``GET
   /kb/q/object-exists``) with 1 and 16 client contexts, in ``--rounds``
   rounds alternating between twin and stormed server (medians kept);
2. **storm**: ``--storm-clients`` aiocoap client contexts each send
   ``--storm-queries`` FETCHes of different SPARQL texts *at once* (JSON
   answers of 1-6 blocks; aiocoap's client sends the Block2 follow-ups
   without the body), every answer checked against the KB;
3. **garbage**: ``--garbage`` datagrams from 64 source ports, half with a
   well-formed CoAP header (random type, code, token, message ID, then random
   options and payload), half random bytes; sent in batches, each batch
   followed by a named query that must be answered, so the server has read
   the batch before the next one is sent (batches of 50: a larger burst
   overflows the server's socket buffer, and the kernel, not the server,
   would drop it);
4. **settled**: after ``--settle`` seconds (the longest state lifetime
   written down in docs/flood.md is 93 s), RSS again and the rates of step 1.

Prints a table and writes ``experiments/results/flood.csv`` (one row per
phase and server, rates as requests per second).
"""

from __future__ import annotations

import argparse
import asyncio
import random
import socket
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import aiocoap

from coapkb.kb.store import KnowledgeBase
from experiments.common import KB_FILES, ROOT, free_port, rss_mib, write_csv
from experiments.server_load import bw_query, checked_fetch, drive, object_names, start_server, stop_server

CSV_FIELDS = ["phase", "server", "rss_mib", "rate_1", "rate_16", "answered", "wrong", "failed", "datagrams",
              "seconds"]
#: Request codes a stranger might use, and some that are not requests at all.
CODES = (1, 2, 3, 4, 5, 6, 7, 0, 31, 65, 69, 132, 160, 255)


@dataclass
class Server:
    name: str
    proc: asyncio.subprocess.Process
    uri: str

    @property
    def port(self) -> int:
        return int(self.uri.rsplit(":", 1)[1])

    def rss(self) -> float:
        return rss_mib(self.proc.pid)


async def rates(servers: list[Server], names: list[str], rounds: int, seconds: float) -> dict[str, dict[int, float]]:
    """Median named-query rate per server and client count, rounds alternating between servers."""
    seen: dict[str, dict[int, list[float]]] = {s.name: {1: [], 16: []} for s in servers}
    for clients in (1, 16):
        for _ in range(rounds):
            for server in servers:
                uris = [f"{server.uri}/kb/q/object-exists?name={n}" for n in names]
                t = await drive(server.proc.pid, uris, clients, seconds, 0.3)
                seen[server.name][clients].append(t.req_s)
    return {name: {c: statistics.median(v) for c, v in by.items()} for name, by in seen.items()}


@dataclass
class StormOutcome:
    answered: int = 0
    wrong: int = 0
    failed: int = 0
    seconds: float = 0.0


async def storm(uri: str, kb: KnowledgeBase, clients: int, queries: int) -> StormOutcome:
    """``clients`` contexts, each with ``queries`` block-wise FETCHes in flight at once."""
    outcome = StormOutcome()
    expected: dict[str, object] = {}

    async def one(ctx: aiocoap.Context, text: str) -> None:
        fate, _ = await checked_fetch(ctx, uri, text, kb, expected, timeout=120)
        if fate == "refused":
            fate = "failed"
        setattr(outcome, fate, getattr(outcome, fate) + 1)

    async def user(n: int) -> None:
        ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
        try:
            await asyncio.gather(*(one(ctx, bw_query(n * queries + k)) for k in range(queries)))
        finally:
            await ctx.shutdown()

    started = time.perf_counter()
    await asyncio.gather(*(user(n) for n in range(clients)))
    outcome.seconds = time.perf_counter() - started
    return outcome


def garbage_datagram(rng: random.Random) -> bytes:
    """Half of them a well-formed CoAP header and random rest, half random bytes."""
    if rng.random() < 0.5:
        return rng.randbytes(rng.randint(1, 300))
    tkl = rng.randint(0, 8)
    head = bytes([0x40 | rng.randint(0, 3) << 4 | tkl, rng.choice(CODES)]) + rng.randbytes(2 + tkl)
    return head + rng.randbytes(rng.randint(0, 200))


async def garbage(server: Server, count: int, seed: int, batch: int = 50) -> float:
    """``count`` garbage datagrams from 64 source ports, a batch at a time,
    each batch closed by a named query the server must answer."""
    rng = random.Random(seed)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(64)]
    for s in socks:
        s.setblocking(False)
    ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
    target = ("127.0.0.1", server.port)
    started = time.perf_counter()
    try:
        for first in range(0, count, batch):
            for i in range(first, min(first + batch, count)):
                try:
                    socks[i % len(socks)].sendto(garbage_datagram(rng), target)
                except BlockingIOError:
                    pass
            for s in socks:  # what the server answered (RSTs, 4.xx): read and dropped
                while True:
                    try:
                        s.recv(2048)
                    except BlockingIOError:
                        break
            probe = aiocoap.Message(code=aiocoap.GET, uri=f"{server.uri}/kb/q/object-exists?name=Box1")
            await asyncio.wait_for(ctx.request(probe).response, 30)
    finally:
        await ctx.shutdown()
        for s in socks:
            s.close()
    return time.perf_counter() - started


async def run(args: argparse.Namespace) -> list[dict[str, object]]:
    kb = KnowledgeBase.load(KB_FILES)
    names = object_names(kb)
    servers = []
    for name in ("twin", "stormed"):
        proc, uri = await start_server(sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES,
                                       "--bind", f"127.0.0.1:{free_port()}")
        servers.append(Server(name, proc, uri))
    twin, stormed = servers
    rows: list[dict[str, object]] = []

    def record(phase: str, measured: dict[str, dict[int, float]] | None = None, **extra: object) -> None:
        for s in servers:
            row: dict[str, object] = {"phase": phase, "server": s.name, "rss_mib": round(s.rss(), 1)}
            if measured:
                row.update(rate_1=round(measured[s.name][1]), rate_16=round(measured[s.name][16]))
            if s is stormed:
                row.update(extra)
            rows.append(row)
            print(f"{phase:>8} {s.name:>8}: RSS {row['rss_mib']:6.1f} MiB"
                  + (f"  rate {row['rate_1']:>5}/s (1 client) {row['rate_16']:>5}/s (16)" if measured else "")
                  + (f"  {extra}" if extra and s is stormed else ""), flush=True)

    try:
        record("fresh", await rates(servers, names, args.rounds, args.seconds))
        out = await storm(stormed.uri, kb, args.storm_clients, args.storm_queries)
        record("storm", answered=out.answered, wrong=out.wrong, failed=out.failed, seconds=round(out.seconds, 1))
        took = await garbage(stormed, args.garbage, args.seed)
        record("garbage", datagrams=args.garbage, seconds=round(took, 1))
        await asyncio.sleep(args.settle)  # state ages out by the clock; nothing to await
        record("settled", await rates(servers, names, args.rounds, args.seconds))
    finally:
        for s in servers:
            await stop_server(s.proc)
    fresh = {r["server"]: r for r in rows if r["phase"] == "fresh"}
    settled = {r["server"]: r for r in rows if r["phase"] == "settled"}
    grew = settled["stormed"]["rss_mib"] - fresh["stormed"]["rss_mib"]  # type: ignore[operator]
    print(f"stormed server's RSS grew {grew:+.1f} MiB (twin {settled['twin']['rss_mib'] - fresh['twin']['rss_mib']:+.1f})")
    for c in (1, 16):
        own = settled["stormed"][f"rate_{c}"] / fresh["stormed"][f"rate_{c}"]  # type: ignore[operator]
        twin_drift = settled["twin"][f"rate_{c}"] / fresh["twin"][f"rate_{c}"]  # type: ignore[operator]
        print(f"{c:>2} client(s): settled / fresh rate {own:.2f} (twin {twin_drift:.2f}, "
              f"stormed against twin {own / twin_drift:.2f})")
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.flood",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--storm-clients", type=int, default=16)
    p.add_argument("--storm-queries", type=int, default=150, help="FETCHes in flight per storm client")
    p.add_argument("--garbage", type=int, default=100_000, help="garbage datagrams after the storm")
    p.add_argument("--settle", type=float, default=100.0, help="seconds between the flood and the last figures")
    p.add_argument("--rounds", type=int, default=5, help="alternating rate rounds per client count")
    p.add_argument("--seconds", type=float, default=2.0, help="measured seconds per rate round")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "flood.csv")
    args = p.parse_args(argv)
    rows = asyncio.run(run(args))
    write_csv(args.out, CSV_FIELDS, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
