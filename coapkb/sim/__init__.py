"""The whole team in a deterministic simulator (``coapkb sim``).

The real robots and feeder run in one OS process on a virtual clock
(:mod:`.loop`), over a simulated network with seeded faults
(:mod:`.network`), under a fault schedule drawn from a seed
(:mod:`.faults`); each run's history is judged against the invariants
(:mod:`.invariants`).  A seed replays its run exactly: same schedule, same
messages, same trace.  docs/simulation.md says how to run, replay and
extend it.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
from collections.abc import Generator, Iterable
from dataclasses import replace
from pathlib import Path
from typing import TextIO

from ..feeder.record import FateCounts
from .faults import FaultMix, FaultSpecError, Schedule
from .invariants import check
from .loop import SimulationError
from .run import KBCache, RunResult, SimSpec, run_seed

__all__ = [
    "FaultMix", "FaultSpecError", "KBCache", "RunResult", "Schedule", "SimSpec", "SimulationError",
    "run_checked", "run_many",
]


def run_checked(spec: SimSpec, seed: int, kbs: KBCache, trace: TextIO | None = None) -> RunResult:
    """Run seed ``seed`` and judge it."""
    return check(run_seed(spec, seed, kbs, trace))


def summary(run: RunResult) -> RunResult:
    """``run`` without its history (what a worker sends back): its fates in one line instead."""
    fates = FateCounts.of(run.record.tasks).line() if run.record is not None else "no record"
    coordination = [t.coordination_s for t in run.record.tasks] if run.record is not None else []
    return replace(run, record=None, picks=[], bounds={}, fates=fates, coordination_s=coordination)


# One KB cache per worker process: loaded once, read by every run there.
_worker_kbs: KBCache | None = None


def _work(job: tuple[SimSpec, int, str]) -> RunResult:
    global _worker_kbs
    spec, seed, scratch = job
    if _worker_kbs is None:
        _worker_kbs = KBCache(Path(scratch))
    return summary(run_checked(spec, seed, _worker_kbs))


def run_many(spec: SimSpec, seeds: Iterable[int], jobs: int | None = None) -> Generator[RunResult, None, None]:
    """One checked run per seed, spread over ``jobs`` worker processes (the
    cores by default); results in seed order, each as soon as it and those
    before it are done."""
    work = [(spec, seed) for seed in seeds]
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(work)))
    if jobs == 1:
        kbs = KBCache()
        for job in work:
            yield summary(run_checked(job[0], job[1], kbs))
        return
    # Forked workers inherit the parent's hash seed, so their runs match a
    # replay.  The pool ends its workers without their cleanup: the folder
    # they generate KBs in is this process's, removed once the pool is over.
    with (tempfile.TemporaryDirectory(prefix="coapkb-sim-") as scratch,
          multiprocessing.get_context("fork").Pool(jobs) as pool):
        yield from pool.imap(_work, [(spec, seed, scratch) for spec, seed in work], chunksize=4)
