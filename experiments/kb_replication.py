"""What replicating the writable KB costs on slow lossy links: bytes per
write, the time until every holder has it, and catching up after missing
writes.

    sudo .venv/bin/python -m experiments.kb_replication spread [--transports coap,zmq,zenoh,dds]
    sudo .venv/bin/python -m experiments.kb_replication catch-up [--missed 10,100,1000] [--loss 2,20]
    .venv/bin/python -m experiments.kb_replication soak [--writes 10000]

Every holder is a process of its own (``node`` below: the Location module,
a :class:`~coapkb.kb.replication.Replicator` and the KB's resources on one
transport) in its own network namespace of the kernel testbed, every link
at 35 kbit/s.  Nothing else runs on the links, so their counters are the
replication's bytes.

* **spread**: 3 holders (one cluster) or 9 (three clusters: each holder
  with its cluster's two and the same place in the next cluster), 2 % and
  20 % loss, over each transport.  An operator (a host of its own) sends
  ``--writes`` one-triple INSERT DATA writes, one every 2 s, each to a
  random holder; every holder logs when each write reaches it.  Bytes per
  write: every link's bytes over the writing phase, minus those of an idle
  phase as long (anti-entropy alone), over the writes.
* **catch-up**: 3 holders; holder C is stopped, the operator writes W times
  to A, C starts again and catches up.  Bytes: C's link, sent and
  received, from its start until it holds every write; against the missed
  writes' own encoding (each one's compact patch, as the peers' benchmark
  carries them: ``experiments/kb_catch_up_peers.py``) and a full transfer
  of the module (its triples in compact CBOR, the smallest form coapkb has).
* **soak**: one holder in this process takes a flood of writes (half of
  them moving a robot, a quarter adding a triple, a quarter deleting one
  added before): its RSS and journal stay bounded.
* **shift**: one holder of Location and Capability in this process takes
  the writes of a long shift, job after job, as robots send them (the pick,
  the position, the delivery, the load and charge: the named updates of
  ``coapkb.agent.knowledge_writer``), and the feeder's delivery of an
  object back to its shelf before it is picked again: written triples,
  the whole-state message, the version vector and CPU per write stay
  bounded.

Prints tables and writes ``experiments/results/kb_replication_*.csv``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import sys
import time
from pathlib import Path

from experiments.common import PORTS, experiment_argv, prepare_link_emulation, rss_mib, write_csv

ROOT = Path(__file__).resolve().parent.parent

LOCATION = ROOT / "ontologies" / "Location.owl"
LOC = "http://www.tcs.org/2018/Location#"
RESULTS = ROOT / "experiments" / "results"


def insert(label: str) -> str:
    return f"PREFIX loc: <{LOC}> INSERT DATA {{ loc:{label} loc:written \"{label}\" }}"


# ============================================================================ a holder


async def node(args: argparse.Namespace) -> None:
    """One holder: serves the Location module and replicates it; prints a
    JSON line when it starts and whenever a write's triple reaches it."""
    from rdflib import URIRef

    from coapkb.kb.live import LiveKB, wall_ms
    from coapkb.kb.replication import Holder, ReplicationSettings, Replicator
    from coapkb.kb.resources import KBResources
    from coapkb.kb.store import KnowledgeBase
    from coapkb.transport import open_client, parse_endpoint, reliability_for, serve
    from coapkb.transport.router import Router

    written = URIRef(LOC + "written")
    seen: set[str] = set()

    class Watched(LiveKB):
        def _show(self, effect) -> None:  # type: ignore[no-untyped-def]
            super()._show(effect)
            now = time.monotonic()
            for _s, p, o in effect.added:
                if p == written and str(o) not in seen:
                    seen.add(str(o))
                    print(json.dumps({"has": str(o), "t": now}), flush=True)

    bind = parse_endpoint(args.bind)
    reliability = reliability_for(bind.scheme, link_kbps=args.link_kbps)
    client = await open_client(bind.scheme, reliability=reliability)
    live = Watched(KnowledgeBase.load([LOCATION]), f"{args.name}.1", wall_ms=wall_ms)
    holders = [Holder(n, parse_endpoint(uri), ("Location",)) for n, _, uri in (p.partition("=") for p in args.peer)]
    holders += [Holder(n, parse_endpoint(uri), ("Location",), remote=True)
                for n, _, uri in (p.partition("=") for p in args.remote)]
    replicator = Replicator(live, client, holders, settings=ReplicationSettings(sync_every_s=args.sync_every),
                            rng=random.Random(args.name))
    router = Router()
    KBResources(live, replicator=replicator).mount(router)
    server = await serve(router, bind, reliability=reliability)
    replicator.start()
    print(json.dumps({"ready": args.name, "t": time.monotonic()}), flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await replicator.aclose()
        await server.aclose()
        await client.aclose()


async def operator(args: argparse.Namespace) -> None:
    """Sends the writes: ``--count`` of them, ``--every`` s apart, each to a
    random one of ``--to``; prints each one's send time and answer."""
    from coapkb.kb.client import KBClient, QueryFailed
    from coapkb.transport import open_client, parse_endpoint, reliability_for
    from coapkb.transport.base import Endpoint, TransportError

    targets = [parse_endpoint(uri) for uri in args.to]
    scheme = targets[0].scheme
    client = await open_client(scheme, reliability=reliability_for(scheme, link_kbps=args.link_kbps))
    kb = KBClient(client, timeout=60)
    rng = random.Random(args.seed)

    async def one(i: int, target: Endpoint) -> None:
        label = f"{args.prefix}{i}"
        sent = time.monotonic()
        try:
            await kb.update(target, insert(label))
            status = "2.04"
        except QueryFailed as exc:
            status = exc.response.status.dotted
        except TransportError:
            status = "lost"
        print(json.dumps({"wrote": label, "sent": sent, "answered": time.monotonic(), "status": status}), flush=True)

    pending = []
    slots = asyncio.Semaphore(args.in_flight)

    async def held(i: int, target: Endpoint) -> None:
        async with slots:
            await one(i, target)

    for i in range(args.count):
        pending.append(asyncio.ensure_future(held(i, rng.choice(targets))))
        if args.every:
            await asyncio.sleep(args.every)
    await asyncio.gather(*pending)
    await client.aclose()


# ============================================================================ on the testbed


class Holders:
    """The holders and the operator on a testbed: processes and their output."""

    def __init__(self, tb, scheme: str, names: list[str], peers: dict[str, tuple[list[str], list[str]]],
                 link_kbps: float,
                 sync_every: float) -> None:
        self.tb, self.scheme, self.names, self.peers = tb, scheme, names, peers
        self.link_kbps, self.sync_every = link_kbps, sync_every
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.has: dict[str, dict[str, float]] = {n: {} for n in names}
        self.readers: list[asyncio.Task[None]] = []

    def uri(self, name: str) -> str:
        return f"{self.scheme}://{self.tb.address(name)}:{PORTS[self.scheme]}"

    async def start(self, name: str) -> None:
        argv = [*experiment_argv("kb_replication"), "node", "--name", name, "--bind", self.uri(name), "--link-kbps", str(self.link_kbps),
                "--sync-every", str(self.sync_every)]
        mates, ring = self.peers[name]
        argv += [a for p in mates for a in ("--peer", f"{p}={self.uri(p)}")]
        argv += [a for p in ring for a in ("--remote", f"{p}={self.uri(p)}")]
        proc = await self.tb.spawn(name, argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
                                   cwd=ROOT)
        line = json.loads(await asyncio.wait_for(proc.stdout.readline(), 60))
        assert line.get("ready") == name, line
        self.procs[name] = proc
        self.readers.append(asyncio.ensure_future(self._read(name, proc)))

    async def _read(self, name: str, proc: asyncio.subprocess.Process) -> None:
        while line := await proc.stdout.readline():
            event = json.loads(line)
            if "has" in event:
                self.has[name].setdefault(event["has"], event["t"])

    async def stop(self, name: str) -> None:
        proc = self.procs.pop(name)
        proc.terminate()
        await proc.wait()

    async def write(self, count: int, every: float, to: list[str], prefix: str, seed: int = 1) -> list[dict]:
        argv = [*experiment_argv("kb_replication"), "operator", "--count", str(count), "--every", str(every), "--prefix", prefix,
                "--seed", str(seed), "--link-kbps", str(self.link_kbps), *(a for n in to for a in ("--to", self.uri(n)))]
        proc = await self.tb.spawn("operator", argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
                                   cwd=ROOT)
        out, err = await proc.communicate()
        if proc.returncode:
            raise RuntimeError(f"operator failed: {err.decode()[-2000:]}")
        return [json.loads(line) for line in out.decode().splitlines()]

    async def until_everyone_has(self, labels: list[str], names: list[str], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(label in self.has[n] for n in names for label in labels):
                return True
            await asyncio.sleep(0.2)
        return False

    async def aclose(self) -> None:
        for name in list(self.procs):
            await self.stop(name)
        for reader in self.readers:
            reader.cancel()


def topology(robots: int) -> dict[str, tuple[list[str], list[str]]]:
    """Each holder's peers, as the team harness gives them: its cluster's
    others, and the same place in the next cluster (a ring of clusters)."""
    names = [f"robot{i}" for i in range(1, robots + 1)]
    clusters = [names[i:i + 3] for i in range(0, robots, 3)]
    peers: dict[str, tuple[list[str], list[str]]] = {}
    for c, cluster in enumerate(clusters):
        for place, name in enumerate(cluster):
            ring = [clusters[(c + 1) % len(clusters)][place]] if len(clusters) > 1 else []
            peers[name] = ([m for m in cluster if m != name], ring)
    return peers


def _total(counters: dict, names: list[str]) -> int:
    return sum(counters[n].tx_bytes for n in names)


def _pct(values: list[float], q: float) -> float:
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))] if values else float("nan")


