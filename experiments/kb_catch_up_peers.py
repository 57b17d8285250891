"""Catch-up with the peers' own recovery mechanisms: what a late joiner
pays, on the same slow lossy link, to get W changes it missed -- the
counterpart of ``kb_replication.py catch-up`` for Zenoh and DDS.

    sudo .venv/bin/python -m experiments.kb_catch_up_peers [--missed 10,100,1000] [--peers zenoh,dds]

The changes are the ones ``kb_replication.py catch-up`` makes: W one-triple
writes ``loc:M{i} loc:written "M{i}"``, each carried as the bytes coapkb
encodes the change in (:func:`coapkb.kb.update.encode_patch` of the inserted
triple, 70-74 bytes), so the payloads are the same and only the mechanism
differs.  Two hosts of the kernel testbed, every link 35 kbit/s with 2 % or
20 % loss: ``robot1`` (the live holder) publishes the W changes while
nobody listens; then the late joiner starts on ``robot3`` (our stopped
holder C) and recovers them with the peer's own means:

* **zenoh** (eclipse-zenoh 1.10, ``zenoh.ext``): robot1 has an
  ``AdvancedPublisher`` with a cache of the last W samples (replies with
  congestion control BLOCK), sample-miss detection with a periodic
  heartbeat (``--heartbeat``, 5 s like coapkb's anti-entropy) and publisher
  detection; robot3 an ``AdvancedSubscriber`` with history (``max_samples``
  W) and recovery by heartbeat.  Both sessions are peers with timestamping
  on and scouting off; robot1 listens on ``tcp/<robot1>:7447`` (or, with
  ``--zenoh-link udp``, ``udp/<robot1>:7447?rel=1``) and robot3 connects
  there.  The history and recovery queries of ``zenoh.ext`` time out after
  10 s (its builder's default; the Python API cannot change it), and
  Zenoh batches up to ``transport/link/tx/batch_size`` (65 535 bytes by
  default, 15 s of this link) into one TCP frame, and a sender that waits
  longer than ``.../congestion_control/block/wait_before_close`` (5 s) for
  room in its queue closes the transport; ``--zenoh-batch`` and
  ``--zenoh-block-wait`` change them on both sessions.
* **zenoh-get** (not in the default set): the same AdvancedPublisher, but
  robot3 sends one plain ``get()`` of its cache (``<key>/@adv/**``, what
  the AdvancedSubscriber's history query asks) with a timeout of
  ``--timeout``: the cost of one history transfer without ``zenoh.ext``'s
  10 s limit.
* **dds** (Cyclone DDS): robot1's writer is RELIABLE, KEEP_ALL,
  TRANSIENT_LOCAL (durability service KEEP_ALL, no limits); robot3's reader
  RELIABLE, KEEP_ALL, TRANSIENT_LOCAL.  A keyless type ``coapkb::Change
  { sequence<octet> body; }``.  The domains are configured as coapkb's DDS
  transport configures them (:mod:`coapkb.transport.dds.config`): no
  multicast, robot1's participant on ``<robot1>:7400`` with no peers,
  robot3's on an ephemeral port with robot1 as its one unicast peer,
  1472-byte messages, 1 s heartbeats, 30 s lease; robot3 re-announces its
  participant (0.25 s doubling to 4 s) until the writer is matched, as the
  transport's client does.

Bytes: robot3's link, sent and received, from the moment its process is
started until it holds all W changes (``catch_up_bytes``, and against the
W payloads' own size ``payload_bytes``: ``x_payload``); time likewise
(``catch_up_s``; ``open_s``: until its session or participant was open).
A case gives up after ``--timeout`` (900 s) and is recorded with
``caught_up`` false and what it had ``received``.  Each role (``zenoh-pub``,
``zenoh-sub``, ``zenoh-get``, ``dds-writer``, ``dds-reader``) runs as a
process of its own in its host's network namespace and reports JSON lines
on stdout; ``--log-dir`` keeps their stderr (Zenoh's warnings).

Prints each row and writes ``experiments/results/kb_catch_up_peers.csv``
(``--out`` another name there).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import json
import sys
import threading
import time
from pathlib import Path

from experiments.common import experiment_argv, prepare_link_emulation, stop_processes, write_csv

ROOT = Path(__file__).resolve().parent.parent

LOC = "http://www.tcs.org/2018/Location#"
RESULTS = ROOT / "experiments" / "results"
KEY = "coapkb/kb/Location/changes"
TOPIC = "coapkb_kb_Location_changes"
ZENOH_PORT = 7447
DDS_PORT = 7400


def change(i: int) -> bytes:
    """The i-th missed write as coapkb encodes it: the patch inserting ``loc:M{i} loc:written "M{i}"``."""
    from rdflib import Literal, URIRef

    from coapkb.kb.update import encode_patch

    label = f"M{i}"
    return encode_patch([], [(URIRef(LOC + label), URIRef(LOC + "written"), Literal(label))])


def label_of(payload: bytes) -> str:
    from coapkb.kb.update import decode_patch

    _, inserts = decode_patch(payload)
    return str(inserts[0][2])


def emit(**event: object) -> None:
    print(json.dumps(event), flush=True)


class Received:
    """The distinct changes a late joiner has got; prints ``done`` when all are in."""

    def __init__(self, count: int) -> None:
        self.count = count
        self.labels: set[str] = set()
        self.deliveries = 0
        self.lock = threading.Lock()
        self.done = threading.Event()

    def add(self, payload: bytes) -> None:
        label = label_of(payload)
        with self.lock:
            self.deliveries += 1
            if label in self.labels:
                return
            self.labels.add(label)
            if len(self.labels) >= self.count and not self.done.is_set():
                self.done.set()
                emit(done=len(self.labels), deliveries=self.deliveries, t=time.monotonic())

    def progress(self) -> None:
        with self.lock:
            emit(have=len(self.labels), deliveries=self.deliveries, t=time.monotonic())


def _wait_forever() -> None:
    threading.Event().wait()


# ============================================================================ zenoh roles


def _zenoh_config(args: argparse.Namespace, *, listen: tuple[str, ...] = (),  # type: ignore[no-untyped-def]
                  connect: tuple[str, ...] = ()):
    """A peer session on explicit endpoints (scouting off, as coapkb's zenoh transport), timestamping on."""
    import zenoh

    from coapkb.transport.zenoh.transport import session_config

    zenoh.init_log_from_env_or("warn")  # lease expiries, closed transports: to stderr (--log-dir keeps them)
    config = session_config("peer", listen=listen, connect=connect)
    config.insert_json5("timestamping/enabled", "true")
    if args.batch:
        config.insert_json5("transport/link/tx/batch_size", str(args.batch))
    if args.block_wait:
        config.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                            str(round(args.block_wait * 1e6)))
    return config


