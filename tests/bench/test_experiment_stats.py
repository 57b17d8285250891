"""experiments/stats.py: medians with distribution-free intervals and paired
ratios, and the report and figures built on them for 1 and 3 repetitions."""

from __future__ import annotations

import dataclasses
from math import comb
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from coapkb.bench.run import append_rows, read_rows
from experiments import matrix_time, stats

#: A one-repetition quick-profile CSV from before the security column (an
#: earlier committed result), so the tests do not move with new results.
QUICK = Path(__file__).parent / "data" / "quick-1rep.csv"


def test_median_rank_matches_the_binomial_tables() -> None:
    # The classic table (e.g. Conover): n=9 -> 2nd to 8th at 96.1 %; n=6 -> range at 96.9 %.
    assert stats.median_rank(6) == (1, pytest.approx(1 - 2 / 64))
    assert stats.median_rank(9) == (2, pytest.approx(1 - 2 * (1 + 9) / 512))
    j, coverage = stats.median_rank(20)
    assert (j, round(coverage, 4)) == (6, 0.9586)
    # The next narrower interval would fall below 95 %.
    assert 1 - 2 * sum(comb(20, i) for i in range(6 + 1)) / 2**20 < 0.95
    # Too few values for 95 %: the range, with its true coverage.
    assert stats.median_rank(3) == (1, 0.75)
    with pytest.raises(ValueError):
        stats.median_rank(1)


def test_median_ci_of_few_values_and_missing_ones() -> None:
    assert stats.median_ci([]) is None
    assert stats.median_ci([None, float("nan")]) is None
    one = stats.median_ci([4.0, None])
    assert (one.value, one.low, one.high, one.n, one.has_interval) == (4.0, None, None, 1, False)
    assert one.format() == "4.0 (n=1)" and one.yerr() == (0.0, 0.0)
    three = stats.median_ci([3.0, 1.0, 2.0])
    assert (three.value, three.low, three.high, three.coverage, three.short) == (2.0, 1.0, 3.0, 0.75, True)
    assert three.format() == f"2.0 [1.0, 3.0]{stats.SHORT}" and three.yerr() == (1.0, 1.0)
    ten = stats.median_ci(range(10))
    assert (ten.low, ten.high, ten.short) == (1.0, 8.0, False) and ten.format(lambda v: f"{v:g}") == "4.5 [1, 8]"


def test_the_interval_covers_the_median_as_often_as_it_says() -> None:
    """Seeded simulation from a skewed distribution (exponential, median ln 2)."""
    rng = np.random.default_rng(7)
    for n in (3, 10, 25):
        hits = 0
        trials = 3000
        for _ in range(trials):
            e = stats.median_ci(rng.exponential(size=n))
            hits += e.low <= np.log(2) <= e.high
        coverage = stats.median_rank(n)[1]
        assert abs(hits / trials - coverage) < 0.025, (n, hits / trials, coverage)


def test_paired_ratios_keep_only_pairs_with_both_values() -> None:
    assert list(stats.paired_ratios([1, 2, None, 4, 3], [2, 2, 3, 0, float("nan")])) == [0.5, 1.0]
    r = stats.ratio_ci([2, 4, 6], [1, 2, 2])
    assert (r.value, r.low, r.high, r.n) == (2.0, 2.0, 3.0, 3)
    saving = r.complement()  # 1 - A/B: the bounds swap
    assert (saving.value, saving.low, saving.high) == (-1.0, -2.0, -1.0)
    assert stats.ratio_ci([1], [0]) is None
    with pytest.raises(ValueError):
        stats.paired_ratios([1, 2], [1])


