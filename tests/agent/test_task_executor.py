"""Task Executor: the simulated drive, pick and unload of each job, in order,
timed by the execution model and published as live state (a fast clock: no waiting)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import pytest

from coapkb.agent.job import Job
from coapkb.agent.robot_state import LiveState
from coapkb.agent.stats import Recharge
from coapkb.agent.task_assigner import ChargeStop
from coapkb.agent.task_executor import TaskExecutor
from coapkb.config import ExecutionModel
from coapkb.world import Position

MODEL = ExecutionModel(speed_m_s=2.0, pick_s=4.0, time_scale=10.0)


class FastClock:
    """Records each simulated wait (wall-clock seconds) and returns at once."""

    def __init__(self) -> None:
        self.waits: list[float] = []

    async def sleep(self, seconds: float) -> None:
        self.waits.append(seconds)
        await asyncio.sleep(0)  # let the publisher and the test see each step


def _job(seq: int, to_object_m: float, to_depot_m: float = 0.0) -> Job:
    return Job(seq, f"Thing_{seq}", aisle=3, rack=7, to_object_m=to_object_m, to_depot_m=to_depot_m, depot=(1, 0))


async def _run(jobs: list[Job], lease: Callable[[float], Awaitable[str | None]] | None = None,
               ) -> tuple[TaskExecutor, list[LiveState], FastClock]:
    published: list[LiveState] = []
    clock = FastClock()
    executor = TaskExecutor(MODEL, LiveState(1.0, 0.0), published.append, sleep=clock.sleep, lease=lease)
    executor.start()
    try:
        for job in jobs:
            executor.submit(job)
        await asyncio.wait_for(executor.wait_idle(), 1)
    finally:
        await executor.aclose()
    return executor, published, clock


async def test_a_job_drives_picks_and_ends_idle_at_the_object() -> None:
    executor, published, clock = await _run([_job(1, to_object_m=30.0)])
    # 30 m at 2 m/s = 15 s, then a 4 s pick; time runs 10x faster than the wall clock.
    assert clock.waits == pytest.approx([1.5, 0.4])
    # Done counts once the pick is over (then, at the object, idle).
    assert [(s.activity, s.done) for s in published] == [
        ("idle", 0), ("travelling", 0), ("picking", 0), ("picking", 1), ("idle", 1)]
    assert published[0].queued == 1 and published[1].executing == "Thing_1"
    assert (executor.live.aisle, executor.live.rack, executor.live.done) == (3.0, 7.0, 1)
    assert executor.live.executing is None and executor.live.queued == 0


async def test_an_unload_drives_to_the_depot_after_the_pick() -> None:
    executor, published, clock = await _run([_job(1, to_object_m=10.0, to_depot_m=20.0)])
    assert clock.waits == pytest.approx([0.5, 0.4, 1.0])
    assert "unloading" in [s.activity for s in published]
    assert (executor.live.aisle, executor.live.rack) == (1.0, 0.0)


async def test_queued_jobs_run_in_order_without_going_idle_between() -> None:
    executor, published, clock = await _run([_job(1, 2.0), _job(2, 4.0), _job(3, 6.0)])
    assert clock.waits[::2] == pytest.approx([0.1, 0.2, 0.3])
    assert executor.live.done == 3
    done_states = [s for s in published if s.executing is None and s.done > 0]
    assert [s.activity for s in done_states] == ["travelling", "travelling", "idle"]


async def test_wait_idle_returns_at_once_with_nothing_to_do() -> None:
    executor = TaskExecutor(MODEL, LiveState(1.0, 0.0), lambda live: None)
    await asyncio.wait_for(executor.wait_idle(), 0.1)


class Fence:
    """A lease that holds for the first ``grants`` asks, then is refused."""

    def __init__(self, grants: int) -> None:
        self.grants = grants
        self.asked: list[float] = []

    async def hold(self, for_s: float, task: int = 0) -> str | None:
        self.asked.append(for_s)
        return None if len(self.asked) <= self.grants else "no lease from a majority of the cluster (Robot2: refused)"


async def test_a_pick_needs_the_lease_before_and_after_it() -> None:
    executor, published, _ = await _run([_job(1, 2.0), _job(2, 4.0)], Fence(grants=4).hold)
    assert executor.live.done == 2 and not executor.live.fenced
    assert "picking" in [s.activity for s in published]


async def test_a_refused_lease_drops_the_job_and_the_queue_unpicked() -> None:
    # Granted before the first pick, refused when it is over (frozen past its lease meanwhile).
    executor, published, _ = await _run([_job(1, 2.0), _job(2, 4.0), _job(3, 6.0)], Fence(grants=1).hold)
    assert executor.live.done == 0
    assert executor.live.fenced == (1, 2, 3) and "Robot2: refused" in (executor.live.fence_reason or "")
    assert (executor.live.activity, executor.live.queued, executor.live.executing) == ("idle", 0, None)
    # A job given after the fence is dropped too (the lease is asked again, and refused).
    fence = Fence(grants=0)
    executor, published, _ = await _run([_job(4, 2.0)], fence.hold)
    assert executor.live.fenced == (4,) and "picking" not in [s.activity for s in published]


async def test_jobs_before_a_join_are_dropped_even_under_a_lease() -> None:
    """A robot its teammates left out joins them again at task 5: the jobs
    of earlier tasks went round again, so it picks none of them, though its
    teammates grant the lease again (they decided those tasks with it a
    member); a job of task 5 or later is its own."""
    published: list[LiveState] = []
    travelling, go_on = asyncio.Event(), asyncio.Event()

    async def sleep(seconds: float) -> None:
        travelling.set()
        await go_on.wait()

    async def lease(for_s: float, task: int = 0) -> str | None:
        return None  # always granted: only the join stops these picks

    executor = TaskExecutor(MODEL, LiveState(1.0, 0.0), published.append, sleep=sleep, lease=lease)
    executor.submit(_job(1, 2.0))
    executor.submit(_job(2, 4.0))
    executor.start()
    try:
        await asyncio.wait_for(travelling.wait(), 1)  # job 1 under way, job 2 queued
        executor.void_before(5, "joined its team again at task 5")
        assert executor.live.fenced == (2,) and executor.live.queued == 0
        executor.submit(_job(3, 2.0))  # decided late: a task before the join
        executor.submit(_job(5, 2.0))
        go_on.set()
        await asyncio.wait_for(executor.wait_idle(), 1)  # idle only once job 5, the last, is done
        assert executor.live.fenced == (2, 1, 3) and executor.live.done == 1
        assert [s.executing for s in published if s.activity == "picking"][-1] == "Thing_5"
    finally:
        await executor.aclose()


async def test_a_charge_stop_drives_to_the_dock_charges_then_does_the_task() -> None:
    stop = ChargeStop(Position(3, 11), to_dock_m=20.0, arrive_wh=25.0, full_wh=400.0, charge_s=600.0)
    job = Job(1, "Thing_1", aisle=3, rack=7, to_object_m=10.0, to_depot_m=0.0, depot=(1, 0), charge=stop)
    executor, published, clock = await _run([job])
    # 20 m to the dock at 2 m/s, 600 s charging, 10 m to the object, a 4 s pick; all 10x faster.
    assert clock.waits == pytest.approx([1.0, 60.0, 0.5, 0.4])
    activities = [s.activity for s in published]
    assert activities.index("charging") < activities.index("picking")
    charging = next(s for s in published if s.activity == "charging")
    assert (charging.aisle, charging.rack) == (3.0, 11.0)
    assert executor.recharges == [Recharge(1, (3, 11), 25.0, 400.0)]
    assert (executor.live.aisle, executor.live.rack, executor.live.done) == (3.0, 7.0, 1)