async def spread(args: argparse.Namespace) -> None:
    from coapkb.bench.linkemu import LinkSpec, Testbed

    rows = []
    for scheme in args.transports.split(","):
        for robots in (3, 9):
            for loss in (2.0, 20.0):
                names = [f"robot{i}" for i in range(1, robots + 1)]
                link = LinkSpec(rate_kbit=args.kbps, loss_pct=loss)
                with Testbed(names + ["operator"], link) as tb:
                    holders = Holders(tb, scheme, names, topology(robots), args.kbps, args.sync_every)
                    try:
                        await asyncio.gather(*(holders.start(n) for n in names))
                        await asyncio.sleep(args.sync_every * 2)
                        before = await tb.acounters()
                        await asyncio.sleep(args.writes * 2.0)
                        idle = _total(await tb.acounters(), names) - _total(before, names)
                        before = await tb.acounters()
                        started = time.monotonic()
                        answers = await holders.write(args.writes, 2.0, names, "W")
                        labels = [a["wrote"] for a in answers if a["status"] == "2.04"]
                        everyone = await holders.until_everyone_has(labels, names, 120)
                        elapsed = time.monotonic() - started
                        after = await tb.acounters()
                    finally:
                        await holders.aclose()
                sent = {a["wrote"]: a["sent"] for a in answers}
                spans = [max(holders.has[n].get(label, float("inf")) for n in names) - sent[label] for label in labels]
                writes_bytes = _total(after, names) - _total(before, names)
                idle_scaled = idle * elapsed / (args.writes * 2.0)
                row = {
                    "transport": scheme, "robots": robots, "loss_pct": loss, "kbps": args.kbps,
                    "writes": args.writes, "acknowledged": len(labels), "everyone_has_all": everyone,
                    "bytes_per_write": round((writes_bytes - idle_scaled) / max(1, args.writes)),
                    "idle_bytes_per_s": round(idle / (args.writes * 2.0), 1),
                    "spread_p50_s": round(_pct(spans, 0.5), 3), "spread_p99_s": round(_pct(spans, 0.99), 3),
                    "spread_max_s": round(max(spans), 3) if spans else None,
                }
                rows.append(row)
                print(row, flush=True)
    write_csv(RESULTS / "kb_replication_spread.csv", list(rows[0]), rows)


