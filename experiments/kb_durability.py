"""What keeping the writable KB on disk costs and what it buys: a local
write's latency, every acknowledged write back after every holder of a
module was killed, and how soon a robot holding many written triples
serves again.

    .venv/bin/python -m experiments.kb_durability latency [--writes 1000]
    .venv/bin/python -m experiments.kb_durability restart [--writes 100] [--rounds 3]
    .venv/bin/python -m experiments.kb_durability big [--triples 100000]
    .venv/bin/python -m experiments.kb_durability lives [--restarts 50] [--writes 4]

* **latency**: ``--writes`` one-triple INSERT DATA writes to a Location
  module in this process, each timed until it returns (for a write with a
  data folder: on disk, fsynced).  Four ways: in memory only (as without
  ``data_dir``); the journal (``coapkb.kb.durable``); and, for the choice
  of format, pyoxigraph's on-disk store taking the same triple, flushed
  (``Store.flush``) so that it is on disk when the write returns, and
  unflushed (RocksDB's write-ahead log, not fsynced: lost on a power cut).
* **restart**: a writable team of three robot processes on loopback, each
  with its data folder.  ``--writes`` INSERT DATA writes, each to a random
  holder of the Location module (Robot1, Robot3) and each answered 2.04;
  then both holders are killed with SIGKILL at once and started again on
  their folders.  How many of the writes each holder has once it serves,
  the time from a holder's start to its first answer holding them, and
  to its ready line (which waits to hear from its teammates).
* **big**: a data folder holding ``--triples`` written triples (writes of
  1,000), as a snapshot and as a journal alone; ``coapkb serve --writable
  --data-dir`` started on it: the time from the start to the serving line
  and to an answer counting them, against the same start without a folder.

* **lives**: the same team kept in memory (no data folders).  Robot3, a
  holder of Location, is killed with SIGKILL and started again
  ``--restarts`` times; each life takes ``--writes`` INSERT DATA writes,
  each answered 2.04.  After each life: the writers Robot1's Location
  context names and the bytes of an anti-entropy question carrying it
  (what every round sends), and how many of the writes acknowledged so
  far each holder shows at the end.

Prints tables and writes ``experiments/results/kb_durability_*.csv``.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import random
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

from experiments.common import ROOT, free_port, write_csv

LOCATION = ROOT / "ontologies" / "Location.owl"
LOC = "http://www.tcs.org/2018/Location#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
RESULTS = ROOT / "experiments" / "results"
#: Location's holders in a cluster of three (the harness's placement).
HOLDERS = ("Robot1", "Robot3")


def insert(label: str) -> str:
    return PREFIX + f'INSERT DATA {{ loc:{label} loc:written "{label}" }}'


def _pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _scratch() -> Path:
    """A folder on the same disk as the checkout (``/tmp`` may be memory)."""
    return Path(tempfile.mkdtemp(prefix="kb-durability-", dir=ROOT.parent))


# ============================================================================ latency


def latency(args: argparse.Namespace) -> None:
    import pyoxigraph as ox

    from coapkb.kb.durable import open_live
    from coapkb.kb.live import wall_ms
    from coapkb.kb.store import KnowledgeBase

    base = KnowledgeBase.load([LOCATION])
    scratch = _scratch()
    rows = []
    try:
        def timed(name: str, write) -> None:  # type: ignore[no-untyped-def]
            for i in range(20):  # warm up: the first write copies the files' graph
                write(f"warm{i}")
            took = []
            for i in range(args.writes):
                started = time.perf_counter()
                write(f"W{i}")
                took.append((time.perf_counter() - started) * 1000)
            rows.append({"how": name, "writes": args.writes, "p50_ms": round(_pct(took, 0.5), 3),
                         "p99_ms": round(_pct(took, 0.99), 3), "max_ms": round(max(took), 3)})
            print(rows[-1], flush=True)

        memory, _ = open_live(base, "Robot1", 1, None, wall_ms=wall_ms)
        timed("memory only", lambda label: memory.update(insert(label)))
        kept, keeper = open_live(base, "Robot1", 1, scratch / "journal", wall_ms=wall_ms)
        assert keeper is not None
        timed("journal (fsync)", lambda label: kept.update(insert(label)))
        keeper.close()

        store = ox.Store(str(scratch / "oxigraph"))

        def quad(label: str) -> ox.Quad:
            return ox.Quad(ox.NamedNode(LOC + label), ox.NamedNode(LOC + "written"), ox.Literal(label),
                           ox.DefaultGraph())

        def flushed(label: str) -> None:
            store.add(quad(label))
            store.flush()

        timed("oxigraph store, flushed", flushed)
        timed("oxigraph store, not flushed", lambda label: store.add(quad(label)))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    write_csv(RESULTS / "kb_durability_latency.csv", list(rows[0]), rows)


# ============================================================================ restart


def _team(scratch: Path, *, data_dirs: bool):  # type: ignore[no-untyped-def]
    """A writable team of three robots on loopback, configured in
    ``scratch`` (each with its data folder there if ``data_dirs``): their
    endpoints, and the :class:`Robots` to start them."""
    from coapkb.config import dump_config
    from coapkb.harness.team import TeamSpec, robot_configs
    from coapkb.transport.base import Endpoint

    spec = TeamSpec(robots=3, kb_writable=True)
    endpoints = {r: Endpoint("coap", "127.0.0.1", free_port()) for r in spec.robot_ids}
    configs = {}
    for robot, config in robot_configs(spec, endpoints).items():
        if data_dirs:
            config = dataclasses.replace(config, data_dir=scratch / "data" / robot)
        configs[robot] = scratch / f"{robot}.toml"
        configs[robot].write_text(dump_config(config), encoding="utf-8")
    return endpoints, Robots(configs)


class Robots:
    """Robot processes (``coapkb agent``) of one team, by name."""

    def __init__(self, configs: dict[str, Path]) -> None:
        self.configs = configs
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.drains: list[asyncio.Task[None]] = []

    async def start(self, robot: str) -> float:
        """Start ``robot``; the seconds until its ready line."""
        started = time.monotonic()
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "coapkb", "agent", "--config", str(self.configs[robot]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
        )
        assert proc.stdout is not None and proc.stderr is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 120)).decode()
        if not line.startswith(f"robot {robot} ready"):
            proc.kill()
            raise RuntimeError(f"{robot} did not start: {line} {(await proc.stderr.read()).decode()[-2000:]}")
        self.procs[robot] = proc
        self.drains.append(asyncio.ensure_future(proc.stderr.read()))
        return time.monotonic() - started

    async def kill(self, robots: tuple[str, ...]) -> None:
        for robot in robots:
            self.procs[robot].send_signal(signal.SIGKILL)
        for robot in robots:
            await self.procs.pop(robot).wait()

    async def aclose(self) -> None:
        from experiments.common import stop_processes

        await stop_processes(self.procs.values())
        for drain in self.drains:
            drain.cancel()


async def _written(kb, endpoint) -> set[str]:  # type: ignore[no-untyped-def]
    from coapkb.kb.results import expect_select

    result = await kb.sparql(endpoint, PREFIX + "SELECT ?v WHERE { ?s loc:written ?v }", timeout=2)
    return {str(row["v"]) for row in expect_select(result, "written").as_dicts()}


async def _first_answer(kb, endpoint, started: float, expected: set[str]) -> tuple[float, set[str]]:  # type: ignore[no-untyped-def]
    """Seconds from ``started`` until ``endpoint`` answers with every label
    of ``expected`` (or 60 s: then what it last had)."""
    from coapkb.transport.base import TransportError

    held: set[str] = set()
    while time.monotonic() - started < 60:
        try:
            held = await _written(kb, endpoint)
        except TransportError:
            await asyncio.sleep(0.05)
            continue
        if expected <= held:
            break
        await asyncio.sleep(0.05)
    return time.monotonic() - started, held


async def restart(args: argparse.Namespace) -> None:
    from coapkb.kb.client import KBClient
    from coapkb.transport import open_client

    rows = []
    for round_no in range(1, args.rounds + 1):
        scratch = _scratch()
        endpoints, robots = _team(scratch, data_dirs=True)
        client = await open_client("coap")
        kb = KBClient(client, timeout=20)
        try:
            await asyncio.gather(*(robots.start(r) for r in endpoints))
            rng = random.Random(round_no)
            labels = [f"R{round_no}W{i}" for i in range(args.writes)]
            acked = []
            for label in labels:
                await kb.update(endpoints[rng.choice(HOLDERS)], insert(label))  # raises unless 2.04
                acked.append(label)
            await robots.kill(HOLDERS)
            started = time.monotonic()
            # Asked from the start on, while they start and catch up.
            ready_s, *answers = await asyncio.gather(
                asyncio.gather(*(robots.start(r) for r in HOLDERS)),
                *(_first_answer(kb, endpoints[r], started, set(acked)) for r in HOLDERS))
            for robot, ready, (serving_s, held) in zip(HOLDERS, ready_s, answers):
                rows.append({"round": round_no, "robot": robot, "acknowledged": len(acked),
                             "present": len(set(acked) & held), "serves_s": round(serving_s, 2),
                             "ready_s": round(ready, 2)})
                print(rows[-1], flush=True)
        finally:
            await client.aclose()
            await robots.aclose()
            shutil.rmtree(scratch, ignore_errors=True)
    write_csv(RESULTS / "kb_durability_restart.csv", list(rows[0]), rows)


# ============================================================================ lives


async def _context_of(client, endpoint, module: str):  # type: ignore[no-untyped-def]
    """``endpoint``'s causal context of ``module``, from its answer to a
    holder's question."""
    from coapkb.model.deltas import CausalContext
    from coapkb.transport.messages import ContentFormat, Method, Request, Status
    from coapkb.wire.sync import SyncMessage, decode_sync, encode_sync

    request = Request(Method.POST, "/kb/sync", payload=encode_sync(SyncMessage(module, CausalContext())),
                      content_format=ContentFormat.CBOR, accept=ContentFormat.CBOR)
    response = await client.request(endpoint, request, timeout=10)
    if response.status != Status.CHANGED:
        raise RuntimeError(f"{endpoint}: {response.status.dotted} {response.text()}")
    return decode_sync(response.payload).context


