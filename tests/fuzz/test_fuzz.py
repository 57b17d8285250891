"""The fuzz targets (fuzz/targets.py): the committed corpus of every target
replays without a crash, and a few seconds of coverage-guided fuzzing per
target find none either (``python fuzz/run.py`` fuzzes for as long as asked)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from support import ROOT

FUZZ = ROOT / "fuzz"
sys.path.insert(0, str(FUZZ))

import targets  # noqa: E402  (fuzz/ is no package: it is on sys.path above)

# Fuzzed literals are odd on purpose ("Parsing weird boolean ...").
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning:rdflib.term")

NAMES = targets.names()
#: Bounds on the committed corpus of one target, so the repository stays small.
MAX_FILES, MAX_BYTES = 300, 1_000_000


def corpus(name: str) -> list[Path]:
    return sorted((FUZZ / "corpus" / name).glob("*"))


def test_every_target_has_a_small_corpus() -> None:
    assert NAMES and set(NAMES) == {p.name for p in (FUZZ / "corpus").iterdir()}
    for name in NAMES:
        files = corpus(name)
        assert files, f"{name}: no corpus (python fuzz/run.py --seed writes the seeds)"
        assert len(files) <= MAX_FILES and sum(p.stat().st_size for p in files) <= MAX_BYTES, name


def test_seeds_are_accepted_by_their_targets() -> None:
    # The seeds are valid inputs: a target that refuses them all fuzzes only its error paths.
    for name, inputs in targets.seeds().items():
        for data in inputs:
            targets.TARGETS[name](data)


@pytest.mark.parametrize("name", NAMES)
def test_corpus_replays_without_a_crash(name: str) -> None:
    fn = targets.TARGETS[name]
    for path in corpus(name):
        try:
            fn(path.read_bytes())
        except Exception as exc:
            raise AssertionError(f"{name}: {path.relative_to(ROOT)} crashes the parser") from exc


def test_the_targets_leave_nothing_in_the_temporary_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fuzzing workers end without exit handlers: nothing a target makes there would be removed.
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    for name, inputs in targets.seeds().items():
        for data in inputs:
            targets.TARGETS[name](data)
    assert list(tmp_path.iterdir()) == []


def test_run_lists_the_targets() -> None:
    listed = subprocess.run([sys.executable, str(FUZZ / "run.py"), "--list"], capture_output=True, text=True, check=True)
    assert listed.stdout.split() == NAMES


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_a_short_fuzzing_run_finds_no_crash(name: str, tmp_path: Path) -> None:
    # New inputs go to tmp_path/work (the first folder), so the committed corpus is only read.
    (tmp_path / "work").mkdir()
    run = subprocess.run(
        [sys.executable, str(FUZZ / "run.py"), name, "-max_total_time=2", "-timeout=10",
         f"-artifact_prefix={tmp_path}/", str(tmp_path / "work"), str(FUZZ / "corpus" / name)],
        capture_output=True, text=True, timeout=120,
    )
    found = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("crash-", "timeout-", "oom-", "leak-")))
    assert run.returncode == 0 and not found, f"{name}: exit {run.returncode}, {found}\n{run.stderr[-4000:]}"
    assert "DONE" in run.stderr, run.stderr[-2000:]