def zenoh_pub(args: argparse.Namespace) -> None:
    """robot1: an AdvancedPublisher with a cache of ``--count`` samples; publishes them, then serves its cache."""
    import zenoh
    from zenoh import ext

    session = zenoh.open(_zenoh_config(args, listen=(args.locator,)))
    publisher = ext.declare_advanced_publisher(
        session, KEY,
        cache=ext.CacheConfig(args.count, replies_config=ext.RepliesConfig(
            congestion_control=zenoh.CongestionControl.BLOCK)),
        sample_miss_detection=ext.MissDetectionConfig(heartbeat=args.heartbeat),
        publisher_detection=True,
    )
    payload_bytes = 0
    for i in range(args.count):
        payload = change(i)
        payload_bytes += len(payload)
        publisher.put(payload)
    emit(published=args.count, payload_bytes=payload_bytes, t=time.monotonic())
    _wait_forever()


def zenoh_sub(args: argparse.Namespace) -> None:
    """robot3, the late joiner: an AdvancedSubscriber with history and heartbeat recovery."""
    import zenoh
    from zenoh import ext

    received = Received(args.count)
    session = zenoh.open(_zenoh_config(args, connect=(args.locator,)))
    emit(open=True, t=time.monotonic())

    def on_sample(sample: zenoh.Sample) -> None:
        received.add(sample.payload.to_bytes())

    subscriber = ext.declare_advanced_subscriber(
        session, KEY, on_sample,
        history=ext.HistoryConfig(detect_late_publishers=args.detect_late_publishers, max_samples=args.count),
        recovery=ext.RecoveryConfig(heartbeat=True),
    )
    while not received.done.wait(10.0):
        received.progress()
    _wait_forever()
    del subscriber


