"""experiments/stats.py: medians with distribution-free intervals and paired
ratios, and the report and figures built on them for 1 and 3 repetitions."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from math import comb
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from support import ROOT

from coapkb.bench.run import append_rows, read_rows

QUICK = ROOT / "experiments" / "results" / "quick.csv"


def _load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"experiments_{name}", ROOT / "experiments" / f"{name}.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


stats = _load("stats")


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
    report, figures = _load("report"), _load("figures")
    path = QUICK
    if reps == 3:
        path = tmp_path / "three.csv"
        _three_reps(path)
    out = tmp_path / "report.md"
    assert report.main([str(path), "--out", str(out), "--figures", str(tmp_path / "figs")]) == 0
    text = out.read_text()
    assert "### Paired ratios per cell (A/B)" in text
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
    figures = _load("figures")
    path = tmp_path / "three.csv"
    _three_reps(path)
    data = figures.Data(read_rows(path))
    p = data.get("coap-distributed", 3, 5, 35, 2)
    assert p.n == 3 and p.wire.has_interval and p.wire_bytes == p.wire.value
    d = data.difference("coap-central", "coap-distributed", 3, 5, 35, 2, "wire_bytes")
    assert d.n == 3 and d.low < d.value < d.high
