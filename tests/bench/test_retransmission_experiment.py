"""experiments/retransmission.py: its pure parts, and one tiny real run on
kernel-emulated links (root only; a failure under CI)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest
from support import ROOT, require

from coapkb.transport.coap.reliability.rto import PROFILES



def _load():
    spec = importlib.util.spec_from_file_location("retransmission_experiment", ROOT / "experiments" / "retransmission.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


R = _load()


def test_percentile_matches_numpy_linear() -> None:
    assert R.percentile([], 50) is None
    assert R.percentile([3.0], 99) == 3.0
    values = [float(v) for v in range(1, 101)]  # numpy.percentile(1..100, q)
    assert R.percentile(values, 50) == pytest.approx(50.5)
    assert R.percentile(values, 95) == pytest.approx(95.05)
    assert R.percentile(values, 99) == pytest.approx(99.01)
    assert R.percentile([5.0, 1.0, 3.0], 100) == 5.0 and R.percentile([5.0, 1.0, 3.0], 0) == 1.0
    with pytest.raises(ValueError):
        R.percentile([1.0], 101)


def test_query_plan_is_seeded_and_mixes_the_four_queries() -> None:
    products = ["A_1", "B_2", "C_3"]
    plan = R.query_plan(8, 7, products)
    assert plan == R.query_plan(8, 7, products) and plan != R.query_plan(8, 8, products)
    assert [name for name, _ in plan[:4]] == [q for q, _ in R.QUERY_MIX]
    assert all(params.get("name") in products or params.get("grip") in R.GRIPS for _, params in plan)


def test_profile_variants() -> None:
    assert R.profile_for("adaptive", 35) is PROFILES["adaptive"]
    assert R.profile_for("adaptive-uncapped", 35).backoff_cap is None
    assert R.profile_for("adaptive+rate", 35).link_rate_bps == 35_000
    with pytest.raises(ValueError):
        R.profile_for("fast", 35)


def _queries(latencies: list[float], failed: int = 0) -> list[dict]:
    return [{"latency_s": x, "ok": i >= failed} for i, x in enumerate(latencies)]


def test_summarise_aggregates_streams() -> None:
    stats = {k: 0 for k in R.STAT_FIELDS}
    s1 = {"stats": {**stats, "transmissions": 60, "retransmissions": 10, "spurious_retransmissions": 1},
          "link": {"tx_packets": 110, "tx_bytes": 30_000, "dropped": 9, "queue_drops": 0},
          "rto": 0.2, "srtt": 0.004, "min_rtt": 0.002, "wall_s": 12.0, "initial_timeouts": [0.5, 0.5, 1.5]}
    s2 = {"stats": {**stats, "transmissions": 55, "retransmissions": 5, "spurious_retransmissions": 0},
          "link": {"tx_packets": 90, "tx_bytes": 20_000, "dropped": 5, "queue_drops": 0},
          "rto": 0.4, "srtt": 0.006, "min_rtt": 0.002, "wall_s": 20.0}
    lat = [0.01] * 98 + [1.0, 5.0]
    row = R.summarise(35, 20, "adaptive", _queries(lat, failed=1), [s1, s2])
    assert row["queries"] == 100 and row["failed"] == 1
    assert row["p50_ms"] == 10.0 and row["p99_ms"] == pytest.approx(1040.0)  # 1.0 + 0.01·4.0 s
    assert row["retransmissions"] == 15 and row["spurious_retransmissions"] == 1
    assert row["wire_datagrams"] == 200 and row["wire_bytes_per_query"] == 500.0
    assert row["spurious_share_datagrams"] == 0.005 and row["spurious_share_con"] == round(1 / 115, 4)
    assert row["excess_retransmissions_bound"] == 1  # 15 retransmissions, 14 datagrams lost
    assert row["final_rto_s"] == 0.3 and row["srtt_ms"] == 5.0 and row["wall_s"] == 20.0
    assert row["t0_p50_ms"] == 500.0 and row["t0_max_ms"] == 1500.0 and row["t0_share_over_1s"] == 0.333
    assert set(row) == set(R.SUMMARY_COLUMNS)
    assert R.stats_delta({"retransmissions": 7, "exchanges": 9}, {"retransmissions": 2}) == {
        **{k: 0 for k in R.STAT_FIELDS}, "retransmissions": 5, "exchanges": 9}


def _row(bw: float, loss: float, profile: str, p50: float, p99: float, share: float, bpq: float) -> dict:
    return {"bandwidth_kbps": bw, "loss_pct": loss, "profile": profile, "queries": 100, "failed": 0,
            "p50_ms": p50, "p95_ms": p50, "p99_ms": p99, "retransmissions_per_query": 0.1,
            "spurious_retransmissions": 0, "excess_retransmissions_bound": 0, "spurious_share_datagrams": share,
            "wire_bytes_per_query": bpq, "wire_datagrams": 200}


def test_aims_and_table_rendering() -> None:
    summary = [
        _row(35, 2, "adaptive", 50, 600, 0.0, 300), _row(35, 20, "adaptive", 50, 140, 0.01, 400),
        _row(35, 2, "rfc7252", 50, 2800, 0.0, 300), _row(35, 20, "rfc7252", 50, 40_000, 0.08, 380),
    ]
    aims = R.evaluate_aims(summary)
    by = {(a["aim"], a["what"]): a["met"] for a in aims}
    assert by[(1, "adaptive p99 @20% <= 3 x p50 @2%")] is True  # 140 <= 150
    assert by[(2, "adaptive: spurious share @2% < 5 %")] is True
    assert by[(3, "adaptive vs rfc7252 @2%: lower p99, bytes/query within 5 %")] is True
    assert by[(3, "adaptive vs rfc7252 @20%: lower p99, bytes/query within 5 %")] is False  # 400 > 1.05·380
    team = [{"bandwidth_kbps": 35, "loss_pct": 20, "retransmission_profile": p, "ok": "True",
             "coordination_s": c, "completion_s": c, "query_p50_ms": 10, "query_p99_ms": q99,
             "remote_queries": 80, "failed_queries": 0, "tasks": 10, "tasks_agreed": 10, "wire_bytes": b,
             "wire_packets": 500, "retransmissions": 50, "dropped_packets": 50, "spurious_retransmissions": 1,
             "spurious_share": 0.002}
            for p, c, q99, b in (("rfc7252", 190.0, 30_000, 70_000), ("adaptive", 90.0, 9000, 69_000))]
    aims = R.evaluate_aims(summary, team)
    assert any(a["what"] == "team @20%: adaptive vs rfc7252" and a["met"] for a in aims)
    stalled = [dict(team[0], ok="False", tasks_agreed=2), team[1]]
    [a] = [a for a in R.evaluate_aims(summary, stalled) if a["what"].startswith("team @")]
    assert a["met"] and "did not finish" in a["value"]
    # team spurious share: the larger of the detected count and retransmissions - drops
    team[0].update(retransmissions=60, dropped_packets=20, spurious_retransmissions=1)  # 40 unexplained of 500
    assert R.team_excess_bound(team[0]) == 40 and R.team_excess_bound({}) == 0
    shares = {a["what"]: a["met"] for a in R.evaluate_aims(summary, team) if a["what"].startswith("team,")}
    assert shares == {"team, rfc7252: spurious share @20% < 5 %": False, "team, adaptive: spurious share @20% < 5 %": True}
    text = R.render_tables(summary, [], team, aims)
    assert "### Query level" in text and "### Team level" in text and "### Aims" in text
    lines = [line for line in text.splitlines() if line.startswith("| 35 | 20 | adaptive")]
    assert len(lines) == 2 and "| 140 |" in lines[0] and "| 9,000 |" in lines[1]  # query level, team level
    header = next(line for line in text.splitlines() if line.startswith("| kbit/s"))
    assert all(line.count("|") == header.count("|") for line in text.splitlines()[:8] if line.startswith("|"))


def test_model_uses_the_profiles_schedules() -> None:
    # No loss: every query takes the RTT, nothing is retransmitted.
    clean = R.simulate("adaptive", 0.0, 0.05, n=200)
    assert clean.failed == 0 and clean.retransmissions == 0 and set(clean.latencies) == {0.05}
    # RFC 7252 at 20 % loss: each attempt fails with 1 - 0.8² = 0.36; mean
    # retransmissions per exchange sum_k 0.36^k for k = 1..4 = 0.548.
    rfc = R.simulate("rfc7252", 20.0, 0.01, n=20_000, seed=3)
    assert rfc.retransmissions / 20_000 == pytest.approx(0.548, rel=0.05)
    assert rfc.failed / 20_000 == pytest.approx(0.36**5, rel=0.3) and rfc.spurious == 0
    # one loss costs the first timeout: lossy-fixed 0.8-1.0 s, adaptive 0.5 s once converged
    lossy = R.simulate("lossy-fixed", 10.0, 0.01, n=5000, seed=4)
    one_loss = [x for x in lossy.latencies if 0.5 < x < 1.5]
    assert one_loss and all(0.81 <= x <= 1.01 for x in one_loss)
    # a timeout shorter than the RTT retransmits spuriously
    # (the first timeouts, 2-3 s, are shorter than a 4 s RTT; then the RTO adapts)
    slow = R.simulate("adaptive", 0.0, 4.0, n=50, warmup=0)
    assert slow.spurious > 0 and slow.retransmissions == slow.spurious
    assert math.isclose(R.percentile(slow.latencies, 50), 4.0)


@pytest.mark.root
@pytest.mark.slow
def test_tiny_real_run(tmp_path: Path) -> None:
    """Every profile at once over one emulated 512 kbit/s, 10 % loss link
    setting: a few queries each, and the whole report pipeline."""
    from coapkb.bench import linkemu

    ok, why = linkemu.available()
    require(ok, f"no kernel link emulation: {why}")
    linkemu.cleanup_stale()
    import asyncio

    records, summary = asyncio.run(R.measure_cell(
        512, 10, ("rfc7252", "lossy-fixed", "adaptive", "adaptive+rate"), queries=6, warmup=2, streams=1,
        timeout_s=30))
    assert len(records) == 4 * 6 and {r["profile"] for r in records} == {"rfc7252", "lossy-fixed", "adaptive",
                                                                        "adaptive+rate"}
    for row in summary:
        # (a query fails only if 4 attempts in a row are lost: ~1e-3 at 10 % loss)
        assert row["queries"] == 6 and row["failed"] <= 1, row
        assert row["exchanges"] >= 6 and row["transmissions"] == row["exchanges"] + row["retransmissions"]
        # every datagram of the stream crossed a counted link: a request and a reply per transmission at least
        assert row["wire_datagrams"] >= row["exchanges"] * 2 and row["queue_drops"] == 0
        assert 0 < row["p50_ms"] <= row["p95_ms"] <= row["p99_ms"] <= row["max_ms"]
        assert row["t0_p50_ms"] >= 500  # every profile's first timeout is at least 0.5 s
    R.write_csv(tmp_path / "queries.csv", R.QUERY_COLUMNS, records)
    R.write_csv(tmp_path / "query_summary.csv", R.SUMMARY_COLUMNS, summary)
    text = R.report(tmp_path, model_samples=500)
    assert "| 512 | 10 | adaptive |" in text
    assert (tmp_path / "retransmission.png").stat().st_size > 10_000
    assert (tmp_path / "model.csv").exists()