def zenoh_get(args: argparse.Namespace) -> None:
    """robot3, the late joiner, without zenoh.ext on its side: one plain query
    of the AdvancedPublisher's cache (what the AdvancedSubscriber's history
    query asks) with a timeout as long as the case may last.  A query that
    ends without a single reply (the session opened before the connection or
    the cache's queryable was in place: "scouting delay elapsed" on a lossy
    link) is asked again a second later."""
    import zenoh
    from zenoh.handlers import Callback

    received = Received(args.count)
    session = zenoh.open(_zenoh_config(args, connect=(args.locator,)))
    emit(open=True, t=time.monotonic())

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            received.add(reply.ok.payload.to_bytes())

    queries = 0
    next_progress = time.monotonic() + 10.0
    while not received.done.is_set():
        ended = threading.Event()
        queries += 1
        emit(query=queries, t=time.monotonic())
        session.get(f"{KEY}/@adv/**", Callback(on_reply, drop=ended.set),
                    consolidation=zenoh.ConsolidationMode.NONE, accept_replies=zenoh.ReplyKeyExpr.ANY,
                    timeout=args.query_timeout)
        while not ended.is_set() and not received.done.is_set():
            ended.wait(0.2)
            if time.monotonic() >= next_progress:
                received.progress()
                next_progress = time.monotonic() + 10.0
        if received.done.is_set() or received.deliveries:
            break
        time.sleep(1.0)
    received.done.wait()
    _wait_forever()


# ============================================================================ DDS roles


def _dds_type():  # type: ignore[no-untyped-def]
    """``coapkb::Change { sequence<octet> body; }`` (keyless: one instance, KEEP_ALL keeps every change)."""
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl.types import sequence, uint8

    return make_idl_struct("Change", "coapkb::Change", {"body": sequence[uint8]})


def _dds_participant(xml: str):  # type: ignore[no-untyped-def]
    from cyclonedds.domain import Domain, DomainParticipant

    domain = Domain(1, xml)
    return domain, DomainParticipant(1)


def dds_writer(args: argparse.Namespace) -> None:
    """robot1: a RELIABLE, KEEP_ALL, TRANSIENT_LOCAL writer of ``--count`` changes."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    from coapkb.transport.dds.config import server_domain_xml

    change_type = _dds_type()
    _domain, participant = _dds_participant(server_domain_xml(args.address, args.port))
    topic = Topic(participant, TOPIC, change_type)
    qos = Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.History.KeepAll,
        Policy.Durability.TransientLocal,
        Policy.DurabilityService(cleanup_delay=0, history=Policy.History.KeepAll, max_samples=-1, max_instances=-1,
                                 max_samples_per_instance=-1),
        Policy.ResourceLimits(max_samples=-1, max_instances=-1, max_samples_per_instance=-1),
    )
    writer = DataWriter(participant, topic, qos=qos)
    payload_bytes = 0
    for i in range(args.count):
        payload = change(i)
        payload_bytes += len(payload)
        writer.write(change_type(body=list(payload)))
    emit(published=args.count, payload_bytes=payload_bytes, t=time.monotonic())
    _wait_forever()


def dds_reader(args: argparse.Namespace) -> None:
    """robot3, the late joiner: a RELIABLE, KEEP_ALL, TRANSIENT_LOCAL reader."""
    from cyclonedds.core import DDSException, Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    from coapkb.transport.dds.config import client_domain_xml, local_address_towards

    change_type = _dds_type()
    host, _, port = args.peer.rpartition(":")
    local = local_address_towards(host, int(port))
    _domain, participant = _dds_participant(client_domain_xml(local, args.peer))
    topic = Topic(participant, TOPIC, change_type)
    qos = Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.History.KeepAll,
        Policy.Durability.TransientLocal,
    )
    reader = DataReader(participant, topic, qos=qos)
    emit(open=True, t=time.monotonic())
    received = Received(args.count)
    # Until the writer is matched, re-announce (SPDP) with a back-off, as
    # coapkb's DDS client does: Cyclone pings an undiscovered peer every 30 s.
    pause, next_announce, announced = 0.25, time.monotonic() + 0.25, 0
    next_progress = time.monotonic() + 10.0
    while not received.done.is_set():
        for sample in reader.take(N=1024):
            if isinstance(sample, change_type):
                received.add(bytes(sample.body))
        now = time.monotonic()
        if next_announce is not None and now >= next_announce:
            if reader.get_subscription_matched_status().current_count > 0:
                next_announce = None
                emit(matched=True, announced=announced, t=now)
            else:
                announced += 1
                try:
                    participant.set_qos(Qos(Policy.Userdata(announced.to_bytes(4, "big"))))
                except DDSException:
                    pass
                pause = min(pause * 2, 4.0)
                next_announce = now + pause
        if now >= next_progress:
            received.progress()
            next_progress = now + 10.0
        time.sleep(0.02)
    _wait_forever()


# ============================================================================ on the testbed


async def _lines(proc: asyncio.subprocess.Process, out: asyncio.Queue[dict], log: Path | None = None) -> None:
    """The process's JSON events into ``out``; other lines (Zenoh logs to stdout) to ``log``."""
    assert proc.stdout is not None
    with open(log, "ab") if log is not None else contextlib.nullcontext() as f:
        while line := await proc.stdout.readline():
            try:
                event = json.loads(line)
            except json.JSONDecodeError:
                if f is not None:
                    f.write(line)
                    f.flush()
                continue
            if f is not None:
                f.write(line)
                f.flush()
            await out.put(event)


