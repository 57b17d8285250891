"""The code passes the lint: ruff over the package, the experiments, the
tests, the fuzzers and the tools, with the rules in pyproject.toml (each
ignore there, and each ``noqa`` left in the code, says why)."""

from __future__ import annotations

import subprocess
import sys

from support import ROOT


def test_ruff_finds_nothing() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise",
         "coapkb", "experiments", "tests", "fuzz", "tools"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
