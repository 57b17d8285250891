"""The mutation score: how many planted bugs (tests/sim/mutants.py) the
simulator's checker catches, and on which seeds.

    .venv/bin/python -m experiments.mutation_score                  # every mutant, seeds 1-40 of its profile
    .venv/bin/python -m experiments.mutation_score --seeds 1-200 --only no-tombstones

Each mutant runs as ``coapkb sim PROFILE --seeds A-B`` with the bug planted
(a new process, ``PYTHONHASHSEED=0``, as a replay would), and each profile
once without any.  A mutant is caught on a seed that violates an invariant
with the bug and holds every one without it (seed 0: the profile's runs
together broke the progress oracle, ``--decide-within``).  Prints one line per
mutant and the score; writes ``experiments/results/sim/mutation_score.csv``
(mutant, profile, seeds run, seeds caught, the first catching seeds, the
first finding, wall seconds).
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "experiments" / "results" / "sim" / "mutation_score.csv"
VIOLATION = re.compile(r"^seed (\d+) .*?VIOLATION (.*)$", re.M)
#: The progress oracle judges all the runs together: reported as seed 0.
PROFILE_VIOLATION = re.compile(r"^sim: VIOLATION (progress: .*)$", re.M)


def _mutants() -> dict[str, tuple[str, ...]]:
    sys.path.insert(0, str(ROOT / "tests" / "sim"))
    from mutants import MUTANTS

    return {name: m.profile for name, m in MUTANTS.items()}


def violations(prefix: list[str], profile: tuple[str, ...], seeds: str, jobs: int) -> dict[int, str]:
    """Seed -> its first finding, for the seeds that violate, run as ``prefix``."""
    result = subprocess.run(
        [sys.executable, *prefix, "sim", *profile, "--seeds", seeds, "--quiet", "--jobs", str(jobs)],
        capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONHASHSEED": "0"}, check=False,
    )
    if result.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(prefix)}: coapkb sim failed ({result.returncode}): {result.stderr[-2000:]}")
    found = {int(seed): finding for seed, finding in VIOLATION.findall(result.stdout)}
    profile_wide = PROFILE_VIOLATION.search(result.stdout)
    if profile_wide is not None:
        found[0] = profile_wide.group(1)
    return found


def run_mutant(name: str, profile: tuple[str, ...], seeds: str, jobs: int,
               clean: dict[int, str]) -> tuple[list[int], str, float]:
    """The seeds on which mutant ``name`` was caught (violating with it, not
    without it: ``clean``), the first finding, wall s."""
    started = time.monotonic()
    found = violations([str(ROOT / "tests" / "sim" / "mutants.py"), name], profile, seeds, jobs)
    caught = sorted(set(found) - set(clean))
    return caught, (found[caught[0]][:200] if caught else ""), time.monotonic() - started


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-40", help="seeds of each mutant's profile (default 1-40)")
    parser.add_argument("--only", action="append", help="this mutant only (repeatable)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes per mutant (default 1)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    mutants = _mutants()
    names = args.only or list(mutants)
    rows = []
    clean: dict[tuple[str, ...], dict[int, str]] = {}
    for name in names:
        profile = mutants[name]
        if profile not in clean:
            clean[profile] = violations(["-m", "coapkb"], profile, args.seeds, args.jobs)
            if clean[profile]:
                print(f"without a bug, {' '.join(profile)} violates on seeds {sorted(clean[profile])}", flush=True)
        caught, finding, wall = run_mutant(name, profile, args.seeds, args.jobs, clean[profile])
        rows.append({"mutant": name, "profile": " ".join(mutants[name]), "seeds": args.seeds,
                     "caught": len(caught), "first_seeds": " ".join(map(str, caught[:5])),
                     "finding": finding, "wall_s": round(wall, 1)})
        print(f"{name:28} caught on {len(caught):3} seeds {caught[:5]} ({wall:.0f} s) {finding[:100]}", flush=True)
    score = sum(1 for r in rows if r["caught"])
    print(f"mutation score: {score} of {len(rows)} caught")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="", encoding="utf-8") as out:
        writer = csv.DictWriter(out, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return 0 if score == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
