"""The checker can fail: every planted bug of ``mutants.py`` is caught on
the seed it names, and that seed holds every invariant without the bug (so
the bug, not the schedule, is what broke it)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from mutants import MUTANTS, Mutant
from support import ROOT

HERE = ROOT / "tests" / "sim"


def _sim(prefix: list[str], mutant: Mutant) -> subprocess.CompletedProcess[str]:
    seeds = ",".join(map(str, mutant.seeds))
    return subprocess.run(
        [sys.executable, *prefix, "sim", *mutant.profile, "--seeds", seeds, "--quiet", "--jobs", "1"],
        capture_output=True, text=True, cwd=ROOT, timeout=600, env={**os.environ, "PYTHONHASHSEED": "0"},
    )


@pytest.mark.parametrize("name", sorted(MUTANTS))
def test_every_planted_bug_is_caught_on_its_seed(name: str) -> None:
    mutant = MUTANTS[name]
    if not mutant.seeds:
        pytest.xfail(f"{name}: no seed of its profile catches it yet ({mutant.what})")
    planted = _sim([str(HERE / "mutants.py"), name], mutant)
    assert planted.returncode == 1 and "VIOLATION" in planted.stdout, planted.stdout[-2000:] + planted.stderr[-2000:]
    clean = _sim(["-m", "coapkb"], mutant)
    assert clean.returncode == 0, f"seed {mutant.seeds} violates without the bug: " + clean.stdout[-2000:]


def test_there_are_a_dozen_planted_bugs_and_most_are_caught() -> None:
    caught = [m for m in MUTANTS.values() if m.seeds]
    assert len(MUTANTS) >= 12 and len(caught) >= 9, [m.name for m in MUTANTS.values() if not m.seeds]