async def _drain(proc: asyncio.subprocess.Process, tail: list[bytes], log: Path | None = None) -> None:
    """Keep the last of the process's stderr in ``tail``, all of it in ``log``."""
    assert proc.stderr is not None
    with open(log, "ab") if log is not None else contextlib.nullcontext() as f:
        while chunk := await proc.stderr.read(4096):
            tail.append(chunk)
            del tail[:-8]
            if f is not None:
                f.write(chunk)
                f.flush()


async def _next(queue: asyncio.Queue[dict], key: str, deadline: float) -> dict | None:
    """The next event with ``key`` before ``deadline`` (monotonic), or None."""
    while (left := deadline - time.monotonic()) > 0:
        try:
            event = await asyncio.wait_for(queue.get(), left)
        except TimeoutError:
            return None
        if key in event:
            return event
    return None


def variant(peer: str, args: argparse.Namespace) -> str:
    """The row's settings, in short."""
    if peer.startswith("zenoh"):
        batch = f"batch {args.zenoh_batch} B" if args.zenoh_batch else "batch default"
        batch += f", block wait {args.zenoh_block_wait:g} s" if args.zenoh_block_wait else ""
        if peer == "zenoh-get":
            return f"one get() of the AdvancedPublisher cache (timeout {args.timeout:g} s), {batch}"
        late = ", detect_late_publishers" if args.detect_late_publishers else ""
        return (f"AdvancedPublisher cache {{W}}, heartbeat {args.heartbeat:g} s; AdvancedSubscriber history "
                f"max {{W}}{late}, recovery heartbeat; query timeout 10 s; {batch}")
    return "RELIABLE KEEP_ALL TRANSIENT_LOCAL writer and reader; unicast peer, 1 s heartbeat, 1472 B messages"


def _roles(peer: str, tb, args: argparse.Namespace, count: int) -> tuple[list[str], list[str], str]:  # type: ignore[no-untyped-def]
    """argv of the holder (robot1) and the late joiner (robot3), and the locator."""
    robot1 = tb.address("robot1")
    if peer in ("zenoh", "zenoh-get"):
        locator = (f"tcp/{robot1}:{ZENOH_PORT}" if args.zenoh_link == "tcp"
                   else f"udp/{robot1}:{ZENOH_PORT}?rel=1")
        batch = ["--batch", str(args.zenoh_batch)] if args.zenoh_batch else []
        if args.zenoh_block_wait:
            batch += ["--block-wait", str(args.zenoh_block_wait)]
        pub = [*experiment_argv("kb_catch_up_peers"), "zenoh-pub", "--locator", locator, "--count", str(count),
               "--heartbeat", str(args.heartbeat), *batch]
        if peer == "zenoh-get":
            return pub, [*experiment_argv("kb_catch_up_peers"), "zenoh-get", "--locator", locator, "--count", str(count), *batch,
                         "--query-timeout", str(args.timeout)], locator
        sub = [*experiment_argv("kb_catch_up_peers"), "zenoh-sub", "--locator", locator, "--count", str(count), *batch]
        if args.detect_late_publishers:
            sub.append("--detect-late-publishers")
        return pub, sub, locator
    if peer == "dds":
        writer = [*experiment_argv("kb_catch_up_peers"), "dds-writer", "--address", robot1, "--port", str(DDS_PORT), "--count", str(count)]
        reader = [*experiment_argv("kb_catch_up_peers"), "dds-reader", "--peer", f"{robot1}:{DDS_PORT}", "--count", str(count)]
        return writer, reader, f"udp {robot1}:{DDS_PORT} (unicast peer)"
    raise ValueError(f"unknown peer {peer!r}")