def _three_reps(path: Path) -> None:
    """The committed quick CSV, three times, each repetition scaled a little, one failed run."""
    rows = read_rows(QUICK)
    scale = (0.9, 1.0, 1.2)
    out = []
    for rep in range(3):
        for r in rows:
            out.append(dataclasses.replace(
                r, rep=rep, seed=1 + rep,
                wire_bytes=None if r.wire_bytes is None else int(r.wire_bytes * scale[rep]),
                completion_s=None if r.completion_s is None else r.completion_s * scale[rep],
                ok=r.ok and not (rep == 2 and r.system == "coap-central" and r.loss_pct == 20)))
    append_rows(path, out)


@pytest.mark.parametrize("reps", [1, 3])
def test_report_and_figures_on_the_quick_csv(tmp_path: Path, reps: int) -> None:
    from experiments import figures, report
    path = QUICK
    if reps == 3:
        path = tmp_path / "three.csv"
        _three_reps(path)
    out = tmp_path / "report.md"
    assert report.main([str(path), "--out", str(out), "--figures", str(tmp_path / "figs")]) == 0
    text = out.read_text()
    assert "### Paired ratios per cell (A/B)" in text
    # The paper matrix's duration, from the runs' wall times (the 1-rep CSV has no security column).
    assert "## How long the paper matrix takes" in text and "| 64 | " in text
    assert "7200 runs of the `paper` profile" in text
    if reps == 1:
        assert "| 3 | 5 | 35 | 2 | 28.2 (n=1) |" in text  # coap-distributed's bytes, no interval
    else:
        # Median of (0.9, 1.0, 1.2) x 28.2 kB and its range, marked: 3 runs cannot give 95 %.
        assert f"| 3 | 5 | 35 | 2 | 28.2 [25.4, 33.9]{stats.SHORT} |" in text
        assert "(1 failed)" in text
        # The same scale in both systems of a pair: every per-rep ratio equal, a zero-width interval.
        assert "distributed vs central, CoAP + compact: saving | 17 % [" in text
    results = figures.draw_all(read_rows(path), tmp_path / "figs")
    assert all(isinstance(results[f"fig{n:02d}"], Path) for n in range(6, 13))


def test_figures_draw_the_interval_as_an_error_bar(tmp_path: Path) -> None:
    from experiments import figures
    path = tmp_path / "three.csv"
    _three_reps(path)
    data = figures.Data(read_rows(path))
    p = data.get("coap-distributed", 3, 5, 35, 2)
    assert p.n == 3 and p.wire.has_interval and p.wire_bytes == p.wire.value
    d = data.difference("coap-central", "coap-distributed", 3, 5, 35, 2, "wire_bytes")
    assert d.n == 3 and d.low < d.value < d.high


# --------------------------------------------------------------------------- how long a matrix takes

#: Known coefficients (setup, per_robot, per_task, serial, per_loss), seconds.
TRUE = {"a": (4.0, 1.5, 0.5, 0.3, 0.6), "b": (9.0, 0.5, 1.2, 0.8, 0.1)}


def _synthetic(systems: dict[str, tuple[float, ...]], losses: tuple[float, ...] = (2, 20)) -> pd.DataFrame:
    from itertools import product

    grid = pd.DataFrame(list(product(systems, (3, 9), (5, 20), (35.0, 256.0), losses)),
                        columns=["system", "robots", "tasks", "bandwidth_kbps", "loss_pct"])
    coef = np.array([systems[s] for s in grid["system"]])
    grid["wall_s"] = np.einsum("ij,ij->i", matrix_time.design(grid), coef)
    grid["ok"] = True
    grid["started_at"] = ""
    return grid


def test_tasks_per_cluster_is_the_sequence_one_cluster_does() -> None:
    assert list(matrix_time.tasks_per_cluster([5, 20, 5, 80, 10], [3, 3, 9, 6, 6])) == [5, 20, 2, 40, 5]