def missed_encoding(count: int) -> tuple[int, int, int]:
    """For ``count`` missed one-triple writes: their own encoded size (each
    write's compact patch, what the peers' benchmark carries too), the same
    writes as deltas in one sync message, and the whole Location module as
    a compact graph (a full transfer)."""
    from coapkb.kb.live import LiveKB
    from coapkb.kb.store import KnowledgeBase
    from coapkb.kb.update import encode_patch
    from coapkb.model.results import GraphResult
    from coapkb.wire import codec
    from coapkb.wire.sync import SyncMessage, encode_sync

    live = LiveKB(KnowledgeBase.load([LOCATION]), "robot1.1", wall_ms=lambda: 1_800_000_000_000)
    deltas = [next(iter(live.update(insert(f"M{i}")).deltas.values())) for i in range(count)]
    own = sum(len(encode_patch([], d.added)) for d in deltas)
    context = live.replicas["Location"].context
    batched = len(encode_sync(SyncMessage("Location", context, deltas)))
    whole = live.query("CONSTRUCT WHERE { ?s ?p ?o }", row_limit=10**7)
    assert isinstance(whole, GraphResult)
    return own, batched, len(codec.encode_cbor(whole))


async def quiet_links(tb, names: list[str], sync_every: float, timeout: float = 600) -> None:  # type: ignore[no-untyped-def]
    """Until ``names`` send no more than anti-entropy would for a while: the
    pushes to the stopped holder have given up, so none reaches it when it
    starts again and counts as catch-up."""
    deadline = time.monotonic() + timeout
    last = _total(await tb.acounters(), names)
    while time.monotonic() < deadline:
        await asyncio.sleep(sync_every)
        now = _total(await tb.acounters(), names)
        if now - last < 400 * len(names):  # a round or two of contexts
            return
        last = now


