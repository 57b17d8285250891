"""Task Executor: the simulated drive, pick and unload of each job, in order,
timed by the execution model and published as live state (a fast clock: no waiting)."""

from __future__ import annotations

import asyncio

import pytest

from coapkb.agent.robot_state import LiveState
from coapkb.agent.task_executor import Job, TaskExecutor
from coapkb.config import ExecutionModel

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


async def _run(jobs: list[Job]) -> tuple[TaskExecutor, list[LiveState], FastClock]:
    published: list[LiveState] = []
    clock = FastClock()
    executor = TaskExecutor(MODEL, LiveState(1.0, 0.0), published.append, sleep=clock.sleep)
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
    assert [s.activity for s in published] == ["idle", "travelling", "picking", "idle"]
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
