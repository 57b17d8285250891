"""How long a run takes, from measured runs, and how long a whole matrix takes on N machines.

The model is linear, per system, in five numbers (seconds)::

    wall = setup + per_robot * (robots - 3)
         + k * (per_task + serial * (35 / bandwidth - 1) + per_loss * (loss - 2))

with ``k = ceil(tasks / (robots // 3))`` the tasks one cluster does in
sequence (clusters work in parallel).  ``setup`` and ``per_robot`` are the
start-up and teardown of the testbed (a namespace, a shaper and processes per
robot); ``per_task`` is a task's cost at the reference link (35 kbit/s, 2 %
loss); ``serial`` scales with ``1 / bandwidth`` (serialisation), so 128 kbit/s
sits between the measured 35 and 256 and 512 a little beyond 256 (``1/512`` is
near ``1/256``); ``per_loss`` is linear in the loss rate, so 5-15 % lie on the
straight line between the measured 2 and 20 %.  Robots enter linearly (6
between 3 and 9), tasks through ``k`` (40 and 80 tasks are beyond the measured
5 and 20: extrapolated).

Each system gets its own least-squares fit (``numpy.linalg.lstsq``).  A
coefficient its own rows cannot determine (say ``per_loss`` for a system
measured at one loss only) comes from the *pooled* fit: all systems together,
one ``setup`` per system and the other four shared.  A system with no rows
at all gets the pooled coefficients and the mean ``setup``.  Failed runs are
fitted like the others: they cost their wall time too.

Pure functions on pandas frames with the benchmark CSV's columns
(``system, robots, tasks, bandwidth_kbps, loss_pct``, and ``wall_s`` to fit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

CLUSTER_SIZE = 3
#: The model's coefficients, in design-matrix order.
FEATURES = ("setup", "per_robot", "per_task", "serial", "per_loss")
#: The reference link the per-task cost is given at.
REF_BANDWIDTH = 35.0
REF_LOSS = 2.0
REF_ROBOTS = 3


def tasks_per_cluster(tasks: np.ndarray | pd.Series, robots: np.ndarray | pd.Series) -> np.ndarray:
    """The tasks one cluster does in sequence: ``ceil(tasks / (robots // 3))``."""
    clusters = np.maximum(np.asarray(robots, dtype=int) // CLUSTER_SIZE, 1)
    return np.ceil(np.asarray(tasks, dtype=float) / clusters)


def design(df: pd.DataFrame) -> np.ndarray:
    """The design matrix, one column per :data:`FEATURES`."""
    k = tasks_per_cluster(df["tasks"], df["robots"])
    bw = df["bandwidth_kbps"].to_numpy(dtype=float)
    loss = df["loss_pct"].to_numpy(dtype=float)
    robots = df["robots"].to_numpy(dtype=float)
    return np.column_stack([np.ones(len(df)), robots - REF_ROBOTS, k,
                            k * (REF_BANDWIDTH / bw - 1), k * (loss - REF_LOSS)])


def identifiable(x: np.ndarray) -> np.ndarray:
    """Per column, whether the rows determine its coefficient: it is not a
    combination of the other columns (dropping it lowers the rank)."""
    if not len(x):
        return np.zeros(x.shape[1], dtype=bool)
    rank = np.linalg.matrix_rank(x)
    return np.array([np.linalg.matrix_rank(np.delete(x, j, axis=1)) < rank for j in range(x.shape[1])])


@dataclass(frozen=True)
class TimeModel:
    """Per-system coefficients (rows: systems, columns: :data:`FEATURES`);
    ``borrowed`` names, per system, the coefficients taken from the pooled fit."""

    coef: pd.DataFrame
    borrowed: dict[str, tuple[str, ...]]
    #: The pooled fit's shared coefficients (``setup``: the mean over the systems).
    pooled: pd.Series
    #: No prediction goes below this: a straight line extrapolated with a noisy
    #: negative slope would otherwise give zero or negative times (no measured
    #: run, with its namespaces and processes to set up, took under 2 s).
    floor_s: float = 1.0

    def predict(self, df: pd.DataFrame, cap_s: np.ndarray | None = None) -> np.ndarray:
        """Predicted wall seconds per row of ``df``; a system the model has no
        row for uses :attr:`pooled`.  ``cap_s`` (per row) is an upper bound,
        e.g. the sweep's kill limit for the run."""
        coef = self.coef.reindex(df["system"].to_numpy())
        coef = coef.fillna(self.pooled).to_numpy(dtype=float)
        pred = np.maximum(np.einsum("ij,ij->i", design(df), coef), self.floor_s)
        return pred if cap_s is None else np.minimum(pred, np.asarray(cap_s, dtype=float))


def _measured(rows: pd.DataFrame) -> pd.DataFrame:
    return rows[rows["wall_s"].notna() & (rows["wall_s"].astype(float) > 0)]


def fit_pooled(rows: pd.DataFrame) -> tuple[pd.Series, pd.Series]:
    """One ``setup`` per system and the other coefficients shared:
    ``(setups by system, shared coefficients)``.  A shared coefficient the
    rows do not determine (no variation in its axis) is 0."""
    systems = pd.get_dummies(rows["system"], dtype=float)
    x = np.column_stack([systems.to_numpy(), design(rows)[:, 1:]])
    keep = identifiable(x)
    keep[: systems.shape[1]] = True
    beta = np.zeros(x.shape[1])
    beta[keep] = np.linalg.lstsq(x[:, keep], rows["wall_s"].to_numpy(dtype=float), rcond=None)[0]
    setups = pd.Series(beta[: systems.shape[1]], index=systems.columns)
    shared = pd.Series([float(setups.mean()), *beta[systems.shape[1]:]], index=list(FEATURES))
    return setups, shared


def _fit_system(rows: pd.DataFrame, prior: np.ndarray) -> tuple[np.ndarray, tuple[str, ...]]:
    """One system's coefficients: its own least squares for what its rows
    determine, ``prior`` (the pooled values) for the rest."""
    x, y = design(rows), rows["wall_s"].to_numpy(dtype=float)
    own = identifiable(x)
    own[0] = True  # the setup is always the system's own (what the fixed slopes leave)
    # Adding the setup back may make the set rank-deficient: drop the last own slopes until it is not.
    for j in range(len(FEATURES) - 1, 0, -1):
        if np.linalg.matrix_rank(x[:, own]) == own.sum():
            break
        own[j] = False
    beta = prior.copy()
    beta[own] = np.linalg.lstsq(x[:, own], y - x[:, ~own] @ prior[~own], rcond=None)[0]
    return beta, tuple(f for f, o in zip(FEATURES, own) if not o)


def fit(rows: pd.DataFrame) -> TimeModel:
    """The model from measured rows (``wall_s`` > 0; failed runs included)."""
    rows = _measured(rows)
    if rows.empty:
        raise ValueError("no rows with a wall time to fit")
    setups, shared = fit_pooled(rows)
    fits = rows.groupby("system").apply(
        lambda g: _fit_system(g, np.array([setups[g.name], *shared.iloc[1:]])), include_groups=False)
    coef = pd.DataFrame(np.vstack(fits.map(lambda f: f[0]).to_numpy()), index=fits.index, columns=list(FEATURES))
    borrowed = fits.map(lambda f: f[1]).to_dict()
    return TimeModel(coef, borrowed, shared)


def abs_errors(model: TimeModel, rows: pd.DataFrame) -> np.ndarray:
    """``|predicted - measured| / measured`` per measured row."""
    rows = _measured(rows)
    wall = rows["wall_s"].to_numpy(dtype=float)
    return np.abs(model.predict(rows) - wall) / wall


CELL = ("robots", "tasks", "bandwidth_kbps", "loss_pct")


def held_out_predictions(rows: pd.DataFrame) -> pd.Series:
    """Each measured row predicted by a model fitted *without its cell* (all
    systems and repetitions of that robots/tasks/bandwidth/loss): how well the
    model guesses a cell it has not seen, which is what the matrix asks of it."""
    rows = _measured(rows)
    return rows.groupby(list(CELL), group_keys=False).apply(
        lambda cell: pd.Series(fit(rows.drop(cell.index)).predict(rows.loc[cell.index]), index=cell.index))


@dataclass(frozen=True)
class MatrixTime:
    """Predicted totals for a plan of runs (seconds)."""

    total_s: float          # sum of the runs' predicted wall times (as measured)
    longest_s: float        # the longest single run: no division of the work beats it
    by_system: pd.Series    # sum per system
    runs_by_system: pd.Series

    def makespan(self, machines: int | np.ndarray, slots: float = 1.0) -> np.ndarray:
        """The wall time on ``machines`` machines each doing ``slots`` runs'
        worth of work at once: ideal division, never below the longest run."""
        return np.maximum(self.total_s / (np.asarray(machines, dtype=float) * slots), self.longest_s)


def matrix_time(model: TimeModel, plan: pd.DataFrame, cap_s: np.ndarray | None = None) -> MatrixTime:
    """The predicted totals of every run of ``plan`` (one row per run)."""
    pred = pd.Series(model.predict(plan, cap_s), index=plan.index)
    by_system = pred.groupby(plan["system"].to_numpy())
    return MatrixTime(float(pred.sum()), float(pred.max()) if len(pred) else 0.0, by_system.sum(), by_system.size())


def concurrency(rows: pd.DataFrame) -> float:
    """How many runs the measured sweep ran at once, on average: the sum of
    the wall times over the span from the first start to the last end (1.0
    without start times)."""
    rows = _measured(rows)
    start = pd.to_datetime(rows["started_at"].replace("", np.nan), errors="coerce", utc=True)
    good = start.notna()
    if good.sum() < 2:
        return 1.0
    end = start[good] + pd.to_timedelta(rows.loc[good, "wall_s"].astype(float), unit="s")
    span = (end.max() - start[good].min()).total_seconds()
    return float(rows.loc[good, "wall_s"].sum() / span) if span > 0 else 1.0
