"""Teammates' queries while strangers flood a robot with EDHOC and OSCORE garbage, on loopback.

    .venv/bin/python -m experiments.edhoc_flood [--strangers 1000] [--seconds 20] [--rounds 3]

One ``coapkb serve`` of the three warehouse KBs with the team's keys
(``--credentials``, as Robot1: OSCORE keyed by EDHOC), its own OS process.
Three teammates (Robot2, Robot3, the feeder), keyed before anything else,
each ask named queries one after another (``GET /kb/q/object-exists``) and
time every answer.  In ``--rounds`` rounds alternating *quiet* and
*flooded* periods of ``--seconds`` each, a strangers' process (its own OS
process, so making the flood does not slow the teammates' timing) sends
from ``--strangers`` source ports, each once a second:

* an EDHOC message_1 (a fresh ephemeral key per stranger, new message ID
  each time: the responder cannot tell it from a member's first contact);

and, spread over the same ports, ``--oscore-rate`` per second of each of:

* a member's protected request (the operator's, captured), replayed byte for byte;
* the same, cut at a random length;
* a protected request under a key id nobody has.

The teammates' latencies are pooled per kind of period (p50, p99, max, and
any request that failed); the strangers count what came back (message_2,
5.03, 4.01...).  Also the server's RSS and CPU.  Prints a table and writes
``experiments/results/edhoc_flood.csv``.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import random
import resource
import socket
import sys
import tempfile
import time
from pathlib import Path

from experiments.common import KB_FILES, ROOT, experiment_argv, free_port, rss_mib, write_csv
from experiments.server_load import cpu_seconds, object_names, start_server, stop_server

CSV_FIELDS = ["period", "round", "queries", "failed", "p50_ms", "p99_ms", "max_ms", "server_cpu_pct", "rss_mib",
              "message_1", "replies"]


# --------------------------------------------------------------------------- the strangers' process


def _message_1(mid: int, payload: bytes) -> bytes:
    from aiocoap import NON, POST, Message

    msg = Message(code=POST, uri_path=(".well-known", "edhoc"), payload=payload)
    msg.mtype, msg.mid, msg.token = NON, mid & 0xFFFF, (mid & 0xFFFF).to_bytes(2, "big")
    return msg.encode()


def _unknown_kid(mid: int, protected: bytes) -> bytes:
    from aiocoap import Message

    seen = Message.decode(protected)
    msg = Message(code=seen.code, payload=seen.payload)
    msg.opt.oscore = bytes([0x09, mid % 256]) + b"\xee" * 6  # a partial IV and a key id nobody has
    msg.mtype, msg.mid, msg.token = seen.mtype, mid & 0xFFFF, seen.token
    return msg.encode()


async def strangers(port: int, count: int, oscore_rate: int, seconds: float, protected: bytes) -> None:
    """Flood 127.0.0.1:``port`` for ``seconds``; print what came back as JSON."""
    import cbor2
    import lakers

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, count + 256)), hard))
    rng = random.Random(7)
    socks = []
    for _ in range(count):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        socks.append(s)
    firsts = [cbor2.dumps(True) + lakers.EdhocInitiator().prepare_message_1(bytes([i % 24])) for i in range(count)]
    target = ("127.0.0.1", port)
    replies: collections.Counter[str] = collections.Counter()
    sent = collections.Counter()
    loop = asyncio.get_running_loop()
    tick = 0.01
    per_tick_1 = count * tick
    per_tick_o = oscore_rate * tick
    due_1 = due_o = 0.0
    mid = 0
    start = loop.time()
    while loop.time() - start < seconds:
        due_1 += per_tick_1
        due_o += per_tick_o
        while due_1 >= 1:
            due_1 -= 1
            i = sent["message_1"] % count
            mid += 1
            socks[i].sendto(_message_1(mid, firsts[i]), target)
            sent["message_1"] += 1
        while due_o >= 1:
            due_o -= 1
            mid += 1
            s = socks[rng.randrange(count)]
            s.sendto(protected, target)
            s.sendto(protected[: rng.randrange(1, len(protected))], target)
            s.sendto(_unknown_kid(mid, protected), target)
            sent["oscore"] += 3
        for s in socks[mid % count: mid % count + 50]:  # read what came back, a slice per tick
            _drain(s, replies)
        await asyncio.sleep(tick)  # the flood's own clock
    for s in socks:
        _drain(s, replies)
        s.close()
    print(json.dumps({"sent": dict(sent), "replies": dict(replies)}), flush=True)


def _drain(s: socket.socket, replies: collections.Counter[str]) -> None:
    while True:
        try:
            data = s.recv(2048)
        except BlockingIOError:
            return
        if len(data) >= 2:
            code = data[1]
            replies[f"{code >> 5}.{code & 0x1F:02d}"] += 1


# --------------------------------------------------------------------------- the teammates


class Teammates:
    """Three members, each asking one query after another, timing each."""

    def __init__(self, team_dir: Path, uri: str, names: list[str]) -> None:
        self.team_dir = team_dir
        self.uri = uri
        self.objects = names
        self.latencies: list[float] = []
        self.failed = 0
        self.clients: list = []

    async def start(self) -> bytes:
        """Key every teammate; returns one protected request as it went on the wire."""
        from coapkb.security import load_identity
        from coapkb.security.coap import ClientSecurity
        from coapkb.transport import open_client, parse_endpoint
        from coapkb.transport.messages import Method, Request

        self.peer = parse_endpoint(self.uri)
        for name in ("Robot2", "Robot3", "feeder"):
            client = await open_client("coap", security=ClientSecurity(load_identity(self.team_dir, name)))
            await client.request(self.peer, Request(Method.GET, "/kb/q/object-exists", {"name": self.objects[0]}),
                                 timeout=10)
            self.clients.append(client)
        # The operator's request is the one replayed: a member keeps one
        # session per server, and through the relay it would be a second.
        operator = await open_client("coap", security=ClientSecurity(load_identity(self.team_dir, "operator")))
        try:
            return await self._capture(operator, Method, Request)
        finally:
            await operator.aclose()

    async def _capture(self, client, method, request_type) -> bytes:  # type: ignore[no-untyped-def]
        """One protected request of ``client``, through a relay that keeps it."""
        from coapkb.transport import Endpoint

        loop = asyncio.get_running_loop()
        kept: list[bytes] = []
        server = ("127.0.0.1", self.peer.port)

        class Relay(asyncio.DatagramProtocol):
            client: tuple[str, int] | None = None

            def connection_made(self, transport) -> None:  # type: ignore[no-untyped-def]
                self.transport = transport

            def datagram_received(self, data: bytes, addr) -> None:  # type: ignore[no-untyped-def]
                if addr[:2] == server:
                    if self.client is not None:
                        self.transport.sendto(data, self.client)
                else:
                    self.client = addr
                    kept.append(data)
                    self.transport.sendto(data, server)

        transport, _ = await loop.create_datagram_endpoint(Relay, local_addr=("127.0.0.1", 0))
        via = Endpoint("coap", "127.0.0.1", transport.get_extra_info("sockname")[1])
        try:
            await client.request(via, request_type(method.GET, "/kb/q/object-exists", {"name": "Box1"}), timeout=10)
        finally:
            transport.close()
        return next(d for d in kept if len(d) > 4 and d[4 + (d[0] & 0x0F)] >> 4 == 9)  # first option OSCORE (9)

    async def ask_for(self, seconds: float) -> tuple[list[float], int]:
        from coapkb.transport.messages import Method, Request

        latencies: list[float] = []
        failed = 0
        loop = asyncio.get_running_loop()
        end = loop.time() + seconds

        async def one(client, k: int) -> None:  # type: ignore[no-untyped-def]
            nonlocal failed
            while loop.time() < end:
                request = Request(Method.GET, "/kb/q/object-exists", {"name": self.objects[k % len(self.objects)]})
                k += 3
                started = time.perf_counter()
                try:
                    response = await client.request(self.peer, request, timeout=10)
                    ok = response.status.is_success
                except Exception:  # noqa: BLE001 -- a failed query is a figure here
                    ok = False
                if ok:
                    latencies.append(time.perf_counter() - started)
                else:
                    failed += 1

        await asyncio.gather(*(one(c, k) for k, c in enumerate(self.clients)))
        return latencies, failed

    async def aclose(self) -> None:
        for client in self.clients:
            await client.aclose()


def _pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


async def run(args: argparse.Namespace) -> list[dict[str, object]]:
    from coapkb.kb.store import KnowledgeBase
    from coapkb.security import generate_team
    from coapkb.security.keys import default_members

    names = object_names(KnowledgeBase.load(KB_FILES))
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        team = Path(tmp) / "team"
        generate_team(team, default_members(3))
        proc, uri = await start_server(sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES,
                                       "--bind", f"127.0.0.1:{free_port()}", "--credentials", str(team),
                                       "--identity", "Robot1")
        mates = Teammates(team, uri, names)
        try:
            protected = await mates.start()
            pooled: dict[str, list[float]] = {"quiet": [], "flooded": []}
            failed = {"quiet": 0, "flooded": 0}
            for r in range(args.rounds):
                for period in ("quiet", "flooded"):
                    cpu0, t0 = cpu_seconds(proc.pid), time.perf_counter()
                    flood = None
                    if period == "flooded":
                        flood = await asyncio.create_subprocess_exec(
                            *experiment_argv("edhoc_flood"), "--flood", str(mates.peer.port), "--strangers",
                            str(args.strangers), "--oscore-rate", str(args.oscore_rate), "--seconds",
                            str(args.seconds), "--protected", protected.hex(), stdout=asyncio.subprocess.PIPE,
                            cwd=ROOT)
                    latencies, lost = await mates.ask_for(args.seconds)
                    outcome = {}
                    if flood is not None:
                        out, _ = await flood.communicate()
                        outcome = json.loads(out)
                    cpu = 100 * (cpu_seconds(proc.pid) - cpu0) / (time.perf_counter() - t0)
                    pooled[period] += latencies
                    failed[period] += lost
                    row = {"period": period, "round": r + 1, "queries": len(latencies), "failed": lost,
                           "p50_ms": round(1e3 * _pct(latencies, 0.5), 2),
                           "p99_ms": round(1e3 * _pct(latencies, 0.99), 2),
                           "max_ms": round(1e3 * max(latencies, default=float("nan")), 1),
                           "server_cpu_pct": round(cpu), "rss_mib": round(rss_mib(proc.pid), 1),
                           "message_1": outcome.get("sent", {}).get("message_1", ""),
                           "replies": json.dumps(outcome.get("replies", {}), sort_keys=True) if outcome else ""}
                    rows.append(row)
                    print(f"round {r + 1} {period:>8}: {row['queries']:>6} queries, {lost} failed, "
                          f"p50 {row['p50_ms']} ms, p99 {row['p99_ms']} ms, max {row['max_ms']} ms, "
                          f"server CPU {row['server_cpu_pct']} %, RSS {row['rss_mib']} MiB"
                          + (f", strangers sent {outcome['sent']} and got {outcome['replies']}" if outcome else ""),
                          flush=True)
            for period, values in pooled.items():
                rows.append({"period": f"{period} (all rounds)", "queries": len(values), "failed": failed[period],
                             "p50_ms": round(1e3 * _pct(values, 0.5), 2), "p99_ms": round(1e3 * _pct(values, 0.99), 2),
                             "max_ms": round(1e3 * max(values, default=float("nan")), 1)})
            ratio = _pct(pooled["flooded"], 0.99) / _pct(pooled["quiet"], 0.99)
            print(f"teammates' p99 flooded / quiet: {ratio:.2f} "
                  f"({1e3 * _pct(pooled['flooded'], 0.99):.2f} / {1e3 * _pct(pooled['quiet'], 0.99):.2f} ms); "
                  f"failed {failed['flooded']} / {failed['quiet']}")
        finally:
            await mates.aclose()
            await stop_server(proc)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.edhoc_flood",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--strangers", type=int, default=1000, help="source ports, each sending a message_1 a second")
    p.add_argument("--oscore-rate", type=int, default=100,
                   help="replayed, cut and unknown-key-id protected requests per second (each)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each quiet and flooded period")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "edhoc_flood.csv")
    p.add_argument("--flood", type=int, metavar="PORT", help=argparse.SUPPRESS)
    p.add_argument("--protected", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.flood is not None:
        asyncio.run(strangers(args.flood, args.strangers, args.oscore_rate, args.seconds,
                              bytes.fromhex(args.protected)))
        return 0
    rows = asyncio.run(run(args))
    write_csv(args.out, CSV_FIELDS, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
