"""The world in the KB in the simulator: repeated objects, in one cluster
and across clusters, with the robots writing their picks; one world gives
each object to one robot."""

from __future__ import annotations

from collections import Counter

import pytest

from coapkb.sim import FaultMix, KBCache, SimSpec, run_checked


@pytest.fixture(scope="module")
def kbs() -> KBCache:
    return KBCache()


def test_repeats_are_skipped_alike_and_no_object_is_picked_twice(kbs: KBCache) -> None:
    """Nine robots, 90 tasks drawn with repeats, the KB writable: every run
    holds every invariant (a cluster never gives an object twice, no
    disagreement); repeats are skipped with the picker named, and a repeat
    that another cluster decided before the pick's write reached it finds
    the shelf empty."""
    spec = SimSpec(robots=9, tasks=90, faults=FaultMix.parse("none"), writes=1)
    runs = [run_checked(spec, seed, kbs) for seed in (1, 2, 3)]
    assert [r.violations for r in runs] == [[], [], []]
    fates = Counter(t.fate for r in runs for t in r.record.tasks)  # type: ignore[union-attr]
    reasons = [t.skip_reason for r in runs for t in r.record.tasks if t.fate == "skipped"]  # type: ignore[union-attr]
    assert fates["skipped"] >= 3 and all(reason.startswith("picked by ") for reason in reasons), reasons
    for run in runs:
        taken = Counter(p.object for p in run.picks)
        assert max(taken.values()) == 1, taken  # the world gave each object once
        for task in run.record.tasks:  # type: ignore[union-attr]
            if task.fate == "not-found":
                assert "gone: picked by Robot" in (task.not_found or ""), task


