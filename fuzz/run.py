"""Run one fuzz target, write the seed corpora, or replay every corpus.

    python fuzz/run.py --list                 the targets
    python fuzz/run.py --seed                 write the seeds to fuzz/corpus/TARGET/
    python fuzz/run.py --replay [TARGET...]   every corpus file once, plain Python
    python fuzz/run.py --report OUT           the results table of fuzz/long_run.sh OUT
    python fuzz/run.py TARGET [libFuzzer flags] [DIR...]

A fuzzing run reads and grows ``fuzz/corpus/TARGET/`` unless corpus folders
are given (then libFuzzer writes new inputs to the first), with the
dictionary ``fuzz/dicts/TARGET.dict`` if there is one.  Only coapkb's
modules are instrumented for coverage: the libraries stay fast.
"""

from __future__ import annotations

import hashlib
import logging
import re
import shlex
import sys
import traceback
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
CORPUS = HERE / "corpus"
sys.path[:0] = [str(HERE), str(HERE.parent)]


def seed() -> None:
    import targets

    for name, inputs in targets.seeds().items():
        folder = CORPUS / name
        folder.mkdir(parents=True, exist_ok=True)
        for data in inputs:
            (folder / f"seed-{hashlib.sha1(data).hexdigest()[:16]}").write_bytes(data)
        print(f"{name}: {len(inputs)} seeds in {folder.relative_to(HERE.parent)}")


def replay(names: list[str]) -> int:
    """Every corpus file of every target (or of ``names``) once; 1 if any crashed."""
    import targets

    failures = 0
    for name in names or targets.names():
        fn = targets.TARGETS[name]
        files = sorted((CORPUS / name).glob("*"))
        for path in files:
            try:
                fn(path.read_bytes())
            except Exception:  # noqa: BLE001 - any exception a parser lets out is the crash being looked for
                failures += 1
                print(f"CRASH {name} {path.relative_to(HERE.parent)}", file=sys.stderr)
                traceback.print_exc()
        print(f"{name}: {len(files)} inputs replayed")
    return 1 if failures else 0


def report(out: Path) -> None:
    """The results table of a long run (fuzz/long_run.sh OUT), in Markdown."""
    print("| target | executions | seconds | coverage (edges) | features | corpus (files, merged) | crashes | hangs |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for log in sorted(out.glob("*.log")):
        if log.name.endswith(".merge.log"):
            continue
        name, text = log.stem, log.read_text(errors="replace")
        status = re.findall(r"^#(\d+)\s+\S+\s+cov: (\d+) ft: (\d+)", text, re.M)
        done = re.search(r"^Done (\d+) runs in (\d+) second", text, re.M)
        executed = re.search(r"stat::number_of_executed_units: (\d+)", text)
        runs = done.group(1) if done else (executed.group(1) if executed else (status[-1][0] if status else "?"))
        rate = re.search(r"stat::average_exec_per_sec:\s+(\d+)", text)
        if done:
            seconds = done.group(2)
        elif executed and rate and int(rate.group(1)):  # stopped by a crash: about how long it ran
            seconds = f"~{int(executed.group(1)) // int(rate.group(1))}"
        else:
            seconds = "?"
        cov, ft = (status[-1][1], status[-1][2]) if status else ("?", "?")
        crashes = len(list(out.glob(f"{name}-crash-*"))) + len(list(out.glob(f"{name}-oom-*")))
        hangs = len(list(out.glob(f"{name}-timeout-*")))
        files = len(list((CORPUS / name).glob("*")))
        print(f"| {name} | {runs} | {seconds} | {cov} | {ft} | {files} | {crashes} | {hangs} |")


def fuzz(name: str, args: list[str]) -> None:
    import atheris

    with atheris.instrument_imports(include=["coapkb"]):
        import targets
    if name not in targets.TARGETS:
        sys.exit(f"unknown target {name!r}; targets: {', '.join(targets.names())}")
    if not any(not a.startswith("-") for a in args):  # no corpus folder given
        (CORPUS / name).mkdir(parents=True, exist_ok=True)
        args = [*args, str(CORPUS / name)]
    dictionary = HERE / "dicts" / f"{name}.dict"  # tokens the mutator splices in (SPARQL keywords, ...)
    if dictionary.exists() and not any(a.startswith("-dict=") for a in args):
        args = [f"-dict={dictionary}", *args]
    fn = targets.TARGETS[name]
    fn(b"")  # builds what a target builds once (the KB) before the first timed input
    # libFuzzer runs its first argument through the shell for -merge=1 and
    # -fork: the interpreter, this script and the target, not the bare script.
    command = " ".join(shlex.quote(part) for part in (sys.executable, sys.argv[0], name))
    atheris.Setup([command, *args], fn)
    atheris.Fuzz()


def main() -> int:
    # rdflib and aiocoap warn about odd literals and messages the targets
    # feed them on purpose; a crash is a traceback, which still shows.
    logging.disable(logging.WARNING)
    warnings.simplefilter("ignore")
    args = sys.argv[1:]
    if not args or args[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    if args[0] == "--list":
        import targets

        print("\n".join(targets.names()))
        return 0
    if args[0] == "--seed":
        seed()
        return 0
    if args[0] == "--report":
        report(Path(args[1]))
        return 0
    if args[0] == "--replay":
        return replay(args[1:])
    fuzz(args[0], args[1:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
