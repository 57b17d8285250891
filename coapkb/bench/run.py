"""Benchmark runs: one system, one team, one emulated link setting, one CSV row.

This reproduces the seed paper's experiment (section IV: 3/6/9 robots,
5..80 tasks, 35..512 kbit/s, 2..20 % loss, distributed vs centralised,
bytes exchanged and task completion time) on real processes and kernel
links, and adds the comparison the seed could not make: CoAP/UDP with
compact CBOR answers against the seed's own ZeroMQ/TCP with SPARQL text and
SPARQL-JSON answers, and the other transports beside them (:data:`SYSTEMS`).

:func:`run_once` puts every process of a run in its own network namespace of
a :class:`coapkb.bench.linkemu.Testbed`: each robot and the central server
behind the run's ``LinkSpec``, the feeder (:meth:`coapkb.harness.team.Team.run`,
in this process, moved into its namespace with
:func:`coapkb.bench.linkemu.enter_netns`) on an unshaped, lossless link.  It
reads the link counters between "team up" and "all tasks done" and returns
one :class:`BenchRow`; it never raises, so a sweep goes on.

docs/benchmarks.md specifies what one run is, the systems, and what every
column of a row measures.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime as _dt
import json
import logging
import math
import sys
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from ..errors import CoapkbError
from ..feeder.record import FateCounts
from ..harness.placement import Placement
from ..harness.record import TeamRecord
from ..harness.stats import percentile
from ..harness.team import DEFAULT_ONTOLOGIES, Fault, Team, TeamError, TeamSpec, draw_tasks
from ..transport.base import Endpoint, TrafficCounters
from ..transport.coap.reliability import ROBUST
from ..transport.registry import find, transport_for
from ..world import CLUSTER_SIZE
from .linkemu import (
    LinkCounters,
    LinkSpec,
    Testbed,
    available,
    cleanup_stale,
    enter_netns,
)
from .row import COLUMNS, KEY_COLUMNS, BenchRow, append_rows, done_keys, format_row, read_rows

__all__ = [
    "COLUMNS",
    "KEY_COLUMNS",
    "SYSTEMS",
    "BenchRow",
    "NetnsPlacement",
    "RunObserver",
    "SystemDef",
    "Timeouts",
    "append_rows",
    "done_keys",
    "format_row",
    "read_rows",
    "retransmission_label",
    "run_once",
    "security_label",
    "system_spec",
    "timeouts_for",
]

log = logging.getLogger(__name__)

FEEDER = "feeder"
CENTRAL = "central"


@dataclass(frozen=True)
class SystemDef:
    """One system under test: how the team is organised and what goes on the wire."""

    mode: str  # "distributed" or "central"
    transport: str  # a scheme of coapkb.transport.SCHEMES: "coap", "zmq", "zenoh", "zenoh+udp", "zenoh+quic", "dds"
    query_wire: str  # "compact" (named queries, CBOR) or "seed" (SPARQL text, SPARQL-JSON)
    description: str


SYSTEMS: dict[str, SystemDef] = {
    "coap-distributed": SystemDef("distributed", "coap", "compact", "CoAP/UDP, named queries, compact CBOR, KB split over the robots"),
    "coap-central": SystemDef("central", "coap", "compact", "CoAP/UDP, named queries, compact CBOR, one remote KB server"),
    "zmq-distributed": SystemDef("distributed", "zmq", "compact", "ZeroMQ/TCP, named queries, compact CBOR, KB split over the robots"),
    "zmq-central": SystemDef("central", "zmq", "compact", "ZeroMQ/TCP, named queries, compact CBOR, one remote KB server"),
    "seed-distributed": SystemDef("distributed", "zmq", "seed", "the seed's set-up: ZeroMQ/TCP, whole SPARQL text, SPARQL-JSON answers"),
    "seed-central": SystemDef("central", "zmq", "seed", "the seed's centralised baseline: ZeroMQ/TCP, SPARQL text, SPARQL-JSON"),
    "zenoh-distributed": SystemDef("distributed", "zenoh", "compact", "Zenoh/TCP, named queries, compact CBOR, KB split over the robots"),
    "zenoh-central": SystemDef("central", "zenoh", "compact", "Zenoh/TCP, named queries, compact CBOR, one remote KB server"),
    "zenoh-udp-distributed": SystemDef("distributed", "zenoh+udp", "compact", "Zenoh's reliable UDP (QUIC without TLS, never secured), named queries, compact CBOR, KB split over the robots"),
    "zenoh-udp-central": SystemDef("central", "zenoh+udp", "compact", "Zenoh's reliable UDP (QUIC without TLS, never secured), named queries, compact CBOR, one remote KB server"),
    "zenoh-quic-distributed": SystemDef("distributed", "zenoh+quic", "compact", "Zenoh/QUIC, named queries, compact CBOR, KB split over the robots"),
    "zenoh-quic-central": SystemDef("central", "zenoh+quic", "compact", "Zenoh/QUIC, named queries, compact CBOR, one remote KB server"),
    "dds-distributed": SystemDef("distributed", "dds", "compact", "DDS (Cyclone DDS, RTPS over UDP, no DDS Security in its wheel), named queries, compact CBOR, KB split over the robots"),
    "dds-central": SystemDef("central", "dds", "compact", "DDS (Cyclone DDS, RTPS over UDP, no DDS Security in its wheel), named queries, compact CBOR, one remote KB server"),
}

# --------------------------------------------------------------------------- systems and timeouts


@dataclass(frozen=True)
class Timeouts:
    """Time limits of one run, scaled to its link so a slow lossy run still ends."""

    query_s: float  # one remote query, retransmissions included
    task_s: float  # one task's coordination (TeamSpec.task_timeout_s)
    run_s: float  # the whole run, a hard stop on top of the team's own limits


#: What one task of one cluster asks a central server: about eleven answers
#: of a few hundred bytes (the three robots' queries, measured on the compact wire).
CENTRAL_BYTES_PER_CLUSTER_TASK = 3300


def timeouts_for(bandwidth_kbps: float, loss_pct: float, tasks_per_cluster: int,
                 central_clusters: int = 0) -> Timeouts:
    """Limits that only bind when something is wrong.

    Why these numbers: a remote query moves a few hundred bytes; at 35 kbit/s
    a 1 KB answer needs 0.25 s on each of two links, and a queue of nine
    robots' traffic at the central server can add seconds.  Each loss costs a
    retransmission timeout (CoAP: 0.5 s and up, backing off by 3x/2x; TCP:
    200 ms and up, doubling), and at 20 % loss three losses in a row on one
    exchange happen about once per 40 exchanges.  So the query limit grows
    with the serialisation time (``512/B``) and with the loss; the task limit
    covers the four queries of a task plus waiting for the teammates'
    decisions; the run limit covers every task of a cluster at a generous
    per-task pace.

    ``central_clusters``: the clusters sharing one central server (0 when
    distributed).  Its link carries every cluster's answers, all clusters
    deciding at once: a query may wait twice the time that link needs for one
    task of each, or the baseline fails only because it is slower.
    """
    slow = math.sqrt(512.0 / bandwidth_kbps)  # 1 at 512 kbit/s, 3.8 at 35 kbit/s
    lossy = 1.0 + loss_pct / 5.0  # 1.4 at 2 %, 5 at 20 %
    queue = 2 * central_clusters * CENTRAL_BYTES_PER_CLUSTER_TASK * 8 / (bandwidth_kbps * 1000)
    query = min(120.0, max(15.0, 6.0 * slow * lossy)) + queue
    task = 4.0 * query + 30.0
    run = 120.0 + tasks_per_cluster * (10.0 * slow * lossy + 10.0) + 2 * task
    return Timeouts(round(query, 1), round(task, 1), round(run, 1))


def system_spec(
    system: str,
    robots: int,
    *,
    timeouts: Timeouts | None = None,
    ontologies: Path = DEFAULT_ONTOLOGIES,
    link_kbps: float | None = None,
    replication: int = 1,
    faults: Sequence[Fault] = (),
    security: bool = True,
    log_dir: Path | None = None,
    kb_writable: bool = False,
    misplaced: Sequence[str] = (),
) -> TeamSpec:
    """The :class:`TeamSpec` of a named system (see :data:`SYSTEMS`), with the
    team's keys protecting it where its transport can (``security``)."""
    try:
        d = SYSTEMS[system]
    except KeyError:
        raise ValueError(f"unknown system {system!r} (choose from {', '.join(SYSTEMS)})") from None
    extra: dict[str, Any] = {}
    if timeouts is not None:
        extra = {"query_timeout_s": timeouts.query_s, "task_timeout_s": timeouts.task_s}
    # replication=1 by default: the benchmarks compare with the seed's system,
    # one KB module per robot (replicas change which queries are remote).
    return TeamSpec(
        robots=robots, mode=d.mode, transport=d.transport, query_wire=d.query_wire,
        ontologies=ontologies, link_kbps=link_kbps,
        replication=replication, faults=tuple(faults),
        security=_protected(d, security), log_dir=log_dir,
        kb_writable=kb_writable and d.mode == "distributed", misplaced=tuple(misplaced), **extra,
    )


