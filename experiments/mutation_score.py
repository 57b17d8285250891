"""The mutation score: how many planted bugs (tests/sim/mutants.py) the
simulator's checker catches, and on which seeds.

    .venv/bin/python -m experiments.mutation_score                  # every mutant, seeds 1-40 of its profile
    .venv/bin/python -m experiments.mutation_score --seeds 1-200 --only no-tombstones

Each mutant runs as ``coapkb sim PROFILE --seeds A-B`` with the bug planted
(a new process, ``PYTHONHASHSEED=0``, as a replay would).  A mutant is
caught when at least one seed violates an invariant.  Prints one line per
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


def _mutants() -> dict[str, tuple[str, ...]]:
    sys.path.insert(0, str(ROOT / "tests" / "sim"))
    from mutants import MUTANTS

    return {name: m.profile for name, m in MUTANTS.items()}


def run_mutant(name: str, profile: tuple[str, ...], seeds: str, jobs: int) -> tuple[list[int], str, float]:
    """The seeds on which mutant ``name`` was caught, the first finding, wall s."""
    started = time.monotonic()
    result = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "sim" / "mutants.py"), name, "sim", *profile, "--seeds", seeds,
         "--quiet", "--jobs", str(jobs)],
        capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONHASHSEED": "0"}, check=False,
    )
    found = VIOLATION.findall(result.stdout)
    if result.returncode not in (0, 1):
        raise SystemExit(f"{name}: coapkb sim failed ({result.returncode}): {result.stderr[-2000:]}")
    return [int(s) for s, _ in found], (found[0][1][:200] if found else ""), time.monotonic() - started


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
    for name in names:
        caught, finding, wall = run_mutant(name, mutants[name], args.seeds, args.jobs)
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