async def lives(args: argparse.Namespace) -> None:
    from coapkb.kb.client import KBClient
    from coapkb.transport import open_client
    from coapkb.wire.sync import SyncMessage, encode_sync

    scratch = _scratch()
    endpoints, robots = _team(scratch, data_dirs=False)
    client = await open_client("coap")
    kb = KBClient(client, timeout=20)
    rows = []
    acked: list[str] = []
    try:
        await asyncio.gather(*(robots.start(r) for r in endpoints))
        for life in range(1, args.restarts + 2):
            if life > 1:
                await robots.kill(("Robot3",))
                await robots.start("Robot3")
            for i in range(args.writes):
                label = f"L{life}W{i}"
                await kb.update(endpoints["Robot3"], insert(label))  # raises unless 2.04
                acked.append(label)
            context = await _context_of(client, endpoints["Robot1"], "Location")
            writers = sorted({*context.vv, *(d.writer for d in context.cloud)})
            rows.append({"life": life, "acknowledged": len(acked), "writers": len(writers),
                         "robot3_writers": sum(w.startswith("Robot3.") for w in writers),
                         "question_bytes": len(encode_sync(SyncMessage("Location", context)))})
            print(rows[-1], flush=True)
        for robot in HOLDERS:
            held = await _written(kb, endpoints[robot])
            print(f"{robot} shows {len(set(acked) & held)} of {len(acked)} acknowledged writes", flush=True)
            rows[-1][f"{robot.lower()}_present"] = len(set(acked) & held)
    finally:
        await client.aclose()
        await robots.aclose()
        shutil.rmtree(scratch, ignore_errors=True)
    for row in rows[:-1]:
        row.update({f"{r.lower()}_present": "" for r in HOLDERS})
    write_csv(RESULTS / "kb_durability_lives.csv", list(rows[-1]), rows)


