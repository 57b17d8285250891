"""A seed replays its run byte for byte: each seed run again as the command
(``coapkb sim --seed S --trace FILE``), each time a new process, writes the
same trace.

Replays within one process agreed even where the code ordered work by id()
(a set of tasks, ``asyncio.wait``'s ``done``): each run laid its objects out
in memory alike.  New processes did not always, so each replay here is one.  Under PYTHONHASHSEED=0, the command's own, so it does not start itself
again (test_simulator.py checks that it does).  The longer check, 20 seeds
replayed 10 times each: ``python -m experiments.replay_check``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from support import ROOT, unmeasured

CI_PROFILE = ["--robots", "3", "--tasks", "10", "--faults", "mixed"]
#: The profile whose seed 20005 gave two traces in ten replays: the feeder's
#: indirect probes started in id() order.  Its seeds below did so too (each
#: about every other replay) before that was fixed; the CI profile's did not.
NINE_ROBOTS = ["--robots", "9", "--tasks", "30", "--faults", "freeze,partition"]


def _trace(profile: list[str], seed: int, trace: Path) -> bytes:
    result = subprocess.run([sys.executable, "-m", "coapkb", "sim", *profile, "--seed", str(seed), "--trace", str(trace)],
                            capture_output=True, text=True, cwd=ROOT, timeout=300,
                            env=unmeasured({**os.environ, "PYTHONHASHSEED": "0"}))  # the same runs, measured elsewhere
    assert result.returncode in (0, 1) and trace.exists(), result.stderr[-2000:]  # 1: a violation, still a trace
    return trace.read_bytes()


def _differing(profile: list[str], seeds: list[int], replays: int, tmp_path: Path) -> list[str]:
    """Each seed run ``replays`` times, two processes at a time: the seeds
    whose traces differ, each with the first line where one differs from the first."""
    runs = [(seed, tmp_path / f"{seed}.{replay}.trace") for seed in seeds for replay in range(replays)]
    with ThreadPoolExecutor(2) as pool:
        traces = list(pool.map(lambda run: _trace(profile, *run), runs))
    differing = []
    for i, seed in enumerate(seeds):
        first, *others = traces[i * replays:(i + 1) * replays]
        other = next((t for t in others if t != first), None)
        if other is not None:
            a, b = next(((a, b) for a, b in zip(first.splitlines(), other.splitlines()) if a != b),
                        (b"", b"(one trace goes on)"))
            differing.append(f"seed {seed}: {a.decode()!r} then {b.decode()!r}")
    return differing


@pytest.mark.slow
def test_seeds_of_the_ci_profile_replay_byte_for_byte(tmp_path: Path) -> None:
    differing = _differing(CI_PROFILE, list(range(1, 21)), 2, tmp_path)
    assert not differing, "\n".join(differing)


@pytest.mark.slow
def test_seeds_of_nine_robots_frozen_and_cut_off_replay_byte_for_byte(tmp_path: Path) -> None:
    differing = _differing(NINE_ROBOTS, [20001, 20003, 20004, 20005], 3, tmp_path)
    assert not differing, "\n".join(differing)