async def one_case(peer: str, count: int, loss: float, args: argparse.Namespace) -> dict:
    from coapkb.bench.linkemu import LinkSpec, Testbed

    link = LinkSpec(rate_kbit=args.kbps, loss_pct=loss)
    procs: list[asyncio.subprocess.Process] = []
    tasks: list[asyncio.Task[None]] = []
    tails: dict[str, list[bytes]] = {"robot1": [], "robot3": []}
    logs: dict[str, Path | None] = {host: None for host in tails}
    if args.log_dir:
        Path(args.log_dir).mkdir(parents=True, exist_ok=True)
        logs = {host: Path(args.log_dir) / f"{peer}-{count}-{loss:g}-{host}.log" for host in tails}
        for log in logs.values():
            log.unlink(missing_ok=True)
    with Testbed(["robot1", "robot3"], link) as tb:
        try:
            holder_argv, joiner_argv, locator = _roles(peer, tb, args, count)
            holder_events: asyncio.Queue[dict] = asyncio.Queue()
            holder = await tb.spawn("robot1", holder_argv, stdout=asyncio.subprocess.PIPE,
                                    stderr=asyncio.subprocess.PIPE, cwd=ROOT)
            procs.append(holder)
            tasks += [asyncio.ensure_future(_lines(holder, holder_events, logs["robot1"])),
                      asyncio.ensure_future(_drain(holder, tails["robot1"], logs["robot1"]))]
            published = await _next(holder_events, "published", time.monotonic() + 120)
            if published is None:
                raise RuntimeError(f"{peer} holder did not publish: {b''.join(tails['robot1']).decode()[-2000:]}")
            await asyncio.sleep(1.0)  # nothing listens yet: robot3's link stays silent
            joiner_events: asyncio.Queue[dict] = asyncio.Queue()
            before = await tb.acounters()
            started = time.monotonic()
            joiner = await tb.spawn("robot3", joiner_argv, stdout=asyncio.subprocess.PIPE,
                                    stderr=asyncio.subprocess.PIPE, cwd=ROOT)
            procs.append(joiner)
            tasks += [asyncio.ensure_future(_lines(joiner, joiner_events, logs["robot3"])),
                      asyncio.ensure_future(_drain(joiner, tails["robot3"], logs["robot3"]))]
            deadline = started + args.timeout
            done = None
            have = 0
            opened = None
            while done is None and time.monotonic() < deadline:
                event = await _next(joiner_events, "t", min(deadline, time.monotonic() + 5))
                if event is None:
                    if joiner.returncode is not None:
                        break
                    continue
                if "have" in event:
                    have = event["have"]
                    print(f"  {peer} W={count} loss={loss:g}%: {have}/{count} after "
                          f"{event['t'] - started:.0f} s", flush=True)
                if "open" in event:
                    opened = event["t"] - started
                if "done" in event:
                    done = event
            after = await tb.acounters()
            took = (done["t"] if done else time.monotonic()) - started
            if done is None and joiner.returncode is not None:
                print(f"  {peer} late joiner exited ({joiner.returncode}): "
                      f"{b''.join(tails['robot3']).decode(errors='replace')[-2000:]}", flush=True)
        finally:
            await stop_processes(procs, grace_s=3.0)
            for task in tasks:
                task.cancel()
    c = after["robot3"] - before["robot3"]
    return {
        "peer": peer, "missed": count, "loss_pct": loss, "kbps": args.kbps, "caught_up": done is not None,
        "catch_up_bytes": c.tx_bytes + c.rx_bytes, "catch_up_s": round(took, 2),
        "open_s": None if opened is None else round(opened, 2),
        "payload_bytes": published["payload_bytes"],
        "x_payload": round((c.tx_bytes + c.rx_bytes) / published["payload_bytes"], 2),
        "tx_bytes": c.tx_bytes, "rx_bytes": c.rx_bytes, "received": done["done"] if done else have,
        "deliveries": done["deliveries"] if done else None, "locator": locator,
        "variant": variant(peer, args).replace("{W}", str(count)),
    }


