"""Every seed on which the simulator found a bug, replayed after its fix
(the 3-robot, 10-task mixed profile, under the command's own hash seed).
A fix's own unit test sits beside the code it fixed; this replays the
whole run that found it."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from support import ROOT

#: Seed -> what went wrong before the fix.
FOUND = {
    2: "a robot gave up waiting for a dead teammate's plan before it could find it down: it decided alone",
    50: "the same, a kill alone on a lossy link",
    100: "the same, with the robot's own loop starved",
    32: "an older plan answered late was taken for a restart: a live teammate declared down, the cluster split",
    65: "the same, after a kill: the survivors disagreed on every later task",
    76: "the same, with the feeder starved",
    478: "a burst of loss swallowed every retransmission of one robot's statistics: the whole run failed",
}


def test_every_seed_that_found_a_bug_now_holds_every_invariant() -> None:
    seeds = ",".join(str(s) for s in sorted(FOUND))
    result = subprocess.run(
        [sys.executable, "-m", "coapkb", "sim", "--robots", "3", "--tasks", "10", "--faults", "mixed",
         "--seeds", seeds, "--quiet"],
        capture_output=True, text=True, cwd=ROOT, timeout=600, env={**os.environ, "PYTHONHASHSEED": "0"},
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert re.search(rf"^sim: {len(FOUND)} runs, 0 violations, ", result.stdout, re.M), result.stdout
