"""The catch-up timer: a restarted holder's sample ends when it shows every
value its co-holders showed at its restart, or the rest were deleted."""

from __future__ import annotations

from typing import Any

from coapkb.sim.catch_up import CatchUps


class Clock:
    now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_catch_up_ends_when_every_owed_value_is_shown_or_deleted() -> None:
    clock, shown = Clock(), {("Object", 1)}
    catch_ups = CatchUps(clock, lambda _kb, module, value: (module, value) in shown)
    kb: Any = object()
    catch_ups.expect("Robot2", {"Object": {1, 2, 3}, "Location": set()})
    clock.now = 0.4
    catch_ups.changed("Robot2", kb)
    assert catch_ups.took_s == []
    shown.add(("Object", 2))
    catch_ups.deleting("Object", 3)
    clock.now = 0.7
    catch_ups.changed("Robot2", kb)
    assert catch_ups.took_s == [0.7]


def test_a_killed_holder_gives_no_sample_and_an_unfinished_one_counts_until_the_end() -> None:
    clock = Clock()
    catch_ups = CatchUps(clock, lambda *_: False)
    catch_ups.expect("Robot1", {"Object": {1}})
    catch_ups.killed("Robot1")
    catch_ups.expect("Robot2", {"Object": {1}})
    catch_ups.expect("Robot3", {})  # owed nothing: no sample
    clock.now = 5.0
    assert catch_ups.finish() == [5.0]