def retransmission_label(system: str) -> str:
    """What the ``retransmission_profile`` column holds: ``robust`` (the CoAP
    reliability layer; older results also hold the retired CON profiles),
    ``tcp`` for ZeroMQ and Zenoh/TCP systems (TCP retransmits by itself),
    ``quic`` for Zenoh over QUIC and Zenoh's reliable UDP (QUIC's loss
    recovery, inside Zenoh).  Older results hold ``none`` for the
    ``zenoh-udp`` systems of before, on Zenoh's plain UDP link."""
    return _retransmission_label(SYSTEMS[system].transport)


def security_label(system: str, on: bool) -> str:
    """What the ``security`` column holds for ``system`` with security ``on``
    or off: the transport's scheme (``TeamSpec.security_scheme``) or ``none``."""
    return _security_label(SYSTEMS[system], on)


def _security_label(d: SystemDef, on: bool) -> str:
    return _mechanism(d, on) or "none"


def _protected(d: SystemDef, on: bool) -> bool:
    return _mechanism(d, on) is not None


def _mechanism(d: SystemDef, on: bool) -> str | None:
    """What protects system ``d``'s messages with security ``on``, or None."""
    # The seed's systems stay as the seed ran them, unprotected: they are the
    # baseline its claims are checked against (docs/benchmarks.md).
    transport = find(d.transport)  # None for an unknown system: reported as a failed row
    if not on or d.query_wire == "seed" or transport is None:
        return None
    return transport.security


