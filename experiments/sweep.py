"""The seed paper's experiment matrix, system by system, into one CSV.

    sudo .venv/bin/python -m experiments.sweep --profile quick --jobs 2  # 420 runs: about an hour on 2 cores (58 min measured)
    sudo .venv/bin/python -m experiments.sweep --profile paper --jobs 1  # the full matrix: days
    .venv/bin/python -m experiments.sweep --profile paper --engine dask://HOST:8786  # on a Dask cluster

Each run is one ``coapkb bench --json`` child process (its own testbed, its
own namespaces), so a crash, a hang or a leaked thread in one run cannot
affect the next, and ``--jobs`` can run several at once.  Rows are appended to
``experiments/results/<profile>.csv`` as runs finish; a sweep that is stopped
and started again skips every run whose key (system, robots, tasks,
bandwidth, loss, rep, retransmission profile) is already in the CSV.

Parallel runs (``--jobs 2``) share the CPU: on two cores the robots' and the
KB server's processing time then grows.  ``experiments/concurrency.py``
measured two at a time on two cores within the one-at-a-time spread, so the
committed results ran two at a time (docs/benchmarks.md).

``--engine dask://HOST:PORT`` runs the same child processes as tasks on a
Dask distributed cluster instead (docs/benchmarks.md, "Running on a
cluster"): each task needs the worker resource ``netns`` (workers started
with ``--resources netns=N`` run at most N runs at once, as root), returns its
row, and this process appends the rows to the one CSV as they complete.  A
run whose worker is lost is retried by Dask on another worker; one the
cluster could not finish (or every run, if the scheduler goes away) is left
out of the CSV, so the next start runs it.  No key is ever appended twice.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import logging
import math
import signal
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import partial
from itertools import product
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from tqdm import tqdm

from coapkb.bench.linkemu import available, cleanup_stale
from coapkb.bench.run import (
    CLUSTER_SIZE,
    SYSTEMS,
    BenchRow,
    append_rows,
    done_keys,
    format_row,
    retransmission_label,
    security_label,
    timeouts_for,
)
from coapkb.errors import CoapkbError

ROOT = Path(__file__).resolve().parent.parent

RESULTS = ROOT / "experiments" / "results"
#: The Dask worker resource one run holds: its own network namespaces, and a
#: core's worth of the machine so runs on one worker do not skew each other's times.
NETNS = "netns"
#: How long to wait for the Dask scheduler before giving up (seconds).
CONNECT_TIMEOUT_S = 10.0


class EngineError(CoapkbError):
    """The engine cannot run the sweep (bad --engine, no scheduler, unfit workers); ``str()`` is for the user."""


@dataclass(frozen=True)
class Grid:
    """A full factorial block of the matrix."""

    robots: tuple[int, ...]
    tasks: tuple[int, ...]
    bandwidths: tuple[float, ...]
    losses: tuple[float, ...]
    systems: tuple[str, ...]
    #: Runs of this block go without the team's keys (``--insecure``): for
    #: peers that have no security to compare with (DDS from PyPI).
    insecure: bool = False


@dataclass(frozen=True)
class Profile:
    """A named union of grids, repeated ``reps`` times."""

    name: str
    grids: tuple[Grid, ...]
    reps: int = 1
    note: str = ""
    # The link beyond rate and loss, for every run of the profile (coapkb bench
    # --delay/--jitter/--loss-model/--burst-len); the defaults are the plain link.
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_model: str = "random"
    burst_len: float = 3.0


@dataclass(frozen=True)
class Run:
    system: str
    robots: int
    tasks: int
    bandwidth: float
    loss: float
    rep: int
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_model: str = "random"
    burst_len: float = 3.0
    #: The team's keys protect the messages (``coapkb bench`` without ``--insecure``).
    security: bool = True

    def row(self, **measured: Any) -> BenchRow:
        """This run's row: its identity (link columns as ``coapkb bench`` writes
        them, burst_len 0 for random loss) and ``measured``."""
        return BenchRow(
            system=self.system, robots=self.robots, tasks=self.tasks, bandwidth_kbps=self.bandwidth,
            loss_pct=self.loss, rep=self.rep,
            retransmission_profile=retransmission_label(self.system),
            delay_ms=self.delay_ms, jitter_ms=self.jitter_ms, loss_model=self.loss_model,
            burst_len=self.burst_len if self.loss_model == "burst" else 0.0,
            security=security_label(self.system, self.security), **measured,
        )

    def key(self) -> tuple[str, ...]:
        return self.row().key()

    @property
    def seed(self) -> int:
        """The task-list seed, ``coapkb bench``'s default for the repetition:
        every system of a cell and repetition does the same tasks (the pair)."""
        return 1 + self.rep

    def argv(self) -> list[str]:
        return [
            sys.executable, "-m", "coapkb", "bench", "--robots", str(self.robots), "--tasks", str(self.tasks),
            "--bandwidth", f"{self.bandwidth:g}", "--loss", f"{self.loss:g}", "--systems", self.system,
            "--first-rep", str(self.rep), "--reps", "1", "--seed", str(self.seed),
            "--json",
            "--delay", f"{self.delay_ms:g}", "--jitter", f"{self.jitter_ms:g}", "--loss-model", self.loss_model,
            "--burst-len", f"{self.burst_len:g}", *(() if self.security else ("--insecure",)),
        ]

    def label(self) -> str:
        return f"{self.system} {self.robots}r {self.tasks}t {self.bandwidth:g}k {self.loss:g}% rep{self.rep}"


#: The systems on the compact wire (named queries, CBOR answers), Zenoh over TCP included.
COMPACT_SYSTEMS = ("coap-distributed", "coap-central", "zmq-distributed", "zmq-central",
                   "zenoh-distributed", "zenoh-central")
#: The paper matrix keeps the systems it was first run with: Zenoh over
#: reliable UDP and over QUIC came later and are compared on their own
#: (docs/zenoh.md); the plain UDP link they replaced failed every lossy run.
PAPER_SYSTEMS = tuple(s for s in SYSTEMS if SYSTEMS[s].transport not in ("zenoh+udp", "zenoh+quic", "dds"))
QUICK_SYSTEMS = (*COMPACT_SYSTEMS, "seed-distributed")
#: What a team choosing in 2026 also asks about: Zenoh over QUIC and over its reliable UDP.
QUIC_SYSTEMS = ("zenoh-quic-distributed", "zenoh-quic-central", "zenoh-udp-distributed", "zenoh-udp-central")
QUIC_DISTRIBUTED = tuple(s for s in QUIC_SYSTEMS if s.endswith("-distributed"))
#: DDS (Cyclone DDS; its wheel has no DDS Security) and CoAP without OSCORE
#: beside it: both run --insecure in these cells.
DDS_VERSUS = ("coap-distributed", "dds-distributed")
#: The quick profile's cells.  Two things cost time at 20 % loss: CoAP's
#: retransmission timeouts and TCP connections the kernel gives up on, which
#: leave a query hanging until its timeout -- mostly on the seed's wire
#: (bigger messages).  So 20 % loss is sampled only in the seed's headline
#: setting (35 kbit/s, 5 tasks) and only for the compact systems; the seed's
#: wire, the bandwidth and the task-count axes are covered at 2 % loss.
QUICK_GRIDS = (
    # Fig. 6/7: bytes vs loss and team size at 35 kbit/s, 5 tasks (the seed's headline setting).
    Grid((3, 9), (5,), (35,), (2, 20), COMPACT_SYSTEMS),
    Grid((3, 9), (5,), (35,), (2,), ("seed-distributed",)),
    # The seed's own centralised baseline, for its ~42 % claim on its own stack.
    Grid((3,), (5,), (35,), (2,), ("seed-central",)),
    # Fig. 8-10: tasks 5 and 20 at both bandwidths, 2 % loss.
    Grid((3,), (5, 20), (35, 256), (2,), QUICK_SYSTEMS),
    # Fig. 11/12: tasks 5 and 20 for 9 robots too (35 kbit/s, 2 %).
    Grid((9,), (20,), (35,), (2,), QUICK_SYSTEMS),
    # The 2026 peers in the cells of their comparison (docs/results.md): 3 robots,
    # 5 tasks, 35 kbit/s at 2 and 20 %, 256 kbit/s at 2 %; distributed, as
    # the targets are (a central server over QUIC gets one cell).
    Grid((3,), (5,), (35,), (2, 20), QUIC_DISTRIBUTED),
    Grid((3,), (5,), (256,), (2,), QUIC_DISTRIBUTED),
    Grid((3,), (5,), (35,), (2,), ("zenoh-quic-central",)),
    # DDS in the same cells, against plain CoAP (no DDS Security to compare with).
    Grid((3,), (5,), (35,), (2, 20), DDS_VERSUS, insecure=True),
    Grid((3,), (5,), (256,), (2,), DDS_VERSUS, insecure=True),
    Grid((3,), (5,), (35,), (2,), ("coap-central", "dds-central"), insecure=True),
)
SCALE_SIZES = (3, 9, 30, 60, 99)
SCALE_SYSTEMS = ("coap-distributed", "coap-central", "zmq-distributed", "zmq-central")
PROFILES: dict[str, Profile] = {
    # A representative subset, 6 repetitions of every cell (the fewest with
    # a distribution-free 95 % interval for a median): 420 runs, about an
    # hour on 2 cores two at a time (docs/benchmarks.md).
    "quick": Profile(
        "quick",
        QUICK_GRIDS,
        reps=6,
        note="subset: 35 kbit/s x 5 tasks x robots 3/9 x loss 2/20 % (the seed's wire at 2 % only); at 2 %: "
        "3 robots x tasks 5/20 x 35/256 kbit/s, 9 robots x 20 tasks x 35 kbit/s",
    ),
    # The part of the paper matrix this 2-core machine ran in two sessions
    # (about three hours two at a time): the quick cells, the seed's loss
    # axis (Fig. 6/7) whole for every team size, its bandwidth axis whole at
    # 10 tasks, and its task axis whole at 3 robots.  6 repetitions: the
    # fewest with a distribution-free 95 % interval for a median.  Its CSV
    # starts from the quick profile's rows (same keys).
    "slice": Profile(
        "slice",
        (
            *QUICK_GRIDS,
            Grid((3, 6, 9), (5,), (35,), (2, 5, 10, 15, 20), COMPACT_SYSTEMS),
            Grid((3,), (10,), (35, 128, 256, 512), (2,), QUICK_SYSTEMS),
            Grid((3,), (40, 80), (35,), (2,), QUICK_SYSTEMS),
        ),
        reps=6,
        note="the quick cells; 35 kbit/s x 5 tasks x robots 3/6/9 x loss 2/5/10/15/20 % (compact systems); "
        "3 robots x 10 tasks x 35/128/256/512 kbit/s at 2 % (with the seed's wire); "
        "3 robots x 40/80 tasks x 35 kbit/s at 2 % (with the seed's wire)",
    ),
    # Team size, past the seed's nine robots: five tasks per cluster of three
    # (the seed's headline cell, once per cluster), so a robot's own work is
    # the same at every size and what grows is only the team around it.
    # One run at a time: 99 robot processes fill both cores.
    "scale": Profile(
        "scale",
        tuple(Grid((n,), (5 * n // 3,), (35,), (2, 10), SCALE_SYSTEMS) for n in SCALE_SIZES),
        reps=1,
        note="robots 3/9/30/60/99 x 5 tasks per cluster x 35 kbit/s x loss 2/10 %, CoAP and ZeroMQ, "
        "distributed and central",
    ),
    # The seed's whole matrix (section IV), every system but Zenoh over UDP and QUIC.
    "paper": Profile(
        "paper",
        (Grid((3, 6, 9), (5, 10, 20, 40, 80), (35, 128, 256, 512), (2, 5, 10, 15, 20), PAPER_SYSTEMS),),
        reps=3,
        note="the seed's full matrix: robots 3/6/9, tasks 5-80, 35-512 kbit/s, 2-20 % loss",
    ),
}


def plan(profile: Profile, reps: int | None = None,
         systems: Sequence[str] | None = None, security: bool = True) -> list[Run]:
    """Every run of the profile, in order: repetition, then setting, then system
    (so a half-finished sweep has all systems of the settings it reached)."""
    seen: set[tuple[str, ...]] = set()
    runs: list[Run] = []
    for rep in range(reps if reps is not None else profile.reps):
        settings = sorted({
            (r, t, b, loss)
            for g in profile.grids
            for r, t, b, loss in product(g.robots, g.tasks, g.bandwidths, g.losses)
        })
        for r, t, b, loss in settings:
            for g in profile.grids:
                if r not in g.robots or t not in g.tasks or b not in g.bandwidths or loss not in g.losses:
                    continue
                for s in g.systems:
                    if systems is not None and s not in systems:
                        continue
                    run = Run(s, r, t, float(b), float(loss), rep, profile.delay_ms,
                              profile.jitter_ms, profile.loss_model, profile.burst_len, security and not g.insecure)
                    if run.key() not in seen:
                        seen.add(run.key())
                        runs.append(run)
    return runs


def pending(runs: Iterable[Run], done: set[tuple[str, ...]]) -> list[Run]:
    """The runs whose key is not in ``done`` (resume)."""
    return [r for r in runs if r.key() not in done]


def units(run: Run) -> int:
    """A run's length in units of one task per cluster, plus one for start-up:
    what the progress bar counts, so an 80-task run weighs 16 times a 5-task
    one and the ETA follows."""
    return math.ceil(run.tasks / (run.robots // CLUSTER_SIZE)) + 1


def limit_for(run: Run) -> float:
    """How long a run may take before the sweep kills it (its own timeouts plus start-up and teardown)."""
    clusters = run.robots // CLUSTER_SIZE
    central = clusters if SYSTEMS[run.system].mode == "central" else 0
    return timeouts_for(run.bandwidth, run.loss, math.ceil(run.tasks / clusters), central).run_s + 180


async def _run_child(run: Run, limit_s: float, cwd: Path = ROOT) -> BenchRow:
    """One ``coapkb bench --json`` child; its row, or a failed row if it died or hung."""
    proc = await asyncio.create_subprocess_exec(
        *run.argv(), stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=cwd,
        start_new_session=True,  # Ctrl-C reaches the sweep, which then stops its children itself
    )
    try:
        out, err = await asyncio.wait_for(proc.communicate(), limit_s)
    except (TimeoutError, asyncio.CancelledError) as exc:
        await _stop(proc)
        if isinstance(exc, asyncio.CancelledError):
            raise
        out, err = b"", f"killed after {limit_s:.0f} s".encode()
    for line in reversed(out.decode(errors="replace").splitlines()):
        if line.startswith("{"):
            return BenchRow.from_dict(json.loads(line))
    tail = " | ".join(err.decode(errors="replace").strip().splitlines()[-3:])
    system = SYSTEMS[run.system]
    return run.row(
        ok=False, mode=system.mode, transport=system.transport, query_wire=system.query_wire, emulation="netns",
        seed=run.seed,
        error=f"bench child exited {proc.returncode}: {tail or 'no output'}"[:500],
    )


async def _stop(proc: asyncio.subprocess.Process) -> None:
    """SIGTERM (the child's testbed tears its namespaces down), then SIGKILL."""
    if proc.returncode is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        await asyncio.wait_for(proc.wait(), 20)
    except TimeoutError:
        proc.kill()
        await proc.wait()


class Progress:
    """Rows into the CSV as runs finish, each key at most once, with a bar on
    a terminal's stderr and one line per run on stdout with the count,
    elapsed time and ETA (for a log).  ``done_runs`` are the profile's runs
    already in the CSV."""

    def __init__(self, out: Path, runs: Sequence[Run], done_runs: Sequence[Run]) -> None:
        self.out = out
        self.total = len(runs) + len(done_runs)
        self.done_before = len(done_runs)
        self.finished = 0
        self.failed = 0
        self.lost = 0
        self._written: set[tuple[str, ...]] = set()
        # The ETA is the remaining units at the mean rate so far (tqdm's smoothing=0):
        # runs of one sweep are interleaved by setting, so the mean is a fair guess.
        # The log line counts for itself: a tqdm without a terminal (a log) keeps no time.
        self.units_total = sum(map(units, [*done_runs, *runs]))
        self.units_before = self.units_done = sum(map(units, done_runs))
        self.t0 = time.monotonic()
        self.bar = tqdm(total=self.units_total, initial=self.units_before, unit="task",
                        desc="sweep", file=sys.stderr, smoothing=0, disable=None)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.close()

    def record(self, run: Run, row: BenchRow) -> None:
        """Append ``row`` unless this sweep already wrote ``run``'s key (an
        engine that delivers a run twice, e.g. after a retry, adds nothing)."""
        if run.key() in self._written:
            self._log(f"{run.label()}: already recorded, second result dropped")
            return
        append_rows(self.out, [row])
        self._written.add(run.key())
        self.finished += 1
        self.failed += not row.ok
        self.bar.update(units(run))
        self.units_done += units(run)
        self._log(format_row(row))

    def missing(self, run: Run, why: str) -> None:
        """A run the engine could not finish: nothing is written, so the next start runs it."""
        self.lost += 1
        self._log(f"{run.label()}: NOT RUN ({why}); left for the next start")

    def _log(self, text: str) -> None:
        count = self.done_before + self.finished
        elapsed = time.monotonic() - self.t0
        rate = (self.units_done - self.units_before) / elapsed if elapsed > 0 else 0.0
        eta = tqdm.format_interval((self.units_total - self.units_done) / rate) if rate > 0 else "?"
        times = f"{tqdm.format_interval(elapsed)} ETA {eta}"
        self.bar.write(f"[{count}/{self.total} {100 * count / self.total:3.0f}%] {times} | {text}", file=sys.stdout)
        sys.stdout.flush()


async def sweep(runs: list[Run], out: Path, jobs: int, done_runs: list[Run]) -> int:
    """Run ``runs`` on this machine (``jobs`` at a time), appending each row to
    ``out`` as it finishes (see :class:`Progress`).  Returns failed runs."""
    queue: asyncio.Queue[Run] = asyncio.Queue()
    for r in runs:
        queue.put_nowait(r)

    async def worker(progress: Progress) -> None:
        while not queue.empty():
            run = queue.get_nowait()
            progress.record(run, await _run_child(run, limit_for(run)))

    with Progress(out, runs, done_runs) as progress:
        await asyncio.gather(*(worker(progress) for _ in range(max(1, jobs))))
    return progress.failed


# --------------------------------------------------------------------------- the Dask engine


@dataclass(frozen=True)
class Engine:
    """Where the runs go: this machine, or a Dask scheduler at ``address``."""

    kind: Literal["local", "dask"]
    address: str = ""

    def __str__(self) -> str:
        return "local" if self.kind == "local" else f"Dask scheduler {self.address}"


def parse_engine(text: str) -> Engine:
    """``local`` or ``dask://HOST:PORT`` (the scheduler's TCP address); EngineError otherwise."""
    if text == "local":
        return Engine("local")
    expected = f"--engine: expected 'local' or 'dask://HOST:PORT', got {text!r}"
    url = urlsplit(text)
    try:
        port = url.port
    except ValueError:
        raise EngineError(expected) from None
    if url.scheme != "dask" or not url.hostname or port is None or url.path not in ("", "/") or url.query:
        raise EngineError(expected)
    host = f"[{url.hostname}]" if ":" in url.hostname else url.hostname
    return Engine("dask", f"tcp://{host}:{port}")


def run_on_worker(run: Run, limit_s: float) -> dict[str, Any]:
    """The Dask task: ``run`` as a ``coapkb bench`` child of the worker, with
    the worker's own Python and checkout; its row as plain data (the client
    may run another version of the row class)."""
    import coapkb  # the worker's checkout, not the client's path

    ok, _ = available()
    if not ok:
        # A worker that joined mid-sweep may be given a run before its gate
        # (_link_emulation_gate) took its slots away: the run goes elsewhere.
        from distributed import Reschedule

        raise Reschedule()
    row = asyncio.run(_run_child(run, limit_s, cwd=Path(coapkb.__file__).resolve().parent.parent))
    return row.to_dict()


def _prepare_worker() -> tuple[bool, str, int]:
    """On each worker before the sweep: can it emulate links, and the stale namespaces it removed."""
    ok, why = available()
    return ok, why, len(cleanup_stale()) if ok else 0


def _link_emulation_gate() -> Any:
    """A Dask worker plugin for workers that join after the sweep started
    (those present are checked by :func:`_prepare_worker`, and the sweep
    stops if one is unfit): a worker that cannot emulate links gives up its
    ``netns`` slots, so no run lands there, and logs why."""
    from distributed import WorkerPlugin

    class LinkEmulationGate(WorkerPlugin):
        name = "coapkb-link-emulation"

        async def setup(self, worker: Any) -> None:
            ok, why, removed = _prepare_worker()
            log = logging.getLogger("coapkb.sweep")
            if ok:
                if removed:
                    log.warning("removed %d namespaces left by crashed runs", removed)
                return
            log.error("this worker takes no sweep runs: %s", why)
            await worker.set_resources(**{NETNS: 0})

    return LinkEmulationGate()


class _Shipped:
    """A call that travels to the workers *by value*: Dask pickles tasks with
    plain pickle, which would name this module (``__main__`` when run with
    ``-m``; a worker has neither that nor, necessarily, this checkout's
    ``experiments``), so the call pickles as its cloudpickle bytes and
    arrives as the bare call."""

    def __init__(self, call: Callable[[], Any]) -> None:
        self.call = call

    def __call__(self) -> Any:
        return self.call()

    def __reduce__(self) -> tuple[Any, ...]:
        import cloudpickle

        return cloudpickle.loads, (cloudpickle.dumps(self.call),)


def task_key(run: Run) -> str:
    """The run's Dask key: two clients submitting the same run share one task."""
    return "coapkb-run-" + hashlib.sha1("\x1f".join(run.key()).encode()).hexdigest()[:20]


async def sweep_dask(runs: list[Run], out: Path, address: str, done_runs: list[Run],
                     connect_timeout_s: float = CONNECT_TIMEOUT_S) -> tuple[int, int]:
    """Run ``runs`` on the Dask cluster at ``address``, one task per run holding
    one ``netns`` resource, appending rows as they complete.  Returns (failed
    runs, runs not run).  EngineError when the cluster cannot take the sweep."""
    try:
        import cloudpickle
        from distributed import Client, as_completed
    except ImportError:
        raise EngineError("--engine dask:// needs Dask: .venv/bin/pip install -e '.[bench]'") from None
    # The workers cannot import this module (``__main__`` under ``-m``, and a worker
    # needs only coapkb): cloudpickle ships its functions and Run by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        client = await Client(address, asynchronous=True, timeout=connect_timeout_s)
    except (OSError, TimeoutError) as exc:
        raise EngineError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
    async with client:
        workers = (await client.scheduler.identity(n_workers=-1))["workers"]
        slots = sum(w.get("resources", {}).get(NETNS, 0) for w in workers.values())
        print(f"{address}: {len(workers)} workers, {slots:g} run slots (resource {NETNS})", flush=True)
        if not slots:
            print(f"sweep: no worker offers the resource {NETNS!r} yet; runs wait for workers started with "
                  f"`dask worker {address} --nthreads 1 --resources {NETNS}=1` (as root)",
                  file=sys.stderr, flush=True)
        checked = await client.run(_Shipped(_prepare_worker))
        unfit = {w: why for w, (ok, why, _) in checked.items() if not ok}
        removed = sum(n for _, _, n in checked.values())
        if removed:
            print(f"workers removed {removed} namespaces left by crashed runs", flush=True)
        if unfit:
            raise EngineError("workers without kernel link emulation (not root?): "
                              + "; ".join(f"{w}: {why}" for w, why in sorted(unfit.items())))
        await client.register_plugin(_link_emulation_gate())
        futures = {
            client.submit(_Shipped(partial(run_on_worker, run, limit_for(run))), key=task_key(run),
                          resources={NETNS: 1}, priority=len(runs) - i): run  # the plan's order, as locally
            for i, run in enumerate(runs)
        }
        with Progress(out, runs, done_runs) as progress:
            async for future in as_completed(futures):
                run = futures[future]
                try:
                    data = await future
                except asyncio.CancelledError:
                    if future.status != "cancelled":  # this sweep was cancelled (Ctrl-C), not the task
                        raise
                    progress.missing(run, "cancelled")
                except Exception as exc:  # noqa: BLE001 - KilledWorker (it killed every worker it was tried on), a lost scheduler
                    if client.status != "running" or "connection-lost" in str(exc):
                        # The scheduler is gone: every other future fails the same way, and the
                        # client's reconnection attempt would log a traceback when we close it.
                        logging.getLogger("distributed.client").setLevel(logging.CRITICAL)
                    first_line = (str(exc).strip().splitlines() or [""])[0]
                    progress.missing(run, f"{type(exc).__name__}: {first_line}"[:200])
                else:
                    progress.record(run, BenchRow.from_dict(data))
    return progress.failed, progress.lost


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.sweep",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--profile", choices=tuple(PROFILES), default="quick")
    p.add_argument("--jobs", type=int, default=1, help="runs at once (default 1; more distorts timings); local engine")
    p.add_argument("--engine", default="local", metavar="local|dask://HOST:PORT",
                   help="where runs go: this machine (default) or a Dask scheduler's workers (their --resources "
                        f"{NETNS}=N set how many at once per worker)")
    p.add_argument("--connect-timeout", type=float, default=CONNECT_TIMEOUT_S, metavar="S",
                   help=f"how long to try the Dask scheduler before giving up (default {CONNECT_TIMEOUT_S:g} s)")
    p.add_argument("--out", type=Path, help="CSV (default experiments/results/<profile>.csv)")
    p.add_argument("--reps", type=int, help="override the profile's repetitions")
    p.add_argument("--systems", help="only these systems (comma-separated)")
    p.add_argument("--insecure", action="store_true",
                   help="runs without the team's keys (coapkb bench --insecure), for comparison")
    p.add_argument("--retry-failed", action="store_true", help="run again the keys whose row has ok=False")
    p.add_argument("--dry-run", action="store_true", help="list the pending runs and exit")
    args = p.parse_args(argv)
    try:
        engine = parse_engine(args.engine)
    except EngineError as exc:
        print(f"sweep: {exc}", file=sys.stderr)
        return 2
    profile = PROFILES[args.profile]
    out = args.out or RESULTS / f"{profile.name}.csv"
    systems = None
    if args.systems:
        systems = [s.strip() for s in args.systems.split(",") if s.strip()]
        unknown = [s for s in systems if s not in SYSTEMS]
        if unknown:
            p.error(f"unknown systems: {', '.join(unknown)}")
    runs = plan(profile, args.reps, systems, security=not args.insecure)
    todo = pending(runs, done_keys(out, include_failed=not args.retry_failed))
    waiting = set(todo)
    done_runs = [r for r in runs if r not in waiting]
    print(f"profile {profile.name}: {len(runs)} runs ({profile.note}); {len(runs) - len(todo)} already in {out}, "
          f"{len(todo)} to go, " + (f"{args.jobs} at a time" if engine.kind == "local" else f"on the {engine}"),
          flush=True)
    if args.dry_run:
        with contextlib.suppress(BrokenPipeError):  # `... --dry-run | head`
            for r in todo:
                print("  " + r.label())
        return 0
    if not todo:
        return 0
    if engine.kind == "local":  # a Dask worker checks its own machine (_prepare_worker)
        ok, why = available()
        if not ok:
            print(f"sweep: no kernel link emulation here: {why}", file=sys.stderr)
            return 2
        removed = cleanup_stale()
        if removed:
            print(f"removed {len(removed)} namespaces left by crashed runs", flush=True)
    t0 = time.monotonic()
    lost = 0
    try:
        if engine.kind == "local":
            failed = asyncio.run(sweep(todo, out, args.jobs, done_runs))
        else:
            failed, lost = asyncio.run(sweep_dask(todo, out, engine.address, done_runs, args.connect_timeout))
    except EngineError as exc:
        print(f"sweep: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ninterrupted; finished rows are kept, run again to resume", file=sys.stderr)
        return 130
    print(f"done in {tqdm.format_interval(time.monotonic() - t0)} ({time.monotonic() - t0:.0f} s): "
          f"{len(todo) - failed - lost} ok, {failed} failed"
          + (f", {lost} not run (run again to resume)" if lost else "") + f"; rows in {out}", flush=True)
    return 1 if failed or lost else 0


if __name__ == "__main__":
    sys.exit(main())
