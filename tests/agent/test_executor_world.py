"""The Task Executor at the shelf: what the world says there (an object
misplaced or already taken ends its task as not found, published in
``missed``) and what the robot then writes into the team's knowledge (a
pick, a delivery, a missing object).  A fast clock: no waiting."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest

from coapkb.agent.job import Job
from coapkb.agent.robot_state import LiveState
from coapkb.agent.task_executor import MISSED_KEPT, TaskExecutor
from coapkb.config import ExecutionModel
from coapkb.world.service import WorldUnavailable
from coapkb.world.truth import Taken, WorldTruth

MODEL = ExecutionModel(speed_m_s=2.0, pick_s=4.0, time_scale=10.0)
MISPLACED = "not where the KB says it is (misplaced)"
BAG, TV, PASTA = "Gucci_bag_14", "Canon_tv_538", "Barilla_pasta_1"


class FastClock:
    """Records each simulated wait (wall-clock seconds) and returns at once."""

    def __init__(self) -> None:
        self.waits: list[float] = []

    async def sleep(self, seconds: float) -> None:
        self.waits.append(seconds)
        await asyncio.sleep(0)


class Knowledge:
    """Stands for the KnowledgeWriter: what the executor reports, in order."""

    def __init__(self) -> None:
        self.facts: list[tuple[str, tuple[object, ...]]] = []
        self.flushes = 0

    def picked(self, job: Job, *rest: object) -> None:
        self.facts.append(("picked", (job.seq,)))

    def missing(self, job: Job, *rest: object) -> None:
        self.facts.append(("missing", (job.seq,)))

    def delivered(self, jobs: list[Job], *rest: object) -> None:
        self.facts.append(("delivered", tuple(job.seq for job in jobs)))

    def load(self, *args: object) -> None:  # what a robot carries after the job, where written
        pass

    def flush(self) -> None:  # the robot turns idle: what waits goes out
        self.flushes += 1

    async def drained(self) -> None:
        pass


class Unreachable:
    """A world whose socket does not answer."""

    def __init__(self) -> None:
        self.asked = 0

    async def take(self, obj: str, robot: str, seq: int) -> str | None:
        self.asked += 1
        raise WorldUnavailable("the world at /tmp/world.sock does not answer: timed out")


def _job(seq: int, obj: str, to_depot_m: float = 0.0) -> Job:
    return Job(seq, obj, aisle=3, rack=7, to_object_m=30.0, to_depot_m=to_depot_m, depot=(1, 0))


class Run:
    def __init__(self, executor: TaskExecutor, published: list[LiveState], clock: FastClock,
                 knowledge: Knowledge) -> None:
        self.executor, self.published, self.clock, self.knowledge = executor, published, clock, knowledge


@pytest.fixture
async def run() -> AsyncIterator[Callable]:
    """``await run(jobs, world, robot_id)``: the executor once it has done ``jobs``."""
    started: list[TaskExecutor] = []

    async def execute(jobs: list[Job], world: object, robot_id: str = "Robot1",
                      knowledge: Knowledge | None = None,
                      lease: Callable[[float], Awaitable[str | None]] | None = None) -> Run:
        published: list[LiveState] = []
        clock = FastClock()
        knowledge = knowledge if knowledge is not None else Knowledge()
        executor = TaskExecutor(MODEL, LiveState(1.0, 0.0), published.append, sleep=clock.sleep,
                                lease=lease, robot_id=robot_id, world=world,  # type: ignore[arg-type]
                                knowledge=knowledge)  # type: ignore[arg-type]
        started.append(executor)
        executor.start()
        for job in jobs:
            executor.submit(job)
        await asyncio.wait_for(executor.wait_idle(), 1)
        return Run(executor, published, clock, knowledge)

    yield execute
    for executor in started:
        await executor.aclose()


async def test_an_object_not_at_the_shelf_ends_its_task_as_not_found(run: Callable) -> None:
    world = WorldTruth.with_misplaced([PASTA])
    r = await run([_job(4, PASTA)], world)
    live = r.executor.live
    assert live.done == 1 and live.missed == ((4, MISPLACED),)  # done: the robot went there
    assert r.knowledge.facts == [("missing", (4,))] and r.knowledge.flushes == 1  # idle: sent what waited
    # It drove there and reached for it (the pick's time: it looks only under its lease), and took nothing.
    assert r.clock.waits == pytest.approx([1.5, MODEL.pick_s / MODEL.time_scale])
    assert [(s.activity, s.done, s.missed) for s in r.published][-2:] == [
        ("picking", 1, ((4, MISPLACED),)), ("idle", 1, ((4, MISPLACED),))]
    assert world.taken == {}


async def test_a_pick_is_written_and_taken_in_the_world(run: Callable) -> None:
    world = WorldTruth()
    r = await run([_job(1, BAG)], world)
    assert r.executor.live.done == 1 and r.executor.live.missed == ()
    assert r.knowledge.facts == [("picked", (1,))]
    assert world.taken == {BAG: Taken("Robot1", 1)}
    assert r.clock.waits == pytest.approx([1.5, 0.4])


async def test_an_unload_delivers_what_the_robot_carries(run: Callable) -> None:
    world = WorldTruth.with_misplaced([PASTA])
    r = await run([_job(1, BAG), _job(2, PASTA), _job(3, TV, to_depot_m=20.0), _job(4, BAG, to_depot_m=20.0)],
                  world)
    # Task 2 was not there; task 4's bag is gone (task 1 took it): nothing to deliver then.
    assert r.knowledge.facts == [("picked", (1,)), ("missing", (2,)), ("picked", (3,)), ("delivered", (1, 3)),
                                 ("missing", (4,))]
    assert r.executor.live.missed == ((2, MISPLACED), (4, "gone: picked by Robot1 at task 1"))
    assert r.executor.live.done == 4
    assert (r.executor.live.aisle, r.executor.live.rack) == (1.0, 0.0)  # unloaded at the depot


async def test_two_robots_at_one_shelf_one_takes_the_object(run: Callable) -> None:
    world = WorldTruth()
    first = await run([_job(1, BAG)], world, "Robot1")
    second = await run([_job(7, BAG)], world, "Robot4")
    assert first.knowledge.facts == [("picked", (1,))]
    assert second.knowledge.facts == [("missing", (7,))]
    assert second.executor.live.missed == ((7, "gone: picked by Robot1 at task 1"),)


async def test_a_world_that_does_not_answer_leaves_the_kbs_word(
    run: Callable, caplog: pytest.LogCaptureFixture
) -> None:
    world = Unreachable()
    r = await run([_job(1, BAG)], world)
    assert world.asked == 1
    assert r.knowledge.facts == [("picked", (1,))] and r.executor.live.missed == ()
    assert "does not answer" in caplog.text and f"taking {BAG} as the KB says" in caplog.text


async def test_only_the_latest_missed_tasks_are_published(run: Callable) -> None:
    world = WorldTruth.with_misplaced([PASTA])
    r = await run([_job(seq, PASTA) for seq in range(1, MISSED_KEPT + 4)], world)
    assert [seq for seq, _ in r.executor.live.missed] == list(range(4, MISSED_KEPT + 4))
    assert r.executor.live.done == MISSED_KEPT + 3


class Fence:
    """A lease granted for the first ``grants`` asks, then refused."""

    def __init__(self, grants: int) -> None:
        self.grants = grants
        self.asked = 0

    async def hold(self, seconds: float, task: int = 0) -> str | None:
        self.asked += 1
        return None if self.asked <= self.grants else "no lease from a majority of the cluster (Robot2: refused)"


async def test_a_job_dropped_at_the_fence_leaves_its_object_for_the_robot_that_does_it_again(
    run: Callable
) -> None:
    world = WorldTruth()
    # Granted before the pick, refused when it is over (frozen past its lease meanwhile).
    fenced = await run([_job(1, BAG)], world, "Robot1", lease=Fence(grants=1).hold)
    assert fenced.executor.live.fenced == (1,) and fenced.executor.live.done == 0
    assert fenced.knowledge.facts == []  # nothing picked, nothing written
    # The feeder sends task 1 round again (task 4, again=1) to Robot2.
    again = await run([_job(4, BAG)], world, "Robot2")
    assert again.knowledge.facts == [("picked", (4,))] and again.executor.live.missed == ()


async def test_without_a_writer_or_a_world_the_robot_picks_as_before() -> None:
    published: list[LiveState] = []
    clock = FastClock()
    executor = TaskExecutor(MODEL, LiveState(1.0, 0.0), published.append, sleep=clock.sleep)
    executor.start()
    try:
        executor.submit(_job(1, BAG, to_depot_m=20.0))
        executor.submit(_job(2, BAG))
        await asyncio.wait_for(executor.wait_idle(), 1)
    finally:
        await executor.aclose()
    assert executor.live.done == 2 and executor.live.missed == ()  # the KB's word: it is there
