#!/bin/sh
# The long run: each target in turn (one core: the other is for other work),
# SECONDS of fuzzing from the committed corpus, then the corpus minimised:
# the fewest inputs of old and new that keep every feature (-set_cover_merge),
# plus the named seeds and regressions.  Logs and any crash files go to OUT.
#
#     fuzz/long_run.sh OUT [SECONDS] [TARGET...]
set -u
cd "$(dirname "$0")/.."
out=${1:?usage: fuzz/long_run.sh OUT [SECONDS] [TARGET...]}
seconds=${2:-600}
shift; [ $# -gt 0 ] && shift
py=${PYTHON:-.venv/bin/python}
targets=${*:-$($py fuzz/run.py --list)}
mkdir -p "$out"
for t in $targets; do
    mkdir -p "$out/work/$t"
    $py fuzz/run.py "$t" -max_total_time="$seconds" -timeout=10 -print_final_stats=1 \
        -artifact_prefix="$out/$t-" "$out/work/$t" "fuzz/corpus/$t" > "$out/$t.log" 2>&1
    echo "$t: exit $?" >> "$out/summary.txt"
    rm -rf "$out/min/$t" && mkdir -p "$out/min/$t"
    if $py fuzz/run.py "$t" -set_cover_merge=1 "$out/min/$t" "fuzz/corpus/$t" "$out/work/$t" > "$out/$t.merge.log" 2>&1
    then
        cp fuzz/corpus/"$t"/seed-* fuzz/corpus/"$t"/regression-* "$out/min/$t/" 2>/dev/null
        rm -rf "fuzz/corpus/$t" && cp -r "$out/min/$t" "fuzz/corpus/$t"
    fi
done
