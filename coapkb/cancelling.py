"""Cancelling a group of background tasks and waiting until each has ended.

A task's ``cancel()`` only asks: the task ends at its next await, perhaps
after its ``finally`` blocks have sent or closed something.  Whoever
cancels waits for that end, so nothing it owns outlives it (a socket
closed under a task still reading, a retransmission after the close), and
swallows what the tasks ended with: a cancelled task's
``CancelledError``, or an error no one is left to handle.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from typing import Any

__all__ = ["cancel_and_wait"]


async def cancel_and_wait(tasks: Iterable[asyncio.Future[Any] | None]) -> None:
    """Cancel every task of ``tasks`` (``None`` stands for none) and wait
    until all have ended, whatever each ended with."""
    running = [task for task in tasks if task is not None]
    for task in running:
        task.cancel()
    await asyncio.gather(*running, return_exceptions=True)
