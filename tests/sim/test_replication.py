"""The KB's replication in the simulator: an operator writes to random
robots while faults are injected; at the end the holders of each module
agree and keep every write they acknowledged."""

from __future__ import annotations

import pytest

from coapkb.sim import FaultMix, KBCache, SimSpec, run_checked
from coapkb.sim.invariants import check_acknowledged_writes, check_replicas


@pytest.fixture(scope="module")
def kbs() -> KBCache:
    return KBCache()


def test_writes_without_faults_reach_every_holder(kbs: KBCache) -> None:
    run = run_checked(SimSpec(robots=6, tasks=12, writes=30), 3, kbs)
    assert run.violations == [] and run.record is not None
    # A write may go to two holders at once (the same value, or an insert racing a delete).
    assert len({w.label for w in run.writes}) == 30 and {w.status for w in run.writes} == {"2.04"}
    assert {w.kind for w in run.writes} == {"insert", "delete", "move"}
    assert set(run.versions) == {"Location", "Object", "Capability"}
    # Each module lives on two robots of each of the two clusters: four holders, one version.
    assert all(len(holders) == 4 and len(set(holders.values())) == 1 for holders in run.versions.values())
    inserted = {w.value for w in run.writes if w.kind == "insert"}
    assert inserted and all(values for holders in run.values.values() for values in holders.values())


@pytest.mark.parametrize("seed", [81, 266])
def test_a_restarted_robot_catches_up_before_the_other_holder_dies(kbs: KBCache, seed: int) -> None:
    """Found by the simulator: a robot restarted, and the module's other
    holder was killed 1.3 s later -- before the first anti-entropy round
    (5 s), so an acknowledged write died with it.  A robot now catches up
    from every holder as soon as it starts."""
    run = run_checked(SimSpec(robots=3, tasks=10, faults=FaultMix.parse("mixed"), writes=20), seed, kbs)
    assert list(check_replicas(run)) == [] and list(check_acknowledged_writes(run)) == [] and run.versions


