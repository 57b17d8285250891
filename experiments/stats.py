"""Medians with distribution-free confidence intervals, and paired ratios, on numpy.

The interval for a median is the pair of order statistics ``x(j) <= median <=
x(n+1-j)`` whose coverage, from Binomial(n, 1/2), is at least the confidence
asked for.  We use it rather than a bootstrap because it assumes nothing about
the distribution (completion times at high loss are skewed by a few long
back-offs) and states its *exact* coverage: with the 3-5 repetitions a cell
gets, no interval can reach 95 % (the range of 3 runs covers the median with
probability 75 %), and a bootstrap would quietly report that range as "95 %".
So an :class:`Estimate` carries its coverage, and the tables mark intervals
below the confidence asked for.

Pure functions, no I/O: ``experiments/report.py`` and ``experiments/figures.py``
draw every median, interval and ratio from here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from math import comb

import numpy as np

CONFIDENCE = 0.95
#: Marks an interval whose coverage is below :data:`CONFIDENCE` (too few runs).
SHORT = "\u2020"


@dataclass(frozen=True, slots=True)
class Estimate:
    """A median, its interval and the number of values behind it.

    ``low``/``high`` are None when there is no interval (one value);
    ``coverage`` is the probability the interval holds the true median."""

    value: float
    low: float | None
    high: float | None
    n: int
    coverage: float | None = None

    @property
    def has_interval(self) -> bool:
        return self.low is not None and self.high is not None

    @property
    def short(self) -> bool:
        """The interval covers less than :data:`CONFIDENCE` (too few values for more)."""
        return self.coverage is not None and self.coverage < CONFIDENCE - 1e-12

    def map(self, f: Callable[[float], float]) -> Estimate:
        """``f`` applied to the median and both bounds; ``f`` must be increasing
        (a unit change, 1 - x needs :meth:`complement`)."""
        return Estimate(f(self.value), None if self.low is None else f(self.low),
                        None if self.high is None else f(self.high), self.n, self.coverage)

    def complement(self) -> Estimate:
        """1 - x (a ratio as a saving): the bounds swap."""
        return Estimate(1 - self.value, None if self.high is None else 1 - self.high,
                        None if self.low is None else 1 - self.low, self.n, self.coverage)

    def yerr(self) -> tuple[float, float]:
        """Distances below and above the median, for matplotlib's ``errorbar`` (0 without an interval)."""
        if not self.has_interval:
            return 0.0, 0.0
        return self.value - self.low, self.high - self.value  # type: ignore[operator]

    def format(self, fmt: Callable[[float], str] = lambda v: f"{v:.1f}") -> str:
        """``median [low, high]``; ``median (n=1)`` without an interval; a
        :data:`SHORT` mark when the interval covers less than the confidence."""
        if not self.has_interval:
            return f"{fmt(self.value)} (n={self.n})"
        mark = SHORT if self.short else ""
        return f"{fmt(self.value)} [{fmt(self.low)}, {fmt(self.high)}]{mark}"  # type: ignore[arg-type]


def _clean(values: Iterable[float | None]) -> np.ndarray:
    """A float array without None and NaN (a run that did not measure the value)."""
    x = np.asarray([np.nan if v is None else v for v in values], dtype=float)
    return np.sort(x[~np.isnan(x)])


def median_rank(n: int, confidence: float = CONFIDENCE) -> tuple[int, float]:
    """``(j, coverage)``: the interval is the ``j``-th smallest to the ``j``-th
    largest of ``n`` values (1-based), the narrowest symmetric one whose
    coverage reaches ``confidence``; ``j = 1`` (the range) with its lower
    coverage when ``n`` is too small for that.  Needs ``n >= 2``."""
    if n < 2:
        raise ValueError("an interval needs at least two values")
    pmf = np.array([comb(n, i) for i in range(n + 1)], dtype=float) / 2.0**n
    cdf = np.cumsum(pmf)
    # Coverage of [x(j), x(n+1-j)] is P(j <= B <= n-j) = 1 - 2 P(B <= j-1).
    best = 1
    for j in range(1, n // 2 + 1):
        if 1 - 2 * cdf[j - 1] >= confidence:
            best = j
        else:
            break
    return best, float(1 - 2 * cdf[best - 1])


def median_ci(values: Iterable[float | None], confidence: float = CONFIDENCE) -> Estimate | None:
    """The median of ``values`` (None and NaN left out) with its
    distribution-free interval; None for no values."""
    x = _clean(values)
    n = len(x)
    if n == 0:
        return None
    median = float(np.median(x))
    if n == 1:
        return Estimate(median, None, None, 1)
    j, coverage = median_rank(n, confidence)
    return Estimate(median, float(x[j - 1]), float(x[n - j]), n, coverage)


def paired_ratios(a: Iterable[float | None], b: Iterable[float | None]) -> np.ndarray:
    """``a[i] / b[i]`` for every pair where both are positive numbers (a pair is
    the same cell and repetition of two systems, hence the same task list)."""
    x = np.asarray([np.nan if v is None else v for v in a], dtype=float)
    y = np.asarray([np.nan if v is None else v for v in b], dtype=float)
    if x.shape != y.shape:
        raise ValueError(f"unpaired: {x.shape[0]} values against {y.shape[0]}")
    good = (x > 0) & (y > 0)  # NaN compares False
    return x[good] / y[good]


def ratio_ci(a: Iterable[float | None], b: Iterable[float | None],
             confidence: float = CONFIDENCE) -> Estimate | None:
    """The median of the paired ratios ``a/b`` with its interval (None for no pairs)."""
    return median_ci(paired_ratios(a, b), confidence)
