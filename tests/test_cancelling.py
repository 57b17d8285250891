"""Cancelling a group of tasks: each has ended when the call returns, its
``finally`` run, and whatever it ended with is swallowed."""

from __future__ import annotations

import asyncio

from coapkb.cancelling import cancel_and_wait


async def _wound_down(done: list[str], name: str) -> None:
    """A cleanup step that runs as a task of its own: awaiting it takes the
    loop at least one more turn."""
    done.append(name)


async def test_every_task_has_ended_and_ran_its_finally() -> None:
    cleaned: list[str] = []
    started = {name: asyncio.Event() for name in ("a", "b")}

    async def waiter(name: str) -> None:
        started[name].set()
        try:
            await asyncio.Event().wait()  # never set: only the cancel ends it
        finally:
            await asyncio.create_task(_wound_down(cleaned, name))  # a cleanup that itself awaits

    tasks = [asyncio.create_task(waiter(n)) for n in started]
    await asyncio.gather(*(event.wait() for event in started.values()))
    await cancel_and_wait(tasks)
    assert all(t.done() for t in tasks)
    assert sorted(cleaned) == ["a", "b"]


async def test_errors_finished_tasks_and_nones_are_swallowed() -> None:
    async def fails() -> None:
        raise ValueError("no one is left to handle it")

    async def finishes() -> None:
        return None

    failed, finished = asyncio.create_task(fails()), asyncio.create_task(finishes())
    await asyncio.wait([failed, finished])
    await cancel_and_wait([failed, None, finished])
    assert isinstance(failed.exception(), ValueError)
    assert finished.result() is None


async def test_a_task_that_does_not_end_at_once_is_waited_for() -> None:
    ended: list[str] = []
    started = asyncio.Event()

    async def winding_down() -> None:
        started.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            await asyncio.create_task(_wound_down(ended, "stubborn"))  # still winding down after the cancel
            raise

    task = asyncio.create_task(winding_down())
    await started.wait()
    await cancel_and_wait([task])
    assert ended == ["stubborn"] and task.cancelled()
