"""The checker can fail: every planted bug of ``mutants.py`` is caught on
the seed it names, and that seed holds every invariant without the bug (so
the bug, not the schedule, is what broke it)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from mutants import MUTANTS, Mutant
from profiles import held_by_ci
from support import ROOT, unmeasured

HERE = ROOT / "tests" / "sim"


VIOLATING = re.compile(r"^seed (\d+) .*VIOLATION", re.M)
#: The progress and catch-up oracles judge the profile's runs together: seed 0 stands for them.
PROFILE_VIOLATES = re.compile(r"^sim: VIOLATION (progress|catch-up)", re.M)


def _violating(prefix: list[str], mutant: Mutant) -> set[int]:
    """The seeds of ``mutant``'s list that violate, run as ``prefix`` (the
    mutant's script, or the command itself)."""
    result = subprocess.run(
        [sys.executable, *prefix, "sim", *mutant.profile, "--seeds", ",".join(map(str, mutant.seeds)),
         "--quiet", "--jobs", "1"],
        # Not measured: a mutant's lines are not the package's, and the rest runs measured elsewhere.
        capture_output=True, text=True, cwd=ROOT, timeout=600, env=unmeasured({**os.environ, "PYTHONHASHSEED": "0"}),
    )
    assert result.returncode in (0, 1), result.stdout[-2000:] + result.stderr[-2000:]
    return {int(seed) for seed in VIOLATING.findall(result.stdout)} | ({0} if PROFILE_VIOLATES.search(result.stdout)
                                                                     else set())


@pytest.mark.parametrize("name", sorted(MUTANTS))
def test_every_planted_bug_is_caught_on_its_seed(name: str) -> None:
    """One of the mutant's seeds (a few are kept, as other fixes shift runs)
    violates with the bug planted and holds without it."""
    mutant = MUTANTS[name]
    if not mutant.seeds:
        pytest.xfail(f"{name} survives: {SURVIVORS[name]}")
    planted = _violating([str(HERE / "mutants.py"), name], mutant)
    # Seeds a CI profile runs are held to every invariant there, without the bug.
    clean = set() if held_by_ci(mutant.profile, mutant.seeds) else _violating(["-m", "coapkb"], mutant)
    assert planted - clean, f"{name}: caught on {sorted(planted)}, and without it {sorted(clean)} violate too"


#: Planted bugs no seed searched has caught yet, and why that may be.
SURVIVORS: dict[str, str] = {}


def test_there_are_a_dozen_planted_bugs_caught_and_the_survivors_are_named() -> None:
    caught = {m.name for m in MUTANTS.values() if m.seeds}
    assert len(MUTANTS) >= 12 and len(caught) >= 12
    assert set(MUTANTS) - caught == set(SURVIVORS)


@pytest.mark.parametrize("name", sorted(MUTANTS))
def test_every_planted_bug_takes_the_arguments_of_what_it_replaces(name: str) -> None:
    """A mutant that takes fewer arguments than the code passes raises
    TypeError where it is called: the run would fail for that, not for the
    bug (two did, after the code they replace took one argument more)."""
    with MUTANTS[name].plant():
        pass
