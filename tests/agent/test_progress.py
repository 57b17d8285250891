"""Live progress is paced; what observers act on is notified at once."""

from __future__ import annotations

import asyncio
from dataclasses import replace

import pytest

from coapkb.agent.progress import ProgressPacing, acted_on
from coapkb.agent.robot_state import LiveState

IDLE = LiveState(1.0, 0.0)

# The pace is timed on the event loop's own clock (looptime): a busy
# machine cannot stretch the waits below past the pace.
pytestmark = pytest.mark.looptime


def test_observers_act_on_jobs_done_dropped_and_the_robot_idle() -> None:
    travelling = replace(IDLE, activity="travelling", executing="Gucci_bag_14")
    picking = replace(travelling, activity="picking", aisle=3.0, rack=21.0)
    done = replace(picking, done=1)
    assert not acted_on(IDLE, travelling) and not acted_on(travelling, picking)
    assert acted_on(picking, done)
    assert acted_on(done, replace(done, activity="idle", executing=None))
    assert not acted_on(done, replace(done, activity="idle", queued=2))  # more jobs waiting: not idle yet
    assert acted_on(IDLE, replace(IDLE, fenced=(4,), fence_reason="lease refused"))


async def test_progress_waits_for_the_pace_and_folds_into_the_next_notification() -> None:
    sent: list[float] = []
    loop = asyncio.get_running_loop()
    pacing = ProgressPacing(lambda: sent.append(loop.time()), pace_s=0.2)
    started = loop.time()
    pacing.now()  # a decision
    await asyncio.sleep(0)
    for _ in range(5):  # travelling, picking, ... within the pace: one notification later
        pacing.progress()
        await asyncio.sleep(0.01)
    assert len(sent) == 1
    await asyncio.sleep(0.25)
    assert len(sent) == 2 and sent[1] - started >= 0.19
    pacing.progress()
    pacing.now()  # a job done and the robot idle: one notification, with the progress waiting
    pacing.now()
    await asyncio.sleep(0)
    assert len(sent) == 3
    pacing.progress()  # within the pace again: waits, and the robot stops first
    pacing.cancel()
    await asyncio.sleep(0.25)
    assert len(sent) == 3