async def catch_up(args: argparse.Namespace) -> None:
    from coapkb.bench.linkemu import LinkSpec, Testbed

    rows = []
    names = ["robot1", "robot2", "robot3"]
    for missed in (int(m) for m in args.missed.split(",")):
        for loss in (float(x) for x in args.loss.split(",")):
            link = LinkSpec(rate_kbit=args.kbps, loss_pct=loss)
            with Testbed(names + ["operator"], link) as tb:
                holders = Holders(tb, "coap", names, topology(3), args.kbps, args.sync_every)
                try:
                    await asyncio.gather(*(holders.start(n) for n in names))
                    await holders.stop("robot3")
                    answers = await holders.write(missed, 0.0, ["robot1"], "M")
                    labels = [a["wrote"] for a in answers if a["status"] == "2.04"]
                    if len(labels) < missed:
                        raise RuntimeError(f"only {len(labels)} of {missed} writes acknowledged")
                    await holders.until_everyone_has(labels, ["robot2"], 600)
                    await quiet_links(tb, ["robot1", "robot2"], args.sync_every)
                    before = await tb.acounters()
                    started = time.monotonic()
                    await holders.start("robot3")
                    done = await holders.until_everyone_has(labels, ["robot3"], 900)
                    took = time.monotonic() - started
                    after = await tb.acounters()
                finally:
                    await holders.aclose()
            c = after["robot3"] - before["robot3"]
            own_bytes, batched_bytes, module_bytes = missed_encoding(missed)
            row = {
                "missed": missed, "loss_pct": loss, "kbps": args.kbps, "caught_up": done,
                "catch_up_bytes": c.tx_bytes + c.rx_bytes, "catch_up_s": round(took, 2),
                "missed_own_bytes": own_bytes, "missed_batched_bytes": batched_bytes,
                "full_module_bytes": module_bytes,
                "x_missed": round((c.tx_bytes + c.rx_bytes) / own_bytes, 2),
                "x_full": round((c.tx_bytes + c.rx_bytes) / module_bytes, 3),
            }
            rows.append(row)
            print(row, flush=True)
    write_csv(RESULTS / "kb_replication_catch_up.csv", list(rows[0]), rows)


