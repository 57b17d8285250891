"""Confirmable retransmission on slow, lossy links: the three profiles of
:data:`coapkb.transport.coap.reliability.rto.PROFILES`, measured on kernel-emulated links.

Two levels (see ``docs/retransmission.md``, "Measured on emulated links"):

**Query level.**  One :class:`coapkb.bench.linkemu.Testbed` per link setting.  For
every profile it has ``--streams`` independent pairs of hosts
(``s-<profile>-<i>`` runs ``coapkb serve`` with the three warehouse KBs,
``c-<profile>-<i>`` is a client), each host behind its own shaped, lossy
link, so the pairs never share a queue.  All profiles run at the same time,
in the same conditions.  Each client (in this process, its sockets opened in
its namespace with :func:`coapkb.bench.linkemu.enter_netns`) sends a warm-up and
then ``--queries`` sequential named queries, a seeded mix of the seed's four
(the same list for every profile).  Recorded per query: latency and outcome;
per stream: the client's :class:`RetransmissionController` counters
(retransmissions, spurious retransmissions, samples) and the link counters
of both hosts (wire bytes and datagrams, including the ones the loss rule
dropped).

**Team level.**  :func:`coapkb.bench.run.run_once` with ``coap-distributed``,
3 robots and ``--team-tasks`` tasks, once per profile, with one task list.

Outputs (in ``--out``, default ``experiments/results/retransmission/``):
``queries.csv`` (every query), ``query_summary.csv`` (one row per link
setting and profile), ``model.csv`` (the same percentiles from a Monte
Carlo model of the profiles, see :func:`simulate`), ``team.csv`` (bench
rows), ``table.md`` and ``retransmission.png``.

    sudo .venv/bin/python experiments/retransmission.py            # the full run (~25 min)
    .venv/bin/python experiments/retransmission.py --report-only   # tables and figure from the CSVs

Needs root (network namespaces, tbf, nftables).
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import random
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
for _path in (ROOT, ROOT / "experiments"):  # the package, and the experiments' shared helpers
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

from coapkb.bench.row import BenchRow
from coapkb.bench.stats import percentile
from common import prepare_link_emulation, GRIPS, QUERY_MIX, query_plan, start_kb_server, stop_processes  # noqa: F401 (re-exported)
from coapkb.transport.coap.reliability.rto import (
    PROFILES,
    SampleKind,
    TransmissionProfile,
    attribute_reply,
    get_profile,
)

DEFAULT_OUT = ROOT / "experiments" / "results" / "retransmission"
PROFILE_NAMES: tuple[str, ...] = ("rfc7252", "lossy-fixed", "adaptive")
#: Query-level variants of ``adaptive`` besides the named profiles.
VARIANTS: dict[str, str] = {
    "adaptive-uncapped": "adaptive without the 8 s backoff cap (AdaptiveProfile(backoff_cap=None)): plain CoCoA backoff",
    "adaptive+rate": "adaptive told the link rate (AdaptiveProfile.with_link_rate): size normalisation on",
}
ALL_PROFILES: tuple[str, ...] = (*PROFILE_NAMES, *VARIANTS)
_HOST_TAGS = {"rfc7252": "rfc", "lossy-fixed": "lossy", "adaptive": "adapt", "adaptive-uncapped": "uncap",
              "adaptive+rate": "rate"}
COLOURS = {"rfc7252": "tab:red", "lossy-fixed": "tab:blue", "adaptive": "tab:green",
           "adaptive-uncapped": "tab:olive", "adaptive+rate": "tab:purple"}
ONTOLOGIES = ROOT / "ontologies"
COAP_PORT = 5683
#: The three aims of the issue, as numbers.
AIM_TAIL_FACTOR = 3.0  # adaptive p99 at the highest loss <= 3 x its p50 at the lowest loss
AIM_SPURIOUS_SHARE = 0.05  # spurious retransmissions < 5 % of datagrams at the lowest loss

QUERY_COLUMNS = ("bandwidth_kbps", "loss_pct", "profile", "stream", "seq", "query", "ok", "latency_s", "error")
SUMMARY_COLUMNS = (
    "bandwidth_kbps", "loss_pct", "profile", "queries", "failed",
    "p50_ms", "p95_ms", "p99_ms", "max_ms", "mean_ms",
    "exchanges", "transmissions", "retransmissions", "spurious_retransmissions", "duplicate_replies",
    "samples_strong", "samples_weak", "samples_discarded", "reattributed_strong",
    "wire_datagrams", "wire_bytes", "dropped", "queue_drops",
    "retransmissions_per_query", "wire_bytes_per_query", "spurious_share_datagrams", "spurious_share_con",
    "excess_retransmissions_bound", "final_rto_s", "srtt_ms", "min_rtt_ms",
    "t0_p50_ms", "t0_p90_ms", "t0_max_ms", "t0_share_over_1s", "wall_s",
)
MODEL_COLUMNS = ("bandwidth_kbps", "loss_pct", "profile", "rtt_ms", "samples", "failed",
                 "p50_ms", "p95_ms", "p99_ms", "retransmissions_per_query", "spurious_per_query")
TEAM_COLUMNS = (
    "bandwidth_kbps", "loss_pct", "retransmission_profile", "ok", "coordination_s", "completion_s",
    "query_p50_ms", "query_p99_ms", "remote_queries", "failed_queries", "tasks", "tasks_agreed",
    "wire_bytes", "wire_packets", "dropped_packets", "queue_drops", "retransmissions",
    "spurious_retransmissions", "spurious_share", "wall_s", "error",
)


# --------------------------------------------------------------------------- pure helpers


def parse_list(text: str, kind: type = float) -> list[Any]:
    """``"35,256"`` -> ``[35.0, 256.0]``."""
    items = [kind(x) for x in text.split(",") if x.strip()]
    if not items:
        raise ValueError(f"empty list {text!r}")
    return items


def profile_for(name: str, bandwidth_kbps: float) -> TransmissionProfile:
    """A profile of :data:`coapkb.transport.coap.reliability.rto.PROFILES` or one of :data:`VARIANTS`."""
    from dataclasses import replace

    if name in PROFILES:
        return PROFILES[name]
    adaptive = PROFILES["adaptive"]
    if name == "adaptive-uncapped":
        return replace(adaptive, backoff_cap=None)
    if name == "adaptive+rate":
        return adaptive.with_link_rate(bandwidth_kbps * 1000)  # type: ignore[attr-defined]
    raise ValueError(f"unknown profile {name!r} (choose from {', '.join(ALL_PROFILES)})")


#: PeerStats fields summed over streams (and diffed over the measured window).
STAT_FIELDS = ("exchanges", "transmissions", "retransmissions", "spurious_retransmissions", "duplicate_replies",
               "samples_strong", "samples_weak", "samples_discarded", "reattributed_strong", "failed")


def stats_delta(after: Mapping[str, Any], before: Mapping[str, Any] | None) -> dict[str, int]:
    """Counter fields of two :class:`PeerStats` dicts, ``after - before``."""
    before = before or {}
    return {k: int(after.get(k) or 0) - int(before.get(k) or 0) for k in STAT_FIELDS}


def summarise(
    bandwidth_kbps: float,
    loss_pct: float,
    profile: str,
    queries: Sequence[Mapping[str, Any]],
    streams: Sequence[Mapping[str, Any]],
) -> dict[str, Any]:
    """One ``query_summary.csv`` row from the per-query records of a cell and
    profile and its per-stream measurements (``stats``: controller counter
    delta, ``link``: tx_packets/tx_bytes/dropped/queue_drops summed over the
    stream's two hosts, ``rto``/``srtt``/``min_rtt``: the estimator at the end).

    Failed queries enter the percentiles with the time the client waited
    before it gave up: a lower bound on their latency, so a profile that
    gives up early is not rewarded with a short tail."""
    lat = [float(q["latency_s"]) for q in queries]
    total = {k: sum(int(s["stats"].get(k, 0)) for s in streams) for k in STAT_FIELDS}
    link = {k: sum(int(s["link"].get(k, 0)) for s in streams) for k in ("tx_packets", "tx_bytes", "dropped", "queue_drops")}
    n = len(queries)

    def ms(v: float | None) -> float | str:
        return "" if v is None else round(v * 1000, 1)

    def mean(values: Iterable[float | None]) -> float | None:
        vals = [v for v in values if v is not None]
        return sum(vals) / len(vals) if vals else None

    srtt, min_rtt = mean(s.get("srtt") for s in streams), mean(s.get("min_rtt") for s in streams)
    t0 = [float(x) for s in streams for x in s.get("initial_timeouts") or ()]
    rto = mean(s.get("rto") for s in streams)
    return {
        "bandwidth_kbps": bandwidth_kbps,
        "loss_pct": loss_pct,
        "profile": profile,
        "queries": n,
        "failed": sum(1 for q in queries if not _truthy(q["ok"])),
        "p50_ms": ms(percentile(lat, 50)),
        "p95_ms": ms(percentile(lat, 95)),
        "p99_ms": ms(percentile(lat, 99)),
        "max_ms": ms(max(lat) if lat else None),
        "mean_ms": ms(sum(lat) / n if n else None),
        **{k: total[k] for k in STAT_FIELDS if k != "failed"},
        "wire_datagrams": link["tx_packets"],
        "wire_bytes": link["tx_bytes"],
        "dropped": link["dropped"],
        "queue_drops": link["queue_drops"],
        "retransmissions_per_query": round(total["retransmissions"] / n, 3) if n else "",
        "wire_bytes_per_query": round(link["tx_bytes"] / n, 1) if n else "",
        "spurious_share_datagrams": round(total["spurious_retransmissions"] / link["tx_packets"], 4)
        if link["tx_packets"] else "",
        "spurious_share_con": round(total["spurious_retransmissions"] / total["transmissions"], 4)
        if total["transmissions"] else "",
        # A needed retransmission needs a lost datagram (the request or its
        # reply), so retransmissions beyond the drops were needless whatever
        # the controller's detectors saw: a ground-truth lower bound.
        "excess_retransmissions_bound": max(0, total["retransmissions"] - link["dropped"]),
        "final_rto_s": "" if rto is None else round(rto, 3),
        "srtt_ms": ms(srtt),
        "min_rtt_ms": ms(min_rtt),
        # The initial timeouts the profile drew for the measured exchanges:
        # how far weak samples pushed an adaptive RTO above the path's RTT.
        "t0_p50_ms": ms(percentile(t0, 50)),
        "t0_p90_ms": ms(percentile(t0, 90)),
        "t0_max_ms": ms(max(t0) if t0 else None),
        "t0_share_over_1s": round(sum(1 for x in t0 if x >= 1.0) / len(t0), 3) if t0 else "",
        "wall_s": round(max((float(s.get("wall_s", 0)) for s in streams), default=0.0), 1),
    }


def _truthy(v: Any) -> bool:
    return v is True or str(v).strip().lower() in ("true", "1", "yes")


def team_excess_bound(row: Mapping[str, Any]) -> int:
    """Retransmissions that no lost datagram can explain (retransmissions
    minus datagrams the loss rule dropped): a lower bound on the truly
    spurious ones, independent of the controller's detectors."""
    try:
        return max(0, int(row.get("retransmissions") or 0) - int(row.get("dropped_packets") or 0))
    except (TypeError, ValueError):
        return 0


def team_row(row: BenchRow) -> dict[str, Any]:
    """The columns of a :func:`coapkb.bench.run.run_once` row this experiment reports."""
    out: dict[str, Any] = {k: v for k, v in row.to_dict().items() if k in TEAM_COLUMNS}
    packets, spurious = row.wire_packets, row.spurious_retransmissions
    out["spurious_share"] = round(spurious / packets, 4) if packets and spurious is not None else ""
    return {k: ("" if out.get(k) is None else out.get(k, "")) for k in TEAM_COLUMNS}


# --------------------------------------------------------------------------- model


@dataclass(frozen=True)
class SimResult:
    latencies: list[float]
    failed: int
    retransmissions: int
    spurious: int


def simulate(
    profile: str | TransmissionProfile,
    loss_pct: float,
    rtt_s: float,
    n: int = 20_000,
    seed: int = 1,
    gap_s: float = 0.0,
    warmup: int = 5,
    wire_bytes: tuple[int, int] = (1216, 300),
) -> SimResult:
    """Monte Carlo model of ``n`` sequential single-exchange queries, using the
    profile's own schedule and estimator code (:mod:`coapkb.transport.coap.reliability.rto`).

    Each transmission reaches the server and its reply comes back with
    probability ``(1 - loss)²`` (the testbed drops each datagram with
    ``loss`` on its sender's link), after a constant ``rtt_s``.  The client
    retransmits on the schedule until the first reply arrives, so a copy sent
    after a surviving earlier copy's reply was due is spurious; its RTT
    sample is classified and, as the controller does, re-attributed with
    :func:`coapkb.transport.coap.reliability.rto.attribute_reply`.  It models the link's loss and the
    timers, nothing else (no queueing, no processing jitter), so it gives
    the percentiles a run of ``n`` queries would converge to, which 100
    measured queries cannot pin down at p99.  ``wire_bytes`` (what the
    controller assumes for a new exchange, what a sample really carried)
    only matters to a profile told the link rate."""
    prof = get_profile(profile)
    rng, loss_rng = random.Random(seed), random.Random(seed + 1_000_003)
    success = (1 - loss_pct / 100.0) ** 2
    rto = prof.new_rto()
    now = 0.0
    latencies: list[float] = []
    failed = retransmissions = spurious = 0
    for i in range(n + warmup):
        schedule = prof.schedule(rng, rto, now, wire_bytes=wire_bytes[0])
        offsets = schedule.transmit_offsets
        # The first copy that gets through answers first (constant RTT);
        # copies keep going out on the schedule until its reply arrives.
        reply_at = first_ok = None
        for offset in offsets:
            if reply_at is not None and offset >= reply_at:
                break
            if first_ok is None and loss_rng.random() < success:
                first_ok, reply_at = offset, offset + rtt_s
        if reply_at is None:
            sent = len(offsets)
            elapsed = schedule.total_wait
        else:
            sent = sum(1 for o in offsets if o < reply_at)
            elapsed = reply_at
            times = [now + o for o in offsets[:sent]]
            min_rtt = rto.min_rtt if rto.strong.samples >= 3 else None
            index = attribute_reply(times, now + reply_at, min_rtt)
            kind = SampleKind.STRONG if index == 0 and sent > 1 else None
            rto.on_sample(reply_at, sent - 1, now + reply_at, wire_bytes=wire_bytes[1], kind=kind)
        if i >= warmup:
            latencies.append(elapsed)
            retransmissions += sent - 1
            if reply_at is None:
                failed += 1
            else:
                spurious += sum(1 for o in offsets[:sent] if o > first_ok)  # type: ignore[operator]
        now += elapsed + gap_s
    return SimResult(latencies, failed, retransmissions, spurious)


def model_rows(summary: Sequence[Mapping[str, Any]], n: int = 20_000, seed: int = 1) -> list[dict[str, Any]]:
    """One model row per measured (link, profile): the simulation with that
    cell's measured base RTT (the p50 at the lowest loss on the link, which is
    a loss-free exchange)."""
    base: dict[float, float] = {}
    for r in sorted(summary, key=lambda r: float(r["loss_pct"])):
        bw = float(r["bandwidth_kbps"])
        if bw not in base and r.get("p50_ms") not in (None, ""):
            base[bw] = float(r["p50_ms"]) / 1000
    rows = []
    for r in summary:
        bw, loss, profile = float(r["bandwidth_kbps"]), float(r["loss_pct"]), str(r["profile"])
        if bw not in base:
            continue
        sim = simulate(profile_for(profile, bw), loss, base[bw], n=n, seed=seed)
        rows.append({
            "bandwidth_kbps": bw, "loss_pct": loss, "profile": profile, "rtt_ms": round(base[bw] * 1000, 1),
            "samples": n, "failed": sim.failed,
            "p50_ms": round(percentile(sim.latencies, 50) * 1000, 1),  # type: ignore[operator]
            "p95_ms": round(percentile(sim.latencies, 95) * 1000, 1),  # type: ignore[operator]
            "p99_ms": round(percentile(sim.latencies, 99) * 1000, 1),  # type: ignore[operator]
            "retransmissions_per_query": round(sim.retransmissions / n, 3),
            "spurious_per_query": round(sim.spurious / n, 4),
        })
    return rows


# --------------------------------------------------------------------------- aims and tables


def _f(v: Any) -> float | None:
    return None if v in (None, "") else float(v)


def evaluate_aims(summary: Sequence[Mapping[str, Any]], team: Sequence[Mapping[str, Any]] = ()) -> list[dict[str, Any]]:
    """The issue's three aims, per bandwidth, from the query-level summary
    (and the team level for the bytes of aim 3 where available)."""
    out: list[dict[str, Any]] = []
    by = {(float(r["bandwidth_kbps"]), float(r["loss_pct"]), str(r["profile"])): r for r in summary}
    for bw in sorted({k[0] for k in by}):
        losses = sorted({k[1] for k in by if k[0] == bw})
        lo, hi = losses[0], losses[-1]
        a_lo, a_hi = by.get((bw, lo, "adaptive")), by.get((bw, hi, "adaptive"))
        if a_lo and a_hi and _f(a_lo["p50_ms"]) and _f(a_hi["p99_ms"]):
            limit = AIM_TAIL_FACTOR * _f(a_lo["p50_ms"])  # type: ignore[operator]
            value = _f(a_hi["p99_ms"])
            out.append({"aim": 1, "bandwidth_kbps": bw, "what": f"adaptive p99 @{hi:g}% <= 3 x p50 @{lo:g}%",
                        "value": f"{value:.0f} ms vs limit {limit:.0f} ms", "met": value <= limit})  # type: ignore[operator]
        for p in ALL_PROFILES:
            r = by.get((bw, lo, p))
            if r and r.get("spurious_share_datagrams") not in (None, ""):
                share = float(r["spurious_share_datagrams"])
                out.append({"aim": 2, "bandwidth_kbps": bw, "what": f"{p}: spurious share @{lo:g}% < 5 %",
                            "value": f"{100 * share:.2f} %", "met": share < AIM_SPURIOUS_SHARE})
        for loss in losses:
            a, r = by.get((bw, loss, "adaptive")), by.get((bw, loss, "rfc7252"))
            if not (a and r):
                continue
            tail = _f(a["p99_ms"]) < _f(r["p99_ms"])  # type: ignore[operator]
            bytes_ok = _f(a["wire_bytes_per_query"]) <= 1.05 * _f(r["wire_bytes_per_query"])  # type: ignore[operator]
            out.append({"aim": 3, "bandwidth_kbps": bw,
                        "what": f"adaptive vs rfc7252 @{loss:g}%: lower p99, bytes/query within 5 %",
                        "value": f"p99 {a['p99_ms']} vs {r['p99_ms']} ms; "
                                 f"{a['wire_bytes_per_query']} vs {r['wire_bytes_per_query']} B/query",
                        "met": tail and bytes_ok})
    by_team = {(float(r["bandwidth_kbps"]), float(r["loss_pct"]), str(r["retransmission_profile"])): r for r in team}
    for bw in sorted({k[0] for k in by_team}):
        lo = min(k[1] for k in by_team if k[0] == bw)
        for p in PROFILE_NAMES:
            r = by_team.get((bw, lo, p))
            if not r or r.get("wire_packets") in (None, "", "0", 0):
                continue
            worst = max(int(r.get("spurious_retransmissions") or 0), team_excess_bound(r))
            share = worst / int(r["wire_packets"])
            out.append({"aim": 2, "bandwidth_kbps": bw, "what": f"team, {p}: spurious share @{lo:g}% < 5 %",
                        "value": f"{100 * share:.2f} % (max of detected and retx - drops)",
                        "met": share < AIM_SPURIOUS_SHARE})
    for (bw, loss, p), a in sorted(by_team.items()):
        r = by_team.get((bw, loss, "rfc7252"))
        if p != "adaptive" or r is None or not _truthy(a.get("ok")):
            continue
        if not _truthy(r.get("ok")):
            out.append({"aim": 3, "bandwidth_kbps": bw, "what": f"team @{loss:g}%: adaptive vs rfc7252",
                        "value": f"rfc7252 did not finish ({r.get('tasks_agreed')}/{r.get('tasks')} tasks agreed); "
                                 f"adaptive coordinated all in {_num(a.get('coordination_s'), 1)} s",
                        "met": True})
            continue
        if _f(a.get("query_p99_ms")) is None or _f(r.get("query_p99_ms")) is None:
            continue
        tail = _f(a["query_p99_ms"]) < _f(r["query_p99_ms"])  # type: ignore[operator]
        bytes_ok = _f(a["wire_bytes"]) <= 1.05 * _f(r["wire_bytes"])  # type: ignore[operator]
        out.append({"aim": 3, "bandwidth_kbps": bw, "what": f"team @{loss:g}%: adaptive vs rfc7252",
                    "value": f"p99 {a['query_p99_ms']} vs {r['query_p99_ms']} ms; "
                             f"{a['wire_bytes']} vs {r['wire_bytes']} B",
                    "met": tail and bytes_ok})
    return out


def _md_table(columns: Sequence[str], rows: Iterable[Sequence[Any]], align: str | None = None) -> str:
    lines = ["| " + " | ".join(columns) + " |",
             "|" + "|".join((align or "-" * len(columns))[i] == "l" and "---" or "---:" for i in range(len(columns))) + "|"]
    lines += ["| " + " | ".join("" if v is None else str(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _num(v: Any, digits: int = 0) -> str:
    if v in (None, ""):
        return "–"
    x = float(v)
    return f"{x:,.{digits}f}"


def render_tables(
    summary: Sequence[Mapping[str, Any]],
    model: Sequence[Mapping[str, Any]] = (),
    team: Sequence[Mapping[str, Any]] = (),
    aims: Sequence[Mapping[str, Any]] = (),
) -> str:
    """Markdown: the query-level table (with the model's p99 beside the
    measured one), the team-level table, and the aims."""
    models = {(float(m["bandwidth_kbps"]), float(m["loss_pct"]), str(m["profile"])): m for m in model}
    order = {p: i for i, p in enumerate(ALL_PROFILES)}
    rows = []
    for r in sorted(summary, key=lambda r: (float(r["bandwidth_kbps"]), float(r["loss_pct"]),
                                            order.get(str(r["profile"]), 99))):
        m = models.get((float(r["bandwidth_kbps"]), float(r["loss_pct"]), str(r["profile"])))
        share = r.get("spurious_share_datagrams")
        rows.append((
            _num(r["bandwidth_kbps"]), _num(r["loss_pct"]), r["profile"], r["queries"], r["failed"],
            _num(r["p50_ms"]), _num(r["p95_ms"]), _num(r["p99_ms"]), _num(m["p99_ms"]) if m else "–",
            _num(r["retransmissions_per_query"], 2),
            f"{r['spurious_retransmissions']} / {r.get('excess_retransmissions_bound', '–')}",
            "–" if share in (None, "") else f"{100 * float(share):.1f}",
            _num(r["wire_bytes_per_query"]), _num(r["wire_datagrams"]),
        ))
    parts = ["### Query level\n", _md_table(
        ("kbit/s", "loss %", "profile", "queries", "failed", "p50 ms", "p95 ms", "p99 ms", "model p99 ms",
         "retx/query", "spurious: detected / ≥ true", "spurious % dgrams", "wire B/query", "datagrams"),
        rows, align="rrlrrrrrrrrrrr")]
    if team:
        trows = []
        for r in sorted(team, key=lambda r: (float(r["bandwidth_kbps"]), float(r["loss_pct"]),
                                             order.get(str(r["retransmission_profile"]), 99))):
            share = r.get("spurious_share")
            trows.append((
                _num(r["bandwidth_kbps"]), _num(r["loss_pct"]), r["retransmission_profile"],
                "yes" if _truthy(r.get("ok")) else "**no**",
                _num(r.get("coordination_s"), 1), _num(r.get("completion_s"), 1),
                _num(r.get("query_p50_ms")), _num(r.get("query_p99_ms")),
                f"{r.get('remote_queries', '')}/{r.get('failed_queries', '')}",
                f"{r.get('tasks_agreed', '')}/{r.get('tasks', '')}",
                _num(r.get("wire_bytes")), _num(r.get("wire_packets")), r.get("retransmissions", ""),
                r.get("dropped_packets", ""), f"{r.get('spurious_retransmissions', '')} / {team_excess_bound(r)}",
                "–" if share in (None, "") else f"{100 * float(share):.1f}",
            ))
        parts += ["\n### Team level (`bench.run_once`, coap-distributed, 3 robots)\n", _md_table(
            ("kbit/s", "loss %", "profile", "ok", "coordination s", "completion s", "query p50 ms",
             "query p99 ms", "remote/failed queries", "tasks agreed", "wire B", "wire pkts", "retx",
             "dropped", "spurious: detected / ≥ true", "detected % pkts"),
            trows, align="rrlrrrrrrrrrrrrr")]
    if aims:
        parts += ["\n### Aims\n", _md_table(
            ("aim", "kbit/s", "check", "measured", "met"),
            ((a["aim"], _num(a["bandwidth_kbps"]), a["what"], a["value"], "yes" if a["met"] else "**no**")
             for a in aims), align="rrllr")]
    return "\n".join(parts) + "\n"


def plot(summary: Sequence[Mapping[str, Any]], team: Sequence[Mapping[str, Any]], path: Path,
         model: Sequence[Mapping[str, Any]] = ()) -> None:
    """One row per bandwidth: p50, p95 and p99 vs loss per profile (log
    scale; the model's p99 dotted; the aim-1 limit dash-dotted),
    retransmissions per query and the controller's spurious detections per
    query, and the team's coordination time where there are team runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    bws = sorted({float(r["bandwidth_kbps"]) for r in summary})
    present = [p for p in ALL_PROFILES if any(r["profile"] == p for r in summary)]
    team_bws = {float(r["bandwidth_kbps"]) for r in team}
    ncols = 3 if team else 2
    fig, axes = plt.subplots(len(bws), ncols, figsize=(5.2 * ncols, 3.9 * len(bws) + 0.9), squeeze=False)
    models = {(float(m["bandwidth_kbps"]), float(m["loss_pct"]), str(m["profile"])): m for m in model}
    for i, bw in enumerate(bws):
        ax_lat, ax_retx = axes[i][0], axes[i][1]
        for p in present:
            rows = sorted((r for r in summary if float(r["bandwidth_kbps"]) == bw and r["profile"] == p),
                          key=lambda r: float(r["loss_pct"]))
            if not rows:
                continue
            loss = [float(r["loss_pct"]) for r in rows]
            c = COLOURS.get(p, "black")
            ax_lat.plot(loss, [float(r["p50_ms"]) / 1000 for r in rows], "o--", color=c, alpha=0.5, ms=4)
            ax_lat.plot(loss, [float(r["p95_ms"]) / 1000 for r in rows], "^-", color=c, alpha=0.5, lw=0.8, ms=4)
            ax_lat.plot(loss, [float(r["p99_ms"]) / 1000 for r in rows], "s-", color=c, ms=5)
            mp = [models.get((bw, x, p)) for x in loss]
            if all(mp):
                ax_lat.plot(loss, [float(m["p99_ms"]) / 1000 for m in mp], ":", color=c, lw=1.5)  # type: ignore[index]
            ax_retx.plot(loss, [float(r["retransmissions_per_query"]) for r in rows], "o-", color=c)
            ax_retx.plot(loss, [int(r["spurious_retransmissions"]) / max(1, int(r["queries"])) for r in rows],
                         "x:", color=c)
        base = [r for r in summary if float(r["bandwidth_kbps"]) == bw and r["profile"] == "adaptive"]
        if base:
            low = min(base, key=lambda r: float(r["loss_pct"]))
            ax_lat.axhline(AIM_TAIL_FACTOR * float(low["p50_ms"]) / 1000, color="grey", lw=1, ls="-.")
        ax_lat.set_yscale("log")
        ax_lat.set_xlabel("loss per datagram, %")
        ax_lat.set_ylabel("query latency, s")
        ax_lat.set_title(f"{bw:g} kbit/s: query latency p50 / p95 / p99", fontsize=10)
        ax_lat.grid(True, which="both", alpha=0.3)
        ax_retx.set_xlabel("loss per datagram, %")
        ax_retx.set_ylabel("per query")
        ax_retx.set_title(f"{bw:g} kbit/s: retransmissions (o) and detected spurious (x)", fontsize=10)
        ax_retx.grid(True, alpha=0.3)
        if team:
            ax = axes[i][2]
            if bw not in team_bws:
                ax.axis("off")
                continue
            trows = [r for r in team if float(r["bandwidth_kbps"]) == bw]
            losses = sorted({float(r["loss_pct"]) for r in trows})
            tprofiles = [p for p in PROFILE_NAMES if any(t["retransmission_profile"] == p for t in trows)]
            width = 0.8 / max(1, len(tprofiles))
            for j, p in enumerate(tprofiles):
                for k, x in enumerate(losses):
                    r = next((t for t in trows if float(t["loss_pct"]) == x and t["retransmission_profile"] == p), None)
                    if not r or r.get("coordination_s") in (None, ""):
                        continue
                    v = float(r["coordination_s"])
                    xpos = k + (j - (len(tprofiles) - 1) / 2) * width
                    ok = _truthy(r.get("ok"))
                    ax.bar(xpos, v, width, color=COLOURS[p], hatch=None if ok else "//", edgecolor="black" if not ok else None)
                    label = f"{v:.0f}" if ok else f"{v:.0f}\nstalled\n{r.get('tasks_agreed')}/{r.get('tasks')}"
                    ax.text(xpos, v * 1.1, label, ha="center", va="bottom", fontsize=7)
            ax.set_yscale("log")
            ax.set_xticks(range(len(losses)), [f"{x:g} % loss" for x in losses])
            ax.set_ylabel("coordination time, s")
            ax.set_ylim(top=ax.get_ylim()[1] * 4)
            ax.set_title(f"{bw:g} kbit/s: team of 3, 10 tasks, coordination", fontsize=10)
            ax.grid(True, axis="y", which="both", alpha=0.3)
    handles = [Line2D([], [], color=COLOURS.get(p, "black"), lw=3, label=p) for p in present]
    handles += [
        Line2D([], [], color="grey", ls="--", marker="o", label="p50"),
        Line2D([], [], color="grey", marker="^", lw=0.8, label="p95"),
        Line2D([], [], color="grey", marker="s", label="p99"),
        Line2D([], [], color="grey", ls=":", lw=1.5, label="model p99"),
        Line2D([], [], color="grey", ls="-.", label="aim 1: 3 x adaptive p50 @ lowest loss"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- CSV


def write_csv(path: Path, columns: Sequence[str], rows: Iterable[Mapping[str, Any]], append: bool = False) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    new = not append or not path.exists() or path.stat().st_size == 0
    with path.open("w" if not append else "a", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore", restval="")
        if new:
            w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in r.items()})


def read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def replace_rows(path: Path, columns: Sequence[str], new: Sequence[Mapping[str, Any]], key: Sequence[str]) -> None:
    """Rewrite ``path`` with ``new`` replacing old rows of the same key."""
    def k(r: Mapping[str, Any]) -> tuple[str, ...]:
        return tuple(f"{float(r[c]):g}" if c in ("bandwidth_kbps", "loss_pct") else str(r[c]) for c in key)

    fresh = {k(r) for r in new}
    kept = [r for r in read_csv(path) if k(r) not in fresh]
    write_csv(path, columns, [*kept, *new])


# --------------------------------------------------------------------------- measurement (needs root)


async def _warm_up(kb: Any, peer: Any, plan: Sequence[tuple[str, dict[str, str]]]) -> None:
    """Unmeasured queries, so the adaptive estimator starts converged (as on a
    robot that has been talking to its peers)."""
    from coapkb.kb.client import QueryFailed
    from coapkb.transport import TransportError

    for name, params in plan:
        try:
            await kb.named(peer, name, params)
        except (QueryFailed, TransportError):
            pass


async def _measure_stream(kb: Any, peer: Any, plan: Sequence[tuple[str, dict[str, str]]]) -> list[dict[str, Any]]:
    """The plan's queries in sequence: one record (latency, outcome) each."""
    from coapkb.kb.client import QueryFailed
    from coapkb.transport import TransportError

    records = []
    for seq, (name, params) in enumerate(plan):
        started = time.monotonic()
        error = ""
        try:
            await kb.named(peer, name, params)
        except (QueryFailed, TransportError) as exc:
            error = f"{type(exc).__name__}: {exc}"[:200]
        records.append({"seq": seq, "query": name, "ok": not error,
                        "latency_s": round(time.monotonic() - started, 6), "error": error})
    return records


async def measure_cell(
    bandwidth_kbps: float,
    loss_pct: float,
    profiles: Sequence[str] = PROFILE_NAMES,
    *,
    queries: int = 100,
    warmup: int = 5,
    streams: int = 1,
    seed: int = 1,
    timeout_s: float = 120.0,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Query level for one link setting, every profile (names of
    :data:`ALL_PROFILES`) at once.  Returns the per-query records and the
    summary rows."""
    from coapkb.kb.client import KBClient
    from coapkb.bench.linkemu import LinkSpec, Testbed, enter_netns
    from coapkb.harness.team import draw_tasks
    from coapkb.transport import Endpoint, open_client

    link = LinkSpec(rate_kbit=bandwidth_kbps, loss_pct=loss_pct)
    tags = {p: _HOST_TAGS.get(p) or p.replace("-", "").replace("+", "")[:8] for p in profiles}
    pairs = [(p, i, f"s-{tags[p]}-{i}", f"c-{tags[p]}-{i}") for p in profiles for i in range(streams)]
    hosts = [h for _, _, s, c in pairs for h in (s, c)]
    products = draw_tasks(200, seed=seed)
    records: list[dict[str, Any]] = []
    per_stream: dict[str, list[dict[str, Any]]] = {p: [] for p in profiles}
    async with Testbed(hosts, link) as tb:
        servers = await asyncio.gather(*(start_kb_server(tb, s) for _, _, s, _ in pairs))
        clients = {}
        try:
            for p, i, s, c in pairs:
                profile = profile_for(p, bandwidth_kbps)
                # The client's socket is created here, so it lives in c's namespace.
                with enter_netns(tb[c].netns):
                    client = await open_client("coap", retransmission=profile)
                client.reliability.rng = random.Random(seed * 1000 + i)
                client.reliability.history = 2 * (warmup + queries) + 64  # keep every exchange
                clients[(p, i)] = client

            peers = {(p, i): Endpoint("coap", tb.address(s), COAP_PORT) for p, i, s, _ in pairs}
            kbs = {key: KBClient(client, timeout=timeout_s) for key, client in clients.items()}
            plans = {(p, i): query_plan(warmup + queries, seed * 1000 + i, products) for p, i, _, _ in pairs}
            await asyncio.gather(*(_warm_up(kbs[k], peers[k], plans[k][:warmup]) for k in kbs))
            # One reading of the link counters before and one after every
            # stream: each stream has its own two hosts, which are idle
            # outside their stream, so per-host deltas are per-stream.
            before_link = await tb.acounters()
            before_stats = {k: clients[k].reliability.stats(peers[k]).as_dict() for k in clients}

            async def run(key: tuple[str, int]) -> tuple[list[dict[str, Any]], float, Any]:
                t0 = time.monotonic()
                recs = await _measure_stream(kbs[key], peers[key], plans[key][warmup:])
                # The estimator as the stream left it (read later, it would
                # have aged while the slower streams were still running).
                controller = clients[key].reliability
                return recs, time.monotonic() - t0, controller.stats(peers[key])

            results = await asyncio.gather(*(run((p, i)) for p, i, _, _ in pairs))
            after_link = await tb.acounters()
            for (p, i, s, c), (recs, wall, st) in zip(pairs, results):
                link_delta = {k: sum(getattr(after_link[h], k) - getattr(before_link[h], k) for h in (s, c))
                              for k in ("tx_packets", "tx_bytes", "dropped", "queue_drops")}
                delta = stats_delta(st.as_dict(), before_stats[(p, i)])
                history = clients[(p, i)].reliability.recent_exchanges(peers[(p, i)])
                measured = history[-delta["exchanges"]:] if delta["exchanges"] else []
                per_stream[p].append({
                    "stats": delta, "link": link_delta,
                    "rto": st.rto, "srtt": st.srtt, "min_rtt": st.min_rtt, "wall_s": wall,
                    "initial_timeouts": [r.schedule.initial_timeout for r in measured],
                })
                records.extend({"bandwidth_kbps": bandwidth_kbps, "loss_pct": loss_pct, "profile": p,
                                "stream": i, **r} for r in recs)
        finally:
            for client in clients.values():
                await client.aclose()
            await stop_processes(servers)
    summary = [summarise(bandwidth_kbps, loss_pct, p, [r for r in records if r["profile"] == p], per_stream[p])
               for p in profiles]
    return records, summary


async def measure_team(bandwidth_kbps: float, loss_pct: float, profile: str, tasks: int, seed: int) -> BenchRow:
    from coapkb.bench import run as bench

    row = await bench.run_once("coap-distributed", 3, tasks, bandwidth_kbps, loss_pct, rep=0,
                               retransmission=profile, seed=seed)
    return row


# --------------------------------------------------------------------------- command line


def report(out: Path, model_samples: int = 20_000) -> str:
    """(Re)build model.csv, table.md and the figure from the CSVs in ``out``."""
    summary = read_csv(out / "query_summary.csv")
    team = read_csv(out / "team.csv")
    model = model_rows(summary, n=model_samples) if summary else []
    if model:
        write_csv(out / "model.csv", MODEL_COLUMNS, model)
    aims = evaluate_aims(summary, team)
    text = render_tables(summary, model, team, aims)
    (out / "table.md").write_text(text, encoding="utf-8")
    if summary:
        plot(summary, team, out / "retransmission.png", model)
    return text


async def amain(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if not args.report_only:
        why = prepare_link_emulation()
        if why is not None:
            print(f"no kernel link emulation here: {why}", file=sys.stderr)
            return 2
        profiles = parse_list(args.profiles, str)
        unknown = [p for p in profiles if p not in ALL_PROFILES]
        if unknown:
            raise SystemExit(f"unknown profile(s) {unknown}; choose from {', '.join(ALL_PROFILES)}")
        team_profiles = [p for p in profiles if p in PROFILES]
        started = time.monotonic()
        if args.queries > 0:
            for bw in parse_list(args.bandwidths):
                for loss in parse_list(args.losses):
                    t0 = time.monotonic()
                    records, summary = await measure_cell(
                        bw, loss, profiles, queries=args.queries, warmup=args.warmup, streams=args.streams,
                        seed=args.seed, timeout_s=args.query_timeout)
                    replace_rows(out / "queries.csv", QUERY_COLUMNS, records,
                                 ("bandwidth_kbps", "loss_pct", "profile", "stream", "seq"))
                    replace_rows(out / "query_summary.csv", SUMMARY_COLUMNS, summary,
                                 ("bandwidth_kbps", "loss_pct", "profile"))
                    for s in summary:
                        print(f"{bw:g} kbit/s {loss:g} %  {s['profile']:<11} p50/p95/p99 {s['p50_ms']}/"
                              f"{s['p95_ms']}/{s['p99_ms']} ms  failed {s['failed']}  retx {s['retransmissions']}"
                              f"  spurious {s['spurious_retransmissions']}  wire {s['wire_bytes']} B",
                              flush=True)
                    print(f"  cell took {time.monotonic() - t0:.0f} s", flush=True)
        if args.team_tasks > 0 and args.team_bandwidths and args.team_losses:
            rows = []
            for bw in parse_list(args.team_bandwidths):
                for loss in parse_list(args.team_losses):
                    for p in team_profiles:
                        row = await measure_team(bw, loss, p, args.team_tasks, args.seed)
                        rows.append(team_row(row))
                        print(f"team {bw:g} kbit/s {loss:g} % {p:<11} ok={row.ok} coordination "
                              f"{row.coordination_s} s wire {row.wire_bytes} B retx {row.retransmissions} "
                              f"spurious {row.spurious_retransmissions} p50/p99 {row.query_p50_ms}/"
                              f"{row.query_p99_ms} ms wall {row.wall_s} s {row.error}", flush=True)
                        replace_rows(out / "team.csv", TEAM_COLUMNS, [rows[-1]],
                                     ("bandwidth_kbps", "loss_pct", "retransmission_profile"))
        print(f"measured in {time.monotonic() - started:.0f} s", flush=True)
    print(report(out, args.model_samples))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bandwidths", default="35,256", help="query level: link rates, kbit/s")
    p.add_argument("--losses", default="2,10,20", help="query level: loss per datagram, %%")
    p.add_argument("--profiles", default=",".join(ALL_PROFILES),
                   help="query level: any of these; team level: the named profiles among them")
    p.add_argument("--queries", type=int, default=100, help="measured queries per stream (0: skip the query level)")
    p.add_argument("--warmup", type=int, default=5, help="unmeasured queries first, per stream")
    p.add_argument("--streams", type=int, default=2, help="independent client/server pairs per profile")
    p.add_argument("--query-timeout", type=float, default=120.0, help="per query, s (above every give-up time but adaptive's)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--team-bandwidths", default="35", help="team level: link rates ('' to skip)")
    p.add_argument("--team-losses", default="2,20", help="team level: losses ('' to skip)")
    p.add_argument("--team-tasks", type=int, default=10, help="team level: tasks per run (0: skip)")
    p.add_argument("--model-samples", type=int, default=20_000)
    p.add_argument("--out", default=str(DEFAULT_OUT))
    p.add_argument("--report-only", action="store_true", help="only rebuild model, table and figure from the CSVs")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    return asyncio.run(amain(build_parser().parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