# ============================================================================ big


def fill(folder: Path, triples: int, snapshot: bool) -> float:
    """A data folder of ``coapkb serve`` (its identity, ``central``) holding ``triples`` written triples; the
    seconds the writes took."""
    from coapkb.kb.durable import open_live
    from coapkb.kb.live import wall_ms
    from coapkb.kb.store import KnowledgeBase

    live, keeper = open_live(KnowledgeBase.load([LOCATION]), "central", 1, folder, wall_ms=wall_ms)
    assert keeper is not None
    keeper.compact_after_bytes = 1 << 40  # no compaction while filling: one snapshot at the end, or none
    started = time.perf_counter()
    for start in range(0, triples, 1000):
        body = " ".join(f'loc:T{i} loc:written "T{i}" .' for i in range(start, min(triples, start + 1000)))
        live.update(PREFIX + f"INSERT DATA {{ {body} }}")
    took = time.perf_counter() - started
    if snapshot:
        keeper.background = False
        keeper.compact()
    keeper.close()
    return took


async def serve_once(folder: Path | None) -> tuple[float, float, int, float]:
    """Start ``coapkb serve`` (on ``folder``): seconds to its serving line,
    to an answer counting the written triples, that count, and the CPU
    seconds the process used in all (on a loaded machine, the wall time
    is more than the work)."""
    import resource

    from coapkb.kb.client import KBClient
    from coapkb.kb.results import expect_select
    from coapkb.transport import open_client
    from coapkb.transport.base import Endpoint

    port = free_port()
    argv = ["serve", "--kb", str(LOCATION), "--writable", "--bind", f"127.0.0.1:{port}"]
    if folder is not None:
        argv += ["--data-dir", str(folder)]
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.monotonic()
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "coapkb", *argv, cwd=ROOT,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    line = (await asyncio.wait_for(proc.stdout.readline(), 300)).decode()
    serving = time.monotonic() - started
    if not line.startswith("serving"):
        raise RuntimeError(f"serve did not start: {line} {(await proc.stderr.read()).decode()[-2000:]}")
    client = await open_client("coap")
    try:
        result = await KBClient(client, timeout=60).sparql(
            Endpoint("coap", "127.0.0.1", port), PREFIX + "SELECT (COUNT(*) AS ?n) WHERE { ?s loc:written ?v }")
        answered = time.monotonic() - started
        count = int(expect_select(result, "count").rows[0][0])
    finally:
        await client.aclose()
        proc.send_signal(signal.SIGKILL)
        await proc.wait()
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = used.ru_utime + used.ru_stime - children.ru_utime - children.ru_stime
    return serving, answered, count, cpu