def soak(args: argparse.Namespace) -> None:
    """A flood of writes to one holder: RSS and the journal's size along the way."""
    import gc
    import os

    from coapkb.kb.live import LiveKB, wall_ms
    from coapkb.kb.store import KnowledgeBase

    live = LiveKB(KnowledgeBase.load([LOCATION]), "A.1", wall_ms=wall_ms)
    replica = live.replicas["Location"]
    rows = []
    rng = random.Random(1)
    kept: list[str] = []
    started = time.process_time()
    for i in range(1, args.writes + 1):
        draw = rng.random()
        if draw < 0.5:  # a robot moves: a single value replaced
            robot, aisle = rng.randint(1, 9), rng.randint(1, 9)
            live.update(f"PREFIX loc: <{LOC}> DELETE {{ loc:Robot{robot} loc:Robot_aisle_no ?a }} "
                        f"INSERT {{ loc:Robot{robot} loc:Robot_aisle_no {aisle} }} "
                        f"WHERE {{ loc:Robot{robot} loc:Robot_aisle_no ?a }}")
        elif draw < 0.75 or not kept:
            kept.append(f"S{i}")
            live.update(insert(f"S{i}"))
        else:
            label = kept.pop(rng.randrange(len(kept)))
            live.update(f"PREFIX loc: <{LOC}> DELETE DATA {{ loc:{label} loc:written \"{label}\" }}")
        if i % (args.writes // 10) == 0:
            gc.collect()
            rows.append({"writes": i, "rss_mib": round(rss_mib(os.getpid()), 1), "journal_deltas": len(replica.journal),
                         "journal_size": replica.journal_size, "journal_max": replica.limits.journal_max,
                         "written_triples": len(replica.entries), "cpu_s": round(time.process_time() - started, 2)})
            print(rows[-1], flush=True)
    write_csv(RESULTS / "kb_replication_soak.csv", list(rows[0]), rows)


def shift(args: argparse.Namespace) -> None:
    """The writes of ``args.jobs`` jobs, three robots taking turns, into one
    holder: what it holds and what a write costs along the way."""
    import gc
    import os

    from coapkb.harness.team import DEFAULT_ONTOLOGIES, product_names
    from coapkb.kb.live import LiveKB
    from coapkb.kb.named_updates import NamedUpdate, named_updates_sparql
    from coapkb.kb.results import expect_select
    from coapkb.kb.store import KnowledgeBase
    from coapkb.wire.sync import SyncMessage, encode_sync

    ontologies = DEFAULT_ONTOLOGIES
    names = product_names(KnowledgeBase.load([ontologies / "Object.owl"]))[: args.catalogue]
    live = LiveKB(KnowledgeBase.load([ontologies / "Location.owl", ontologies / "Capability.owl"]), "A.1",
                  wall_ms=lambda: clock_ms)
    places: dict[str, tuple[int, int, int]] = {}
    rows = expect_select(live.query(
        f"PREFIX loc: <{LOC}> SELECT ?o ?a ?r ?b WHERE {{ ?o loc:Inventory_aisle_no ?a ; loc:Inventory_rack_no ?r ; "
        "loc:Inventory_bin_no ?b }", row_limit=1_000_000), "the shelves").rows
    for o, a, r, b in rows:
        places[str(o).rsplit("#", 1)[-1]] = (int(a), int(r), int(b))
    names = [n for n in names if n in places]
    clock_ms = 1_700_000_000_000
    picked: set[str] = set()
    out: list[dict[str, object]] = []
    window_writes, window_cpu = 0, 0.0

    def write(*updates: NamedUpdate) -> None:
        nonlocal window_writes, window_cpu
        text = named_updates_sparql(updates)
        started = time.process_time()
        live.update(text)
        window_cpu += time.process_time() - started
        window_writes += 1

    for job in range(1, args.jobs + 1):
        clock_ms += 7_000  # a job every few seconds of the shift
        robot = f"Robot{job % 3 + 1}"
        obj = names[job % len(names)]
        aisle, rack, bin_no = places[obj]
        if obj in picked:  # delivered back to its shelf before it is drawn again (the feeder's restock)
            write(NamedUpdate("restock", (obj, aisle, rack, bin_no)))
        write(NamedUpdate("pick", (obj, robot, job)), NamedUpdate("robot-at", (robot, aisle, rack, clock_ms)))
        write(NamedUpdate("delivered", (obj, job)), NamedUpdate("robot-at", (robot, 0, 0, clock_ms + 3_000)))
        write(NamedUpdate("load", (robot, 0.0, 400.0 - job % 50, clock_ms + 3_000)))
        picked.add(obj)
        if job % args.every == 0:
            gc.collect()
            row: dict[str, object] = {"jobs": job, "rss_mib": round(rss_mib(os.getpid()), 1)}
            for module in ("Location", "Capability"):
                replica = live.replicas[module]
                state = encode_sync(SyncMessage(module, replica.context, replica.state()))
                row[f"{module.lower()}_written"] = len(replica.entries)
                row[f"{module.lower()}_state_bytes"] = len(state)
                row[f"{module.lower()}_writers"] = len(replica.context.vv)
            row["cpu_ms_per_write"] = round(1000 * window_cpu / window_writes, 3)
            row["store_rebuilds"] = live.rebuilds
            window_writes, window_cpu = 0, 0.0
            out.append(row)
            print(row, flush=True)
    write_csv(RESULTS / "kb_replication_shift.csv", list(out[0]), out)


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.kb_replication",
                                     description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("spread")
    p.add_argument("--transports", default="coap,zmq,zenoh,dds")
    p.add_argument("--writes", type=int, default=30)
    p.add_argument("--kbps", type=float, default=35.0)
    p.add_argument("--sync-every", type=float, default=5.0)
    p = sub.add_parser("catch-up")
    p.add_argument("--missed", default="10,100,1000")
    p.add_argument("--loss", default="2,20", help="loss rates (%%) of the links, comma-separated")
    p.add_argument("--kbps", type=float, default=35.0)
    p.add_argument("--sync-every", type=float, default=5.0)
    p = sub.add_parser("soak")
    p.add_argument("--writes", type=int, default=30_000)
    p = sub.add_parser("shift")
    p.add_argument("--jobs", type=int, default=100_000)
    p.add_argument("--every", type=int, default=1000, help="a row every this many jobs")
    p.add_argument("--catalogue", type=int, default=1000, help="objects on the shelves (each delivered back)")
    p = sub.add_parser("node")
    p.add_argument("--name", required=True)
    p.add_argument("--bind", required=True)
    p.add_argument("--peer", action="append", default=[], help="NAME=URI of a holder in this cluster")
    p.add_argument("--remote", action="append", default=[], help="NAME=URI of a holder in the next cluster")
    p.add_argument("--link-kbps", type=float, default=None)
    p.add_argument("--sync-every", type=float, default=5.0)
    p = sub.add_parser("operator")
    p.add_argument("--to", action="append", required=True)
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--every", type=float, default=2.0)
    p.add_argument("--prefix", default="W")
    p.add_argument("--in-flight", type=int, default=4, help="writes awaiting their answer at once, at most")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--link-kbps", type=float, default=None)
    args = parser.parse_args()
    if args.what in ("soak", "shift"):
        {"soak": soak, "shift": shift}[args.what](args)
        return 0
    if args.what in ("spread", "catch-up"):
        why = prepare_link_emulation()
        if why is not None:
            print(f"cannot emulate links here: {why}", file=sys.stderr)
            return 1
    run = {"spread": spread, "catch-up": catch_up, "node": node, "operator": operator}[args.what]
    asyncio.run(run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
