"""The simulator's CI profile: the seeded runs the suite holds to every
invariant (``test_simulator.py``), and which of them a planted bug's seeds
fall in (``test_mutants.py``: those need no run without the bug of their own)."""

from __future__ import annotations

from typing import NamedTuple


class CIProfile(NamedTuple):
    """One of the CI profile's command lines, and the seeds it runs (``A-B``)."""

    name: str
    options: tuple[str, ...]
    seeds: str

    def span(self) -> range:
        first, last = map(int, self.seeds.split("-"))
        return range(first, last + 1)


#: The CI profile: swarm testing (each seed draws its own faults, traps at
#: picks, long outages) with the operator writing, on 3 robots and on 9.
CI_PROFILES = [
    CIProfile("3 robots", ("--robots", "3", "--tasks", "10", "--faults", "mixed,swarm", "--writes", "20"), "1-200"),
    CIProfile("9 robots", ("--robots", "9", "--tasks", "30", "--faults", "freeze,partition,swarm", "--writes", "20"),
              "1-12"),
    CIProfile("forged syncs", ("--robots", "3", "--tasks", "10", "--faults", "mixed,forge,swarm", "--writes", "20"),
              "1-50"),
    CIProfile("power cuts", ("--robots", "3", "--tasks", "10", "--faults", "mixed,crash,swarm", "--writes", "20",
                             "--storage"), "1-40"),
    # The progress oracle judges the runs together (a median under 1 s now).
    CIProfile("progress", ("--robots", "3", "--tasks", "10", "--faults", "loss=0.2", "--decide-within", "1.5"),
              "1-40"),
    # The catch-up oracle judges the restarts together (a median of one exchange, 0.07 s, now); its
    # two planted bugs are caught on these seeds too (tests/sim/mutants.py).
    CIProfile("catch-up", ("--robots", "3", "--tasks", "10", "--faults", "kill,loss=0.1", "--writes", "20",
                           "--catch-up-within", "0.5"), "121-180"),
    # Messages held back 0.5-3 s, past their senders' retries, and retries sent as two exchanges: the
    # operator removes a third of its adds once spread, and a late try of one must be answered as a
    # repeat (its write id), not make it again.
    CIProfile("late messages", ("--robots", "3", "--tasks", "10", "--faults", "mixed,late,hedge,swarm",
                                "--writes", "20"), "1-40"),
    # A replica takes one dot at most past a gap: pushes held back or lost are refused at the bound
    # (5.03, never 2.04) and taken again, in order, at the next exchanges.
    CIProfile("bounded waiting", ("--robots", "3", "--tasks", "10", "--faults", "mixed,late,swarm", "--writes", "20",
                                  "--waiting-max", "1"), "1-60"),
    # Robots killed and started again at once (a supervisor's restart), with data folders and power
    # cuts: a life's last pushes may land after the next life started.
    CIProfile("quick restarts", ("--robots", "3", "--tasks", "10", "--faults", "mixed,bounce,crash,swarm",
                                 "--writes", "20", "--storage"), "1-40"),
    # Clients observing the written knowledge as `coapkb query --observe` does, through restarts, cuts and
    # lost notifications: each must show what its robot's KB shows once the replicas agree.
    CIProfile("observers", ("--robots", "3", "--tasks", "10", "--faults", "mixed,swarm", "--writes", "20",
                            "--observers", "2"), "1-60"),
    # Every fault at once, no swarm: the operator's writes against kills, restarts, cuts and loss.
    CIProfile("every fault", ("--robots", "3", "--tasks", "10", "--faults", "mixed", "--writes", "20"), "1-60"),
    # A restarted robot cut off from its cluster the moment it is back, on lossy links: its join.
    CIProfile("rejoin", ("--robots", "3", "--tasks", "30", "--faults", "rejoin,loss,swarm"), "1-40"),
    # Long task lists that draw objects again, across three clusters, with every fault.
    CIProfile("repeats", ("--robots", "9", "--tasks", "60", "--faults", "mixed", "--writes", "3"), "1-6"),
]


def judged_together(profile: tuple[str, ...]) -> bool:
    """Whether an oracle of ``profile`` judges its runs together
    (``--decide-within``, ``--catch-up-within``), not each on its own."""
    return any(option.endswith("-within") for option in profile)


def held_by_ci(profile: tuple[str, ...], seeds: tuple[int, ...]) -> bool:
    """Whether a CI profile's test already holds ``seeds`` of ``profile`` to
    every invariant: each is one of its runs, and where an oracle judges the
    runs together (``--decide-within``, ``--catch-up-within``), they are
    all of its runs."""
    together = judged_together(profile)
    return any(
        seeds == tuple(ci.span()) if together else all(seed in ci.span() for seed in seeds)
        for ci in CI_PROFILES if ci.options == profile
    )
