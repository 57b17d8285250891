"""Whether a seed replays its run byte for byte: each seed run again and
again as ``coapkb sim --seed S --trace FILE``, a new process each time (as a
user replays it), and its traces compared.

    .venv/bin/python -m experiments.replay_check                          # seeds 1-20, 10 replays each, the CI profile
    .venv/bin/python -m experiments.replay_check --seeds 20001-20020 -- --robots 9 --tasks 30 --faults freeze,partition

Options after ``--`` (or any this script does not know) go to ``coapkb sim``
as they are: the profile.  A seed is identical when its replays all wrote
the same trace; one that is not keeps its differing traces in ``--keep``, if
given, to diff.  Writes ``experiments/results/sim/replay_check.csv``: per
seed, the replays, how many distinct traces, the first line where one
differs from the first, and the wall time.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "experiments" / "results" / "sim" / "replay_check.csv"
CI_PROFILE = ["--robots", "3", "--tasks", "10", "--faults", "mixed"]


def seed_range(text: str) -> list[int]:
    """``A-B`` or ``N``."""
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def replay(seed: int, profile: list[str], trace: Path) -> int:
    """One run of ``seed`` as the command, its trace written to ``trace``; its exit status."""
    result = subprocess.run([sys.executable, "-m", "coapkb", "sim", *profile, "--seed", str(seed), "--trace", str(trace)],
                            capture_output=True, text=True, cwd=ROOT)
    if result.returncode not in (0, 1) or not trace.exists():  # 1: a violation, still a run and its trace
        raise SystemExit(f"seed {seed}: coapkb sim failed ({result.returncode})\n{result.stderr[-2000:]}")
    return result.returncode


def first_difference(a: Path, b: Path) -> int:
    """The number of the first line where the traces differ."""
    with a.open("rb") as fa, b.open("rb") as fb:
        n = 0
        for n, (x, y) in enumerate(zip(fa, fb), 1):
            if x != y:
                return n
        return n + 1  # one is the other's beginning


def check_seed(seed: int, replays: int, profile: list[str], work: Path, keep: Path | None) -> dict[str, object]:
    started = time.monotonic()
    traces = [work / f"{seed}.{i}.trace" for i in range(replays)]
    statuses = {replay(seed, profile, t) for t in traces}
    digests = [hashlib.sha256(t.read_bytes()).hexdigest() for t in traces]
    differing = [t for t, d in zip(traces, digests) if d != digests[0]]
    line = first_difference(traces[0], differing[0]) if differing else ""
    if differing and keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        for t in [traces[0], *differing]:
            shutil.copy(t, keep / t.name)
    for t in traces:
        t.unlink()
    return {"seed": seed, "replays": replays, "distinct_traces": len(set(digests)), "identical": not differing,
            "first_difference_line": line,
            "exit_statuses": " ".join(map(str, sorted(statuses))), "wall_s": round(time.monotonic() - started, 1),
            "profile": " ".join(profile)}


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.replay_check", description=__doc__.split("\n\n")[0],
                                     epilog="other options go to coapkb sim (default: the CI profile, "
                                            + " ".join(CI_PROFILE) + ")")
    parser.add_argument("--seeds", type=seed_range, default="1-20", metavar="A-B", help="the seeds (default 1-20)")
    parser.add_argument("--replays", type=int, default=10, help="runs of each seed (default 10)")
    parser.add_argument("--jobs", type=int, default=1, help="seeds checked at once (default 1: one run at a time)")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="keep the traces of seeds that differ here")
    parser.add_argument("--out", type=Path, default=OUT, help=f"the CSV (default {OUT.relative_to(ROOT)})")
    args, profile = parser.parse_known_args()
    profile = [a for a in profile if a != "--"] or CI_PROFILE
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="replay_check.") as tmp, ThreadPoolExecutor(args.jobs) as pool:
        rows = []
        for row in pool.map(lambda s: check_seed(s, args.replays, profile, Path(tmp), args.keep), args.seeds):
            rows.append(row)
            print(f"seed {row['seed']}: {'identical' if row['identical'] else 'DIFFERS'}, "
                  f"{row['distinct_traces']} distinct traces in {row['replays']} replays", flush=True)
    identical = sum(1 for r in rows if r["identical"])
    print(f"replay_check: {identical} of {len(rows)} seeds identical over {args.replays} replays each "
          f"({' '.join(profile)}), {time.monotonic() - started:,.1f} wall s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {args.out}")
    sys.exit(0 if identical == len(rows) else 1)


if __name__ == "__main__":
    main()