def _retransmission_label(scheme: str) -> str:
    transport = find(scheme)
    if transport is None:  # an unknown system: reported as a failed row
        return ROBUST
    if transport.recovery is not None:
        return transport.recovery
    return "none" if transport.reliability is None else ROBUST


# --------------------------------------------------------------------------- placement


class NetnsPlacement(Placement):
    """Every process of the team in its own namespace of ``testbed``.

    The testbed's host names are the team's process names (``Robot1`` ..,
    ``central``); each binds its namespace address at the transport's usual
    port and is started with ``ip netns exec``."""

    def __init__(self, testbed: Testbed) -> None:
        super().__init__()
        self.testbed = testbed

    def endpoint(self, name: str, spec: TeamSpec) -> Endpoint:
        # Every host has its own namespace, so all can use the transport's usual port.
        return Endpoint(spec.transport, self.testbed.address(name), transport_for(spec.transport).default_port)

    def command(self, name: str, argv: list[str]) -> list[str]:
        return self.testbed.exec_args(name, argv)


# --------------------------------------------------------------------------- one run


class RunObserver(Protocol):
    """What a caller of :func:`run_once` is shown of a run, without changing it.

    Pass one as ``run_once(..., observer=...)``.  For a run whose team ran to
    the end, :meth:`team_recorded` is called once, in the benchmark's own
    process, after the team stopped and before ``run_once`` returns: the
    team's :class:`~coapkb.harness.record.TeamRecord` (every task's fate,
    each robot's statistics and retransmission counters) is what the CSV row
    only sums up.  A run that fails before its team has a record (bad
    configuration, no namespaces, a timeout, a crash) calls nothing; its row
    says why, as without an observer.

    ``experiments/byte_budget.py`` keeps the robots' per-peer reliability
    counters this way.  An observer should not raise: an exception from it
    ends the run as a failed row (``ok=False``, its message in ``error``).

    Example::

        class KeepRecords:
            def __init__(self) -> None:
                self.records: list[TeamRecord] = []

            def team_recorded(self, row: BenchRow, record: TeamRecord) -> None:
                self.records.append(record)

        keep = KeepRecords()
        row = await run_once("coap-distributed", 3, 10, 35, 2, observer=keep)
    """

    def team_recorded(self, row: BenchRow, record: TeamRecord) -> None:
        """The team's record of the run.  ``row`` is the run's row with what
        the record tells filled in (times, queries, task fates, ``ok`` and
        ``error``); the link counters' columns are not yet."""


