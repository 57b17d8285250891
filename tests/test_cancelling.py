"""Cancelling a group of tasks: each has ended when the call returns, its
``finally`` run, and whatever it ended with is swallowed."""

from __future__ import annotations

import asyncio

from coapkb.cancelling import cancel_and_wait


async def test_every_task_has_ended_and_ran_its_finally() -> None:
    cleaned: list[str] = []

    async def sleeper(name: str) -> None:
        try:
            await asyncio.sleep(3600)
        finally:
            await asyncio.sleep(0)  # a cleanup that itself awaits
            cleaned.append(name)

    tasks = [asyncio.create_task(sleeper(n)) for n in ("a", "b")]
    await asyncio.sleep(0)
    await cancel_and_wait(tasks)
    assert all(t.done() for t in tasks)
    assert sorted(cleaned) == ["a", "b"]


async def test_errors_finished_tasks_and_nones_are_swallowed() -> None:
    async def fails() -> None:
        raise ValueError("no one is left to handle it")

    failed = asyncio.create_task(fails())
    finished = asyncio.create_task(asyncio.sleep(0))
    await asyncio.sleep(0.01)
    await cancel_and_wait([failed, None, finished])
    assert isinstance(failed.exception(), ValueError)
    assert finished.result() is None


async def test_a_task_that_refuses_to_end_at_once_is_waited_for() -> None:
    ended = asyncio.Event()

    async def stubborn() -> None:
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            await asyncio.sleep(0.01)  # still winding down after the cancel
            ended.set()
            raise

    task = asyncio.create_task(stubborn())
    await asyncio.sleep(0)
    await cancel_and_wait([task])
    assert ended.is_set() and task.cancelled()
