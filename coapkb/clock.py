"""The one clock the protocols read: the running event loop's.

In a robot, the feeder or a test, the loop's clock is ``time.monotonic``;
in the simulator (:mod:`coapkb.sim`) it is virtual time that jumps to the
next timer.  Timeouts, sleeps and leases already run on the loop's clock
(``asyncio.timeout``, ``asyncio.sleep``); reading the time through here
keeps every deadline the protocols compute on that same clock.
"""

from __future__ import annotations

import asyncio
import time


def monotonic() -> float:
    """Seconds on the running loop's clock; ``time.monotonic()`` outside a
    loop (a KB query on a worker thread, a synchronous caller)."""
    try:
        return asyncio.get_running_loop().time()
    except RuntimeError:
        return time.monotonic()