async def _tcp_counters(testbed: Testbed, hosts: Iterable[str]) -> dict[str, dict[str, int]]:
    """The kernel's TCP counters of each host's namespace (``Tcp`` and
    ``TcpExt`` of ``/proc/net/snmp`` and ``/proc/net/netstat`` read inside
    it), by name."""

    async def one(host: str) -> tuple[str, dict[str, int]]:
        proc = await asyncio.create_subprocess_exec(
            *testbed.exec_args(host, ["cat", "/proc/net/snmp", "/proc/net/netstat"]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
        )
        out, _ = await proc.communicate()
        return host, proc_counters(out.decode(), ("Tcp", "TcpExt"))

    return dict(await asyncio.gather(*(one(h) for h in hosts)))


def proc_counters(text: str, groups: Iterable[str]) -> dict[str, int]:
    """Every counter of ``groups`` in ``/proc/net/snmp``-style text, by name."""
    found: dict[str, int] = {}
    for group in groups:
        lines = [line.split()[1:] for line in text.splitlines() if line.startswith(f"{group}:")]
        for names, values in zip(lines[::2], lines[1::2]):
            found.update((name, int(value)) for name, value in zip(names, values) if value.lstrip("-").isdigit())
    return found


def parse_proc_counter(text: str, group: str, name: str) -> int:
    """One counter from ``/proc/net/snmp``-style text (a header line of names
    and a line of values, both starting with ``group:``); 0 when absent."""
    lines = [line.split()[1:] for line in text.splitlines() if line.startswith(f"{group}:")]
    for names, values in zip(lines[::2], lines[1::2]):
        if name in names:
            return int(values[names.index(name)])
    return 0


def parse_retrans_segs(snmp: str) -> int:
    """``RetransSegs`` from the text of ``/proc/net/snmp`` (0 when absent)."""
    return parse_proc_counter(snmp, "Tcp", "RetransSegs")


def _base_row(system: str, robots: int, tasks: int, bandwidth_kbps: float, loss_pct: float, rep: int,
              seed: int, security: bool) -> BenchRow:
    d = SYSTEMS.get(system, SystemDef("", "", "", ""))  # unknown: reported by run_once as a failed row
    return BenchRow(
        security=_security_label(d, security),
        system=system, robots=robots, tasks=tasks, bandwidth_kbps=bandwidth_kbps, loss_pct=loss_pct, rep=rep,
        retransmission_profile=_retransmission_label(d.transport), ok=False,
        mode=d.mode, transport=d.transport, query_wire=d.query_wire, seed=seed, emulation="netns",
        started_at=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    )


def _sum_counters(readings: Mapping[str, LinkCounters]) -> LinkCounters:
    total = LinkCounters()
    for c in readings.values():
        total = LinkCounters(*(a + b for a, b in zip(vars(total).values(), vars(c).values())))
    return total


def _with_record(row: BenchRow, record: TeamRecord, tasks: int) -> tuple[BenchRow, int]:
    """``row`` with what the team's own record tells (times, queries, app
    bytes, agreement), and the CoAP retransmissions the transports counted
    (the ``retransmissions`` column of a CoAP run; TCP's come from the kernel)."""
    stats = record.robot_stats.values()
    latencies = [x for s in stats for x in s.queries.remote_latencies]
    p50, p99 = percentile(latencies, 50), percentile(latencies, 99)
    robots_traffic = sum((s.traffic for s in stats), TrafficCounters())
    problems = [f"task {t.cluster}.{t.seq} {t.object}: {t.errors or t.decisions}" for t in record.disputed]
    given = [t for t in record.tasks if t.reassigned_from is None]  # re-runs of a dead robot's tasks come on top
    if len(given) != tasks:
        problems.insert(0, f"{len(given)} of {tasks} tasks recorded")
    kills = [f.detected_after_s for f in record.faults if f.action == "kill"]
    detected = [s for s in kills if s is not None]  # the longest, or none if a kill went undetected
    fates = FateCounts.of(record.tasks)
    row = replace(
        row,
        coordination_s=record.coordination_s,
        completion_s=record.completion_s,
        query_p50_ms=None if p50 is None else round(p50 * 1000, 2),
        query_p99_ms=None if p99 is None else round(p99 * 1000, 2),
        remote_queries=sum(s.queries.remote for s in stats),
        pushed_answers=sum(s.queries.pushed for s in stats),
        local_queries=sum(s.queries.local for s in stats),
        failed_queries=sum(s.queries.failed for s in stats),
        app_bytes=record.feeder_traffic.bytes_sent + robots_traffic.bytes_sent,
        spurious_retransmissions=sum(s.spurious_retransmissions for s in stats),
        tasks_agreed=sum(1 for t in record.tasks if t.agreed),
        fault_detected_s=max(detected) if detected and len(detected) == len(kills) else None,
        tasks_reassigned=fates.reassigned,
        tasks_unavailable=fates.unavailable,
        tasks_assigned=fates.assigned,
        tasks_skipped=fates.skipped,
        tasks_unassigned=fates.unassigned,
        tasks_errors=fates.errors,
        tasks_disagreements=fates.disagreements,
        tasks_not_found=fates.not_found,
        unassigned_reason=fates.unassigned_reason or "",
        unassigned_reason_tasks=fates.unassigned_reason_tasks,
        ok=not problems,
        error="; ".join(problems)[:500],
    )
    return row, record.feeder_traffic.retransmissions + robots_traffic.retransmissions


@contextlib.contextmanager
def _logged_to(log_dir: Path | None) -> Iterator[None]:
    """This process's coapkb log (the feeder's side) at INFO level in
    ``log_dir/feeder.log`` while the team runs, as the robots' are."""
    if log_dir is None:
        yield
        return
    log_dir.mkdir(parents=True, exist_ok=True)
    logger = logging.getLogger("coapkb")
    to_file = logging.FileHandler(log_dir / f"{FEEDER}.log", encoding="utf-8")
    to_file.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
    to_screen = logging.StreamHandler()  # what the screen showed before: warnings and errors
    to_screen.setLevel(logging.WARNING)
    saved = logger.level, logger.propagate
    logger.addHandler(to_file)
    logger.addHandler(to_screen)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield
    finally:
        for handler in (to_file, to_screen):
            logger.removeHandler(handler)
            handler.close()
        logger.level, logger.propagate = saved


def _run_name(row: BenchRow) -> str:
    """A run's folder name under ``--trace``: its system, cell and repetition."""
    return (f"{row.system}-{row.robots}r{row.tasks}t-{row.bandwidth_kbps:g}k-{row.loss_pct:g}pct"
            f"-{row.security}-rep{row.rep}")


async def run_once(
    system: str,
    robots: int,
    tasks: int,
    bandwidth_kbps: float,
    loss_pct: float,
    rep: int = 0,
    seed: int | None = None,
    *,
    ontologies: Path = DEFAULT_ONTOLOGIES,
    timeouts: Timeouts | None = None,
    delay_ms: float = 0.0,
    jitter_ms: float = 0.0,
    loss_model: str = "random",
    burst_len: float = 3.0,
    replication: int = 1,
    faults: Sequence[Fault] = (),
    security: bool = True,
    trace_dir: Path | None = None,
    kb_writable: bool = False,
    misplaced: Sequence[str] = (),
    task_list: Sequence[str] | None = None,
    observer: RunObserver | None = None,
    testbed_class: type[Testbed] = Testbed,
) -> BenchRow:
    """Run ``system`` once and return its row.

    The task list is ``draw_tasks(tasks, seed=seed)`` with ``seed`` defaulting
    to ``1 + rep``, so every system of a repetition does the same tasks.
    Never raises for a failed run: a timeout, a crash or an emulator failure
    gives ``ok=False`` and the reason in ``error``, so a sweep goes on.
    ``delay_ms``, ``jitter_ms``, ``loss_model`` and ``burst_len`` go into the
    robots' and the central's :class:`LinkSpec` (one-way, per sending host).
    ``faults`` kill robots during the run (``coapkb bench --fail``), usually
    with ``replication`` 2 so their KB modules live on.  ``security``: the
    team's keys protect every process's messages (OSCORE, CurveZMQ), as in
    ``coapkb team``; off only for comparison.  ``trace_dir``: keep the run's
    traces there, in a folder named after the run: each process's log at
    INFO level and the team's record (``record.json``).  ``kb_writable``:
    the robots write their picks into the KB (distributed systems only);
    ``misplaced``: objects not where the KB says; ``task_list``: these
    ``tasks`` objects instead of a draw.

    ``observer`` is shown the team's record of the run (:class:`RunObserver`).
    ``testbed_class`` builds the run's testbed, as
    ``testbed_class(hosts, links)``: :class:`~coapkb.bench.linkemu.Testbed`
    by default; a subclass may add to it (``experiments/byte_budget.py``
    starts a packet capture in its bridge namespace and keeps the times of
    its counter readings) but must keep what the run reads: the hosts'
    addresses, namespaces, ``exec_args`` and ``acounters``.  Neither changes
    the row.
    """
    seed = 1 + rep if seed is None else seed
    row = _base_row(system, robots, tasks, bandwidth_kbps, loss_pct, rep, seed, security)
    # burst_len means nothing for independent loss: 0 there, so it does not split the resume key.
    row = replace(row, delay_ms=delay_ms, jitter_ms=jitter_ms, loss_model=loss_model,
                  burst_len=burst_len if loss_model == "burst" else 0.0, replication=replication,
                  kb_writable=kb_writable and system in SYSTEMS and SYSTEMS[system].mode == "distributed",
                  faults="+".join(f"{f.robot}@{f.at_s:g}" for f in faults))
    started = time.monotonic()
    try:
        plan = _plan_run(row, seed, burst_len, ontologies=ontologies, timeouts=timeouts, faults=faults, security=security,
                         trace_dir=trace_dir, kb_writable=kb_writable, misplaced=misplaced, task_list=task_list)
    except (ValueError, TeamError) as exc:
        return replace(row, error=f"bad configuration: {exc}")
    row = replace(row, query_timeout_s=plan.limits.query_s, task_timeout_s=plan.limits.task_s)
    row = await _run_on_testbed(row, plan, observer, testbed_class)
    return replace(row, wall_s=round(time.monotonic() - started, 2))


@dataclass(frozen=True)
class _RunPlan:
    """What one run is, once its arguments are checked."""

    spec: TeamSpec
    task_list: list[str]
    #: The robots' and the central's link (the feeder's is unshaped).
    link: LinkSpec
    limits: Timeouts


def _plan_run(
    row: BenchRow,
    seed: int,
    burst_len: float,
    *,
    ontologies: Path,
    timeouts: Timeouts | None,
    faults: Sequence[Fault],
    security: bool,
    trace_dir: Path | None,
    kb_writable: bool,
    misplaced: Sequence[str],
    task_list: Sequence[str] | None,
) -> _RunPlan:
    """The team, task list, link and limits of ``row``'s run (``run_once``'s
    arguments); a ValueError or a TeamError for a bad configuration."""
    system, robots, tasks = row.system, row.robots, row.tasks
    link = LinkSpec(rate_kbit=row.bandwidth_kbps, loss_pct=row.loss_pct, delay_ms=row.delay_ms,
                    jitter_ms=row.jitter_ms, loss_model=row.loss_model, burst_len=burst_len)
    clusters = robots // CLUSTER_SIZE
    central = clusters if system in SYSTEMS and SYSTEMS[system].mode == "central" else 0
    limits = timeouts or timeouts_for(row.bandwidth_kbps, row.loss_pct, math.ceil(tasks / clusters), central)
    # Robots know their radio's rate, as a real radio reports it.
    run_dir = None if trace_dir is None else trace_dir / _run_name(row)
    spec = system_spec(system, robots, timeouts=limits, ontologies=ontologies,
                       link_kbps=row.bandwidth_kbps, replication=row.replication, faults=faults, security=security,
                       log_dir=run_dir, kb_writable=kb_writable, misplaced=misplaced)
    drawn = draw_tasks(tasks, ontologies, seed=seed) if task_list is None else list(task_list)
    if len(drawn) != tasks:
        raise ValueError(f"{len(drawn)} objects listed for {tasks} tasks")
    return _RunPlan(spec, drawn, link, limits)


async def _run_on_testbed(row: BenchRow, plan: _RunPlan, observer: RunObserver | None,
                          testbed_class: type[Testbed]) -> BenchRow:
    """``row`` with what the run measured on a testbed of its own, or with
    why it failed (never raises, so a sweep goes on)."""
    spec = plan.spec
    hosts = [*spec.robot_ids, *([CENTRAL] if spec.mode == "central" else []), FEEDER]
    links = {h: plan.link for h in hosts}
    links[FEEDER] = LinkSpec()  # the external task source: unshaped, lossless
    try:
        async with asyncio.timeout(plan.limits.run_s):
            async with testbed_class(hosts, links) as testbed:
                row = await _measure(testbed, row, spec, plan.task_list, hosts, observer)
    except TimeoutError:
        row = replace(row, error=f"run did not finish within {plan.limits.run_s:g} s")
    except (CoapkbError, OSError) as exc:  # the team's, the transport's or the emulator's own failure
        row = replace(row, error=f"{type(exc).__name__}: {exc}"[:500])
    except Exception as exc:
        log.error("%s failed unexpectedly", row.system, exc_info=True)  # a bug: its traceback helps
        row = replace(row, error=f"unexpected {type(exc).__name__}: {exc}"[:500])
    return row


async def _measure(testbed: Testbed, row: BenchRow, spec: TeamSpec, task_list: list[str], hosts: list[str],
                   observer: RunObserver | None = None) -> BenchRow:
    """``row`` with what one team run measured: link counters and the team's record."""
    # The kernel's retransmissions (RetransSegs) count only TCP's; QUIC's are Zenoh's business.
    tcp = transport_for(spec.transport).recovery == "tcp"

    async def reading() -> dict[str, Any]:
        counters = await testbed.acounters()
        retrans = await _tcp_counters(testbed, hosts) if tcp else {}
        return {"counters": counters, "tcp": retrans}

    end: dict[str, Any] = {}

    async def read_end() -> None:
        # Before the feeder downloads the robots' statistics (a few KB at 80
        # tasks), so that download is not charged to the system.
        end.update(await reading())

    recorder = None
    if spec.log_dir is not None:
        # The trace keeps the run for Foxglove too (the recording's module
        # is imported only here: a run without a trace never loads it).
        from ..harness.recording import RunRecorder, run_metadata, warehouse

        spec.log_dir.mkdir(parents=True, exist_ok=True)
        layout, docks = warehouse(spec.ontologies)
        recorder = RunRecorder(spec.log_dir / "run.mcap", None, spec.robot_ids, layout, docks, metadata=run_metadata(
            ["coapkb", "bench"], **{k: v for k, v in row.to_dict().items() if v not in (None, "")}))
    try:
        async with Team.launch(spec, NetnsPlacement(testbed)) as team:
            before = await reading()
            # The feeder's client transport is opened inside Team.run, so its
            # sockets (and a ZeroMQ context's I/O threads) belong to the feeder's
            # namespace; the robots' addresses are reachable only from there.
            with enter_netns(testbed[FEEDER].netns), _logged_to(spec.log_dir):
                record = await team.run(task_list, None if recorder is None else recorder.task, finished=read_end,
                                        on_state=None if recorder is None else recorder.robot_state)
            after = end or await reading()
        if recorder is not None:
            recorder.finished(record)
    finally:
        if recorder is not None:
            recorder.close()
    delta = {h: after["counters"][h] - before["counters"][h] for h in hosts}
    total = _sum_counters(delta)
    row, coap_retx = _with_record(row, record, row.tasks)
    if observer is not None:
        observer.team_recorded(row, record)
    if spec.log_dir is not None:
        (spec.log_dir / "record.json").write_text(json.dumps(record.to_dict(), indent=1) + "\n", encoding="utf-8")
    if tcp:
        kernel = {h: {name: n - before["tcp"][h].get(name, 0) for name, n in after["tcp"][h].items()} for h in hosts}
        retransmissions = sum(k.get("RetransSegs", 0) for k in kernel.values())
        tcp_aborts: int | None = sum(k.get("TCPAbortOnTimeout", 0) for k in kernel.values())
        if spec.log_dir is not None:  # what TCP did on each host, for a trace
            changed = {h: {name: n for name, n in k.items() if n} for h, k in kernel.items()}
            (spec.log_dir / "tcp_counters.json").write_text(json.dumps(changed, indent=1) + "\n", encoding="utf-8")
    else:
        retransmissions, tcp_aborts = coap_retx, None
    return replace(
        row, wire_bytes=total.tx_bytes, wire_packets=total.tx_packets, dropped_packets=total.dropped,
        queue_drops=total.queue_drops, feeder_wire_bytes=delta[FEEDER].tx_bytes,
        retransmissions=retransmissions, tcp_aborts=tcp_aborts,
        central_wire_bytes=delta[CENTRAL].tx_bytes if CENTRAL in delta else None,
        robot_wire_bytes_max=max(delta[r].tx_bytes for r in spec.robot_ids),
    )


# --------------------------------------------------------------------------- command line


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``coapkb bench`` options (also used by ``experiments/sweep.py``)."""
    p.add_argument("--robots", type=int, required=True, help="team size, a multiple of 3")
    p.add_argument("--tasks", type=int, required=True, help="number of picking tasks")
    p.add_argument("--bandwidth", type=float, required=True, metavar="KBPS", help="link rate, kbit/s")
    p.add_argument("--loss", type=float, required=True, metavar="PCT", help="packet loss, percent")
    p.add_argument("--delay", type=float, default=0.0, metavar="MS",
                   help="one-way delay per sending host, ms (RTT between two hosts: twice this)")
    p.add_argument("--jitter", type=float, default=0.0, metavar="MS",
                   help="uniform +- jitter on each packet's delay, ms (at most --delay; no reordering)")
    p.add_argument("--loss-model", choices=("random", "burst"), default="random",
                   help="random: independent per packet; burst: Gilbert bursts of mean --burst-len")
    p.add_argument("--burst-len", type=float, default=3.0, metavar="PKTS",
                   help="mean run of consecutive losses for --loss-model burst (default 3)")
    p.add_argument("--systems", default="coap-distributed,coap-central,zmq-distributed,zmq-central",
                   help=f"comma-separated, from: {', '.join(SYSTEMS)}")
    p.add_argument("--reps", type=int, default=1, help="repetitions (rep numbers first-rep .. first-rep+reps-1)")
    p.add_argument("--first-rep", type=int, default=0, help="number of the first repetition")
    p.add_argument("--seed", type=int, default=None, help="task-list seed (default: 1 + rep)")
    p.add_argument("--replication", type=int, default=1, metavar="R",
                   help="robots of a cluster holding each KB module (default 1, as the seed; 2 with --fail)")
    p.add_argument("--fail", action="append", default=[], metavar="ROBOT@SECONDS",
                   help="kill ROBOT (SIGKILL) this many seconds into the run; repeatable")
    p.add_argument("--insecure", action="store_true",
                   help="no OSCORE, CurveZMQ or TLS, for comparison (default: the team's keys protect every message, "
                        "as in coapkb team)")
    p.add_argument("--writable", action="store_true",
                   help="the robots' KBs take writes and the robots write every pick (distributed systems); "
                        "default: read-only, unlike coapkb team: the paper's workflow, as every committed "
                        "benchmark figure was measured")
    p.add_argument("--misplace", action="append", default=[], metavar="OBJECT",
                   help="the object is not where the KB says (repeatable)")
    p.add_argument("--out", metavar="F.csv", help="append one row per run (header if new)")
    p.add_argument("--trace", metavar="DIR", type=Path,
                   help="keep each run's process logs (INFO level), team record and recording (run.mcap, "
                        "for Foxglove) in DIR/<run>/")
    p.add_argument("--json", action="store_true", help="print each row as one JSON line on stdout")


def _check_out(out: Path) -> None:
    """``--out``, before any run: a CSV file in a folder that is one (made if missing)."""
    taken = next((p for p in out.parents if p.exists()), None)
    if taken is not None and not taken.is_dir():
        raise ValueError(f"--out {out}: {taken} is not a folder")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot make its folder: {exc.strerror}") from None
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder: give the CSV file's name")


def parse_systems(text: str) -> list[str]:
    systems = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in systems if s not in SYSTEMS]
    if unknown or not systems:
        raise ValueError(f"unknown system(s) {', '.join(unknown) or '(none given)'}; choose from {', '.join(SYSTEMS)}")
    return systems


async def main(args: argparse.Namespace) -> int:
    """``coapkb bench``: exit 0 if every run was ok, 1 if one failed, 2 if none could start."""
    systems = parse_systems(args.systems)
    if args.robots < CLUSTER_SIZE or args.robots % CLUSTER_SIZE:
        raise ValueError(f"--robots must be a multiple of {CLUSTER_SIZE}, got {args.robots}")
    if args.tasks < 1 or args.reps < 1:
        raise ValueError("--tasks and --reps must be at least 1")
    if not args.bandwidth > 0:
        raise ValueError(f"--bandwidth must be positive (kbit/s), got {args.bandwidth:g}")
    link = {"delay_ms": args.delay, "jitter_ms": args.jitter, "loss_model": args.loss_model,
            "burst_len": args.burst_len}
    # --fail names the option; a kill is what the team carries out.
    faults = [Fault("kill", f.robot, f.at_s) for f in (Fault.parse("fail", text) for text in args.fail)]
    # The team's own checks (robots named, replication), before any run starts.
    TeamSpec(robots=args.robots, replication=args.replication, faults=tuple(faults))
    LinkSpec(rate_kbit=args.bandwidth, loss_pct=args.loss, **link)  # validates, raises ValueError
    if args.out:
        _check_out(Path(args.out))
    ok, why = available()
    if not ok:
        print(f"coapkb bench: no kernel link emulation here: {why}", file=sys.stderr)
        return 2
    cleanup_stale()
    failed = 0
    for rep in range(args.first_rep, args.first_rep + args.reps):
        for system in systems:
            row = await run_once(system, args.robots, args.tasks, args.bandwidth, args.loss, rep,
                                 args.seed, replication=args.replication, faults=faults,
                                 security=not args.insecure, trace_dir=args.trace,
                                 kb_writable=args.writable, misplaced=args.misplace, **link)
            if args.out:
                append_rows(args.out, [row])
            if args.json:
                print(json.dumps(row.to_dict()), flush=True)
            else:
                print(format_row(row), flush=True)
            failed += not row.ok
    return 1 if failed else 0


if __name__ == "__main__":  # pragma: no cover - `coapkb bench` is the entry point
    parser = argparse.ArgumentParser(prog="coapkb bench")
    add_arguments(parser)
    sys.exit(asyncio.run(main(parser.parse_args())))
