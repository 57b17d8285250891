"""Local health: a process knows when its own loop runs late, and its
failure detector does not blame a peer for a timeout while it did.  Run on
the simulator's clock, where a loop's pauses are set, not suffered."""

from __future__ import annotations

import asyncio
import random

from coapkb.agent.local_health import LoopHealth
from coapkb.agent.observed_states import PLAN_PATH, ObservedStates
from coapkb.sim.loop import Scheduler
from coapkb.transport.base import Endpoint, PeerTimeout, PeerUnreachable
from coapkb.transport.memory import MemoryNetwork


def _run(coroutine_factory, starve: float | None):  # type: ignore[no-untyped-def]
    scheduler = Scheduler(random.Random(1), lambda _: None)
    process = scheduler.spawn("robot")
    if starve is not None:
        process.starve(starve, 1_000.0, now=0.0)
    task = scheduler.start(process, coroutine_factory())
    scheduler.run(task.done, limit_s=1_000)
    return task.result()


def test_a_loop_on_time_reads_no_lateness_and_a_starved_one_does() -> None:
    async def measure() -> tuple[float, dict[str, float | int]]:
        health = LoopHealth()
        health.start()
        await asyncio.sleep(20)
        late = health.late_within(10)
        await health.aclose()
        return late, health.stats().as_dict()

    on_time, stats = _run(measure, starve=None)
    assert on_time == 0.0 and stats["late_ticks"] == 0 and stats["ticks"] >= 70
    late, stats = _run(measure, starve=1.0)
    assert late > 0.5 and stats["late_ticks"] > 0 and stats["max_s"] >= late


def test_a_timeout_while_the_own_loop_ran_late_is_not_counted_against_the_peer() -> None:
    peer = {"Robot2": Endpoint("coap", "10.0.0.2", 5683)}

    async def failures(late_by: float) -> tuple[int, bool, bool]:
        health = LoopHealth()
        states = ObservedStates(MemoryNetwork().client(), peer, PLAN_PATH, liveness=True, health=health)
        health.note(asyncio.get_running_loop().time(), late_by)
        stretched = states.liveness_timeout_s > 2.0
        for _ in range(3):
            await states.detector.failed("Robot2", PeerTimeout("no answer within 1s"))
        timed_out_down = "Robot2" in states.down
        await states.detector.failed("Robot2", PeerUnreachable("port unreachable"))  # the network said so: counts
        return states.detector.failures_in_a_row("Robot2"), timed_out_down, stretched

    assert _run(lambda: failures(0.0), starve=None) == (4, True, False)
    count, down, stretched = _run(lambda: failures(1.0), starve=None)
    assert (count, down, stretched) == (1, False, True)


def test_a_stall_is_remembered_once_it_is_over() -> None:
    """A process stopped for 20 s reads, once it runs again, how long it
    stood still (its teammates may have settled a task without it), while
    the lateness of its recent turns is back to nothing."""
    scheduler = Scheduler(random.Random(1), lambda _: None)
    robot = scheduler.spawn("robot")
    injector = scheduler.spawn("injector")

    async def measure() -> tuple[float, float, float]:
        health = LoopHealth()
        health.start()
        await asyncio.sleep(30)  # stopped from 5 s to 25 s meanwhile
        readings = health.late_within(2), health.stalled_within(10), health.stalled_within(1)
        await health.aclose()
        return readings

    async def stop_for_a_while() -> None:
        await asyncio.sleep(5)
        scheduler.freeze(robot)
        await asyncio.sleep(20)
        scheduler.resume(robot)

    task = scheduler.start(robot, measure())
    scheduler.start(injector, stop_for_a_while())
    scheduler.run(task.done, limit_s=1_000)
    late, stalled, long_ago = task.result()
    assert late == 0.0 and 19.0 < stalled <= 20.0 and long_ago == 0.0
