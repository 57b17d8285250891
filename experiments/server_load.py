"""Server load on loopback: coapkb's robot server against a bare aiocoap server,
side by side in one run, plus block-wise FETCHes from many aiocoap clients and
the load time of a large KB.

    .venv/bin/python -m experiments.server_load [--seconds 3] [--kb-dir /tmp/kb100k]

Three servers' worth of work, each server in its own OS process:

* **bare**: aiocoap alone, one static 150-byte resource ``/static`` (GET);
* **coapkb**: ``coapkb serve`` with the three KBs in ``ontologies/``, named
  query ``GET /kb/q/object-exists?name=...`` (names cycled over the KB's
  objects, so the answer cache sees misses as well as hits).

The load comes from ONE driver process (this one) holding N aiocoap client
contexts (N client endpoints), each sending CON requests one after another
for ``--seconds`` after a warm-up, in ``--rounds`` rounds alternating
between the two servers (each one's median round is kept).  The driver can be the bottleneck on a small
machine, so each row also gives the server's own CPU time per request (from
/proc), which does not depend on the driver.

Then ``--bw-clients`` contexts x ``--bw-queries`` FETCHes of different SPARQL
texts (JSON answers of 1-6 blocks) from a plain ``aiocoap`` client, which
sends its Block2 follow-ups without the body: every answer is compared with
the KB's own result (loaded in this process), and counted answered / refused
(4.08) / wrong / failed.

With ``--kb-dir`` (e.g. the output of ``tools/gen_warehouse.py --products
100000 --out /tmp/kb100k``), a fresh process times ``KnowledgeBase.load`` of
its ``*.owl`` files and reports its peak RSS.

Prints a table and writes ``experiments/results/server_load.csv``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import aiocoap
import aiocoap.resource

from coapkb.kb.store import KnowledgeBase
from coapkb.wire import codec
from experiments.common import experiment_argv, free_port, write_csv

ROOT = Path(__file__).resolve().parent.parent

KB_FILES = [str(ROOT / "ontologies" / f"{n}.owl") for n in ("Object", "Location", "Capability")]
OBJ = "http://www.tcs.org/2018/Object#"
STATIC_PAYLOAD = bytes(range(150))
JSON = 50
CBOR = 60
CSV_FIELDS = ["section", "server", "clients", "requests", "seconds", "req_s", "server_cpu_us_per_req",
              "ratio", "answered", "refused", "wrong", "failed", "load_s", "peak_rss_mb"]


# --------------------------------------------------------------------------- child processes


class _Static(aiocoap.resource.Resource):
    async def render_get(self, request: aiocoap.Message) -> aiocoap.Message:
        return aiocoap.Message(payload=STATIC_PAYLOAD, content_format=42)


async def serve_bare(port: int) -> None:
    """The baseline: aiocoap with one static resource, until killed."""
    site = aiocoap.resource.Site()
    site.add_resource(["static"], _Static())
    await aiocoap.Context.create_server_context(site, bind=("127.0.0.1", port), transports=["udp6"])
    print(f"serving static on coap://127.0.0.1:{port}", flush=True)
    await asyncio.Event().wait()


def time_kb_load(kb_dir: Path) -> None:
    """Load every ``*.owl`` in ``kb_dir``; print seconds, triples and peak RSS as JSON."""
    paths = sorted(kb_dir.glob("*.owl"))
    started = time.perf_counter()
    kb = KnowledgeBase.load(paths)
    seconds = time.perf_counter() - started
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(json.dumps({"load_s": seconds, "triples": kb.triple_count, "peak_rss_mb": peak_kib / 1024,
                      "backend": kb.backend}))


# --------------------------------------------------------------------------- driver


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def start_server(*argv: str) -> tuple[asyncio.subprocess.Process, str]:
    proc = await asyncio.create_subprocess_exec(*argv, stdout=asyncio.subprocess.PIPE, cwd=ROOT)
    assert proc.stdout is not None
    line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
    if not line.startswith("serving"):
        raise SystemExit(f"server did not start: {line!r}")
    return proc, line.rsplit(" on ", 1)[1].strip()


async def stop_server(proc: asyncio.subprocess.Process) -> None:
    proc.terminate()
    await proc.wait()


@dataclass
class Throughput:
    requests: int
    seconds: float
    server_cpu_s: float
    failed: int

    @property
    def req_s(self) -> float:
        return self.requests / self.seconds

    @property
    def cpu_us_per_req(self) -> float:
        return 1e6 * self.server_cpu_s / max(self.requests, 1)


async def drive(pid: int, uris: list[str], clients: int, seconds: float, warmup: float) -> Throughput:
    """``clients`` contexts, each sending the next of ``uris`` (cycled) as soon
    as the last one was answered; counted between warm-up and warm-up+seconds."""
    contexts = [await aiocoap.Context.create_client_context(transports=["udp6"]) for _ in range(clients)]
    counted = [0] * clients
    failed = [0] * clients
    loop = asyncio.get_running_loop()
    start = loop.time() + warmup
    end = start + seconds
    marks: dict[str, float] = {}

    async def user(n: int) -> None:
        ctx = contexts[n]
        i = n
        while (now := loop.time()) < end:
            msg = aiocoap.Message(code=aiocoap.GET, uri=uris[i % len(uris)], accept=CBOR)
            i += clients
            answer = await ctx.request(msg).response
            if now >= start:
                if answer.code.is_successful():
                    counted[n] += 1
                else:
                    failed[n] += 1

    async def cpu_marks() -> None:
        await asyncio.sleep(warmup)  # a time mark, not a wait for an event
        marks["start"] = cpu_seconds(pid)
        await asyncio.sleep(seconds)
        marks["end"] = cpu_seconds(pid)

    try:
        await asyncio.gather(cpu_marks(), *(user(n) for n in range(clients)))
    finally:
        for ctx in contexts:
            await ctx.shutdown()
    return Throughput(sum(counted), seconds, marks["end"] - marks["start"], sum(failed))


def object_names(kb: KnowledgeBase) -> list[str]:
    result = kb.query(f'SELECT DISTINCT ?o WHERE {{ ?o a ?c FILTER(STRSTARTS(STR(?o), "{OBJ}")) }}',
                      row_limit=100_000)
    return sorted(str(row["o"]).removeprefix(OBJ) for row in result.as_dicts())


def bw_query(i: int) -> str:
    """A different SPARQL text for each ``i``, its JSON answer 1 to 6 blocks long."""
    return f"SELECT ?s ?p ?o WHERE {{ ?s ?p ?o }} OFFSET {i * 13 % 26000} LIMIT {2 + i % 5 * 5}"


@dataclass
class BlockwiseOutcome:
    answered: int = 0
    refused: int = 0
    wrong: int = 0
    failed: int = 0
    blocks: list[int] = field(default_factory=list)
    seconds: float = 0.0


async def checked_fetch(ctx: aiocoap.Context, uri: str, text: str, kb: KnowledgeBase,
                        expected: dict[str, object], timeout: float = 60) -> tuple[str, int]:
    """One plain aiocoap FETCH of ``text`` (JSON answer), checked against the
    KB: ("answered" | "wrong" | "refused" (4.08) | "failed", answer bytes)."""
    msg = aiocoap.Message(code=aiocoap.FETCH, uri=f"{uri}/kb/sparql", payload=text.encode(),
                          content_format=0, accept=JSON)
    try:
        answer = await asyncio.wait_for(ctx.request(msg).response, timeout)
    except (aiocoap.error.Error, TimeoutError):
        return "failed", 0
    if answer.code == aiocoap.REQUEST_ENTITY_INCOMPLETE:
        return "refused", 0
    if answer.code != aiocoap.CONTENT:
        return "failed", 0
    if text not in expected:
        expected[text] = kb.query(text)
    right = codec.decode_json(answer.payload) == expected[text]
    return ("answered" if right else "wrong"), len(answer.payload)


async def blockwise(uri: str, kb: KnowledgeBase, clients: int, queries: int) -> BlockwiseOutcome:
    """Plain aiocoap FETCHes (follow-ups without the body), each answer checked."""
    outcome = BlockwiseOutcome()
    expected: dict[str, object] = {}

    async def user(n: int) -> None:
        ctx = await aiocoap.Context.create_client_context(transports=["udp6"])
        try:
            for k in range(queries):
                fate, size = await checked_fetch(ctx, uri, bw_query(n * queries + k), kb, expected)
                setattr(outcome, fate, getattr(outcome, fate) + 1)
                if size:
                    outcome.blocks.append(-(-size // 1024))
        finally:
            await ctx.shutdown()

    started = time.perf_counter()
    await asyncio.gather(*(user(n) for n in range(clients)))
    outcome.seconds = time.perf_counter() - started
    return outcome


async def run(args: argparse.Namespace) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    kb = KnowledgeBase.load(KB_FILES)
    names = object_names(kb)
    bare, bare_uri = await start_server(*experiment_argv("server_load", "--serve-bare", str(free_port())))
    robot, robot_uri = await start_server(sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES,
                                          "--bind", f"127.0.0.1:{free_port()}")
    try:
        for clients in args.clients:
            # alternate the two servers round by round and keep each one's
            # median round: other load on the machine hits both alike
            bases, ourses = [], []
            for _ in range(args.rounds):
                bases.append(await drive(bare.pid, [f"{bare_uri}/static"], clients, args.seconds, args.warmup))
                ourses.append(await drive(robot.pid, [f"{robot_uri}/kb/q/object-exists?name={n}" for n in names],
                                          clients, args.seconds, args.warmup))
            base = sorted(bases, key=lambda t: t.req_s)[len(bases) // 2]
            ours = sorted(ourses, key=lambda t: t.req_s)[len(ourses) // 2]
            ratio = ours.req_s / base.req_s
            for server, t in (("bare aiocoap GET /static", base), ("coapkb GET /kb/q/object-exists", ours)):
                rows.append({"section": "throughput", "server": server, "clients": clients, "requests": t.requests,
                             "seconds": t.seconds, "req_s": round(t.req_s, 1),
                             "server_cpu_us_per_req": round(t.cpu_us_per_req), "failed": t.failed,
                             "ratio": round(ratio, 3) if t is ours else ""})
            print(f"{clients:>3} clients: bare {base.req_s:7.0f} req/s ({base.cpu_us_per_req:4.0f} us CPU/req)  "
                  f"coapkb {ours.req_s:7.0f} req/s ({ours.cpu_us_per_req:4.0f} us CPU/req)  ratio {ratio:.2f}"
                  f"  failed {base.failed}/{ours.failed}", flush=True)
        bw = await blockwise(robot_uri, kb, args.bw_clients, args.bw_queries)
        rows.append({"section": "blockwise", "server": "coapkb FETCH /kb/sparql (aiocoap client)",
                     "clients": args.bw_clients, "requests": args.bw_clients * args.bw_queries,
                     "seconds": round(bw.seconds, 2), "answered": bw.answered, "refused": bw.refused,
                     "wrong": bw.wrong, "failed": bw.failed})
        sizes = {b: bw.blocks.count(b) for b in sorted(set(bw.blocks))}
        print(f"block-wise FETCH, {args.bw_clients} clients x {args.bw_queries}: answered {bw.answered}, "
              f"refused {bw.refused}, wrong {bw.wrong}, failed {bw.failed} in {bw.seconds:.1f} s; "
              f"answers by blocks {sizes}", flush=True)
    finally:
        await stop_server(bare)
        await stop_server(robot)
    if args.kb_dir is not None:
        proc = await asyncio.create_subprocess_exec(*experiment_argv("server_load", "--load-kb", str(args.kb_dir)),
                                                    stdout=asyncio.subprocess.PIPE, cwd=ROOT)
        out, _ = await proc.communicate()
        loaded = json.loads(out)
        rows.append({"section": "kb-load", "server": f"KnowledgeBase.load {args.kb_dir} ({loaded['backend']})",
                     "requests": loaded["triples"], "load_s": round(loaded["load_s"], 2),
                     "peak_rss_mb": round(loaded["peak_rss_mb"])})
        print(f"KB load {args.kb_dir}: {loaded['triples']} triples in {loaded['load_s']:.2f} s, "
              f"peak RSS {loaded['peak_rss_mb']:.0f} MB", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.server_load",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=3.0, help="measured seconds per throughput run")
    p.add_argument("--warmup", type=float, default=0.5)
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds per client count (median kept)")
    p.add_argument("--clients", type=lambda s: [int(c) for c in s.split(",")], default=[1, 16])
    p.add_argument("--bw-clients", type=int, default=16)
    p.add_argument("--bw-queries", type=int, default=150)
    p.add_argument("--kb-dir", type=Path, help="also time loading the *.owl files of this directory")
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "server_load.csv")
    p.add_argument("--serve-bare", type=int, metavar="PORT", help=argparse.SUPPRESS)
    p.add_argument("--load-kb", type=Path, metavar="DIR", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.serve_bare is not None:
        asyncio.run(serve_bare(args.serve_bare))
        return 0
    if args.load_kb is not None:
        time_kb_load(args.load_kb)
        return 0
    rows = asyncio.run(run(args))
    write_csv(args.out, CSV_FIELDS, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