async def run(args: argparse.Namespace) -> None:
    rows = []
    for peer in args.peers.split(","):
        for count in (int(m) for m in args.missed.split(",")):
            for loss in (float(p) for p in args.loss.split(",")):
                row = await one_case(peer, count, loss, args)
                rows.append(row)
                print(row, flush=True)
    path = RESULTS / args.out
    fields = list(rows[0])
    if args.append and path.exists():
        with path.open(newline="") as f:
            old = list(csv.DictReader(f))
        fields = list(dict.fromkeys([*(old[0] if old else []), *fields]))
        rows = old + rows
    write_csv(path, fields, rows)


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.kb_catch_up_peers",
                                     description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--missed", default="10,100,1000", help="W: the changes the late joiner missed")
    parser.add_argument("--peers", default="zenoh,dds", help="of zenoh, dds and zenoh-get (see above)")
    parser.add_argument("--loss", default="2,20", help="loss percentages, every host's link")
    parser.add_argument("--kbps", type=float, default=35.0)
    parser.add_argument("--timeout", type=float, default=900.0, help="give up on a case after this many seconds")
    parser.add_argument("--zenoh-link", choices=("tcp", "udp"), default="tcp",
                        help="tcp/<robot1>:7447 or udp/<robot1>:7447?rel=1")
    parser.add_argument("--heartbeat", type=float, default=5.0, help="the AdvancedPublisher's heartbeat period, s")
    parser.add_argument("--zenoh-batch", type=int, default=None,
                        help="zenoh's transport/link/tx/batch_size on both sessions (default: zenoh's, 65535)")
    parser.add_argument("--zenoh-block-wait", type=float, default=None,
                        help="zenoh's .../congestion_control/block/wait_before_close, s (default: zenoh's, 5 s)")
    parser.add_argument("--append", action="store_true", help="add the rows to --out instead of replacing it")
    parser.add_argument("--detect-late-publishers", action="store_true",
                        help="also HistoryConfig(detect_late_publishers=True): a second history query per publisher")
    parser.add_argument("--out", default="kb_catch_up_peers.csv", help="file name under experiments/results/")
    parser.add_argument("--log-dir", default=None, help="keep each process's stderr (zenoh warnings) here")
    sub = parser.add_subparsers(dest="role")
    p = sub.add_parser("zenoh-pub")
    p.add_argument("--locator", required=True)
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--heartbeat", type=float, default=5.0)
    p.add_argument("--batch", type=int, default=None)
    p.add_argument("--block-wait", type=float, default=None)
    p = sub.add_parser("zenoh-sub")
    p.add_argument("--locator", required=True)
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--detect-late-publishers", action="store_true")
    p.add_argument("--batch", type=int, default=None)
    p.add_argument("--block-wait", type=float, default=None)
    p = sub.add_parser("zenoh-get")
    p.add_argument("--locator", required=True)
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--batch", type=int, default=None)
    p.add_argument("--block-wait", type=float, default=None)
    p.add_argument("--query-timeout", type=float, default=900.0)
    p = sub.add_parser("dds-writer")
    p.add_argument("--address", required=True)
    p.add_argument("--port", type=int, default=DDS_PORT)
    p.add_argument("--count", type=int, required=True)
    p = sub.add_parser("dds-reader")
    p.add_argument("--peer", required=True, help="HOST:PORT of the writer's participant")
    p.add_argument("--count", type=int, required=True)
    args = parser.parse_args()
    roles = {"zenoh-pub": zenoh_pub, "zenoh-sub": zenoh_sub, "zenoh-get": zenoh_get, "dds-writer": dds_writer,
             "dds-reader": dds_reader}
    if args.role is not None:
        roles[args.role](args)
        return 0
    why = prepare_link_emulation()
    if why is not None:
        print(f"cannot emulate links here: {why}", file=sys.stderr)
        return 1
    asyncio.run(run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
