"""The package type-checks: mypy over coapkb with the configuration in
pyproject.toml (its overrides name the known debts, each narrowed to its
error codes)."""

from __future__ import annotations

import subprocess
import sys

from support import ROOT


def test_mypy_finds_no_error() -> None:
    result = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary"], cwd=ROOT, capture_output=True,
                            text=True, timeout=280)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