async def big(args: argparse.Namespace) -> None:
    scratch = _scratch()
    rows = []
    try:
        serving, answered, count, cpu = await serve_once(None)
        rows.append({"folder": "none", "written_triples": count, "bytes": 0, "serving_s": round(serving, 2),
                     "answer_s": round(answered, 2), "cpu_s": round(cpu, 2)})
        print(rows[-1], flush=True)
        for snapshot in (True, False):
            folder = scratch / ("snapshot" if snapshot else "journal")
            took = fill(folder, args.triples, snapshot)
            size = sum(p.stat().st_size for p in folder.iterdir())
            print(f"filled {folder.name}: {args.triples} triples in {took:.1f} s, {size} bytes", flush=True)
            for _ in range(args.repeat):
                serving, answered, count, cpu = await serve_once(folder)
                rows.append({"folder": folder.name, "written_triples": count, "bytes": size,
                             "serving_s": round(serving, 2), "answer_s": round(answered, 2), "cpu_s": round(cpu, 2)})
                print(rows[-1], flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    write_csv(RESULTS / "kb_durability_big.csv", list(rows[0]), rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("latency")
    p.add_argument("--writes", type=int, default=1000)
    p = sub.add_parser("restart")
    p.add_argument("--writes", type=int, default=100)
    p.add_argument("--rounds", type=int, default=3)
    p = sub.add_parser("lives")
    p.add_argument("--restarts", type=int, default=50)
    p.add_argument("--writes", type=int, default=4)
    p = sub.add_parser("big")
    p.add_argument("--triples", type=int, default=100_000)
    p.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if args.what == "latency":
        latency(args)
    else:
        asyncio.run({"restart": restart, "lives": lives, "big": big}[args.what](args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
