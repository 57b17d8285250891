"""What the simulator costs, and what its profiles find.

    .venv/bin/python -m experiments.sim_profiles                 # cost of a 9-robot, 100-task run; the CI profile
    .venv/bin/python -m experiments.sim_profiles --long         # and the long profile (10,000 seeds, about 10 min)

Cost: one 9-robot, 100-task run with mixed faults, seed after seed in this
process (the KBs loaded once, as in a worker): CPU seconds per run, with the
simulated seconds, messages and violations of each.  Profiles: ``coapkb sim``
itself, as a user runs it (its summary line is the result).  Writes
``experiments/results/sim/cost.csv`` and ``profiles.csv``.
"""

from __future__ import annotations

import argparse
import csv
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "experiments" / "results" / "sim"

PROFILES = {
    "ci": ["--robots", "3", "--tasks", "10", "--seeds", "1-500", "--faults", "mixed"],
    "six-robots-cc": ["--robots", "6", "--tasks", "12", "--seeds", "1-400", "--faults", "mixed",
                      "--strategy", "compute-and-communicate"],
    "nine-robots": ["--robots", "9", "--tasks", "100", "--seeds", "1-100", "--faults", "mixed"],
    "long": ["--robots", "3", "--tasks", "10", "--seeds", "1-10000", "--faults", "mixed"],
}


def cost(seeds: int) -> list[dict[str, object]]:
    from coapkb.sim import FaultMix, KBCache, SimSpec, run_checked

    kbs = KBCache()
    spec = SimSpec(robots=9, tasks=100, faults=FaultMix.parse("mixed"))
    run_checked(spec, 0, kbs)  # the KBs and configurations loaded, as in a worker that ran one already
    rows = []
    for seed in range(1, seeds + 1):
        run = run_checked(spec, seed, kbs)
        rows.append({"seed": seed, "cpu_s": round(run.cpu_s, 3), "sim_s": run.sim_s, "steps": run.steps,
                     "messages": run.messages, "lost": run.lost, "violations": len(run.violations),
                     "schedule": run.schedule})
    return rows


def profile(name: str) -> dict[str, object]:
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "coapkb", "sim", *PROFILES[name], "--quiet"],
                            capture_output=True, text=True, cwd=ROOT)
    wall = time.monotonic() - started
    summary = re.search(r"^sim: (\d+) runs, (\d+) violations, ([\d,]+) simulated s in ([\d.,]+) wall s$",
                        result.stdout, re.M)
    excused = re.search(r"^sim: (\d+) findings excused", result.stdout, re.M)
    violating = [line for line in result.stdout.splitlines() if "VIOLATION" in line]
    if summary is None:
        raise SystemExit(f"{name}: no summary line\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}")
    return {"profile": name, "options": " ".join(PROFILES[name]), "runs": int(summary[1]),
            "violations": int(summary[2]), "excused": int(excused[1]) if excused else 0,
            "simulated_s": int(summary[3].replace(",", "")), "wall_s": round(wall, 1),
            "violating_seeds": " ".join(line.split()[1] for line in violating)}


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.sim_profiles", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="runs for the cost (default 20)")
    parser.add_argument("--long", action="store_true", help="also the 10,000-seed profile")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    rows = cost(args.seeds)
    cpu = [float(r["cpu_s"]) for r in rows]  # type: ignore[arg-type]
    print(f"cost: 9 robots, 100 tasks, mixed faults: CPU per run min {min(cpu):.2f} s, "
          f"median {statistics.median(cpu):.2f} s, max {max(cpu):.2f} s over {len(rows)} runs; "
          f"violations {sum(int(r['violations']) for r in rows)}")  # type: ignore[call-overload]
    with open(OUT / "cost.csv", "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    names = ["ci", "six-robots-cc", "nine-robots"] + (["long"] if args.long else [])
    results = []
    for name in names:
        results.append(profile(name))
        r = results[-1]
        print(f"{name}: {r['runs']} runs, {r['violations']} violations ({r['violating_seeds'] or 'none'}), "
              f"{r['excused']} excused, {r['simulated_s']:,} simulated s in {r['wall_s']} wall s", flush=True)
    with open(OUT / "profiles.csv", "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(results[0]))
        writer.writeheader()
        writer.writerows(results)


if __name__ == "__main__":
    main()