def test_the_model_recovers_known_setup_and_per_task_times() -> None:
    rows = _synthetic(TRUE)
    rows.loc[rows.index[::5], "ok"] = False  # failed runs cost their time like the others
    model = matrix_time.fit(rows)
    for system, values in TRUE.items():
        assert model.coef.loc[system].to_numpy() == pytest.approx(values, abs=1e-9)
        assert model.borrowed[system] == ()
    assert np.median(matrix_time.abs_errors(model, rows)) == pytest.approx(0, abs=1e-9)
    # A cell left out is predicted from the others: exact for an exactly linear truth.
    held = matrix_time.held_out_predictions(rows)
    assert held.sort_index().to_numpy() == pytest.approx(rows["wall_s"].to_numpy(), rel=1e-9)
    # 6 robots, 80 tasks, 128 kbit/s, 10 % loss: the straight lines through the measured points.
    cell = pd.DataFrame({"system": ["a"], "robots": [6], "tasks": [80], "bandwidth_kbps": [128.0], "loss_pct": [10.0]})
    s, r, t, ser, loss = TRUE["a"]
    assert model.predict(cell)[0] == pytest.approx(s + 3 * r + 40 * (t + ser * (35 / 128 - 1) + loss * 8))


def test_what_a_system_cannot_determine_comes_from_the_pooled_fit() -> None:
    same_slopes = {"a": (4.0, 1.0, 0.5, 0.8, 0.6), "b": (9.0, 1.0, 0.5, 0.8, 0.6)}
    rows = pd.concat([_synthetic(same_slopes), _synthetic({"c": (2.0, 1.0, 0.5, 0.8, 0.6)}, losses=(2,))],
                     ignore_index=True)
    model = matrix_time.fit(rows)
    assert model.borrowed["c"] == ("per_loss",)
    assert model.coef.loc["c"].to_numpy() == pytest.approx((2.0, 1.0, 0.5, 0.8, 0.6), abs=1e-9)
    assert model.pooled["per_loss"] == pytest.approx(0.6)
    # A system with no runs gets the pooled values and the mean setup ((4 + 9 + 2) / 3).
    unseen = pd.DataFrame({"system": ["z"], "robots": [3], "tasks": [5], "bandwidth_kbps": [35.0], "loss_pct": [2.0]})
    assert model.predict(unseen)[0] == pytest.approx(5 + 5 * 0.5)
    # Never below the shortest measured run, never above a cap.
    assert model.predict(unseen, cap_s=np.array([3.0]))[0] == 3.0


def test_a_plan_total_is_the_sum_and_machines_never_beat_the_longest_run() -> None:
    model = matrix_time.fit(_synthetic(TRUE))
    plan = _synthetic(TRUE).drop(columns="wall_s")
    plan = pd.concat([plan, plan.assign(tasks=80, loss_pct=10.0)], ignore_index=True)
    pred = model.predict(plan)
    t = matrix_time.matrix_time(model, plan)
    assert t.total_s == pytest.approx(pred.sum()) and t.longest_s == pytest.approx(pred.max())
    assert t.by_system.sum() == pytest.approx(t.total_s)
    assert t.runs_by_system.to_dict() == {"a": 32, "b": 32}
    assert t.makespan(1) == pytest.approx(t.total_s)
    assert t.makespan(4) == pytest.approx(t.total_s / 4)
    assert t.makespan(2, slots=2) == pytest.approx(t.total_s / 4)
    spans = t.makespan(np.array([1, 4, 16, 64, 10_000]), slots=2)
    assert np.all(np.diff(spans) <= 0) and np.all(spans >= t.longest_s)
    assert spans[-1] == pytest.approx(t.longest_s)


def test_concurrency_is_the_runs_wall_time_over_the_sweeps_span() -> None:
    rows = pd.DataFrame({"wall_s": [10.0, 10.0, 10.0, 10.0],
                         "started_at": ["2026-01-01T00:00:00+00:00", "2026-01-01T00:00:00+00:00",
                                        "2026-01-01T00:00:10+00:00", "2026-01-01T00:00:10+00:00"]})
    assert matrix_time.concurrency(rows) == pytest.approx(2.0)
    assert matrix_time.concurrency(rows.assign(started_at="")) == 1.0
