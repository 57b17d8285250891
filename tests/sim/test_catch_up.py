"""The catch-up timer: a restarted holder's sample ends when it shows every
value its co-holders showed at its restart, or the rest were deleted; a
query it answers before then is a stale read."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from coapkb.sim.catch_up import CatchUps
from coapkb.transport.messages import Method, Request, Response, Status


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


def test_a_query_answered_before_the_catch_up_is_a_stale_read() -> None:
    clock, shown = Clock(), set[tuple[str, int]]()
    catch_ups = CatchUps(clock, lambda _kb, module, value: (module, value) in shown)
    robot2: Any = SimpleNamespace(name="Robot2")
    read, answer = Request(Method.GET, "/kb/q/pick-place"), Response(Status.CONTENT)
    catch_ups.answered(robot2, read, answer)  # not restarted: nothing owed
    catch_ups.expect("Robot2", {"Location": {4, 5}})
    clock.now = 0.25
    catch_ups.answered(robot2, Request(Method.POST, "/kb/sync"), Response(Status.CHANGED))  # not a query
    catch_ups.answered(robot2, read, Response(Status.SERVICE_UNAVAILABLE))  # not answered
    catch_ups.answered(robot2, read, answer)
    assert catch_ups.stale_reads == [
        "Robot2 answered GET /kb/q/pick-place 0.250 s after its restart, still lacking acknowledged values "
        "(2 of Location)"]
    shown |= {("Location", 4), ("Location", 5)}
    catch_ups.changed("Robot2", object())
    catch_ups.answered(robot2, read, answer)  # caught up
    assert len(catch_ups.stale_reads) == 1
