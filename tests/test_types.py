"""The package type-checks: mypy over coapkb with the configuration in
pyproject.toml (its overrides name the known debts, each narrowed to its
error codes), and every ``type: ignore`` left in the code names its error
codes and says why."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from support import ROOT, comments


def test_mypy_finds_no_error() -> None:
    result = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary"], cwd=ROOT, capture_output=True,
                            text=True, timeout=280)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


_IGNORE = re.compile(r"#\s*type:\s*ignore(?P<codes>\[[a-z0-9, -]+\])?(?P<rest>.*)")


def unexplained_ignore(comment: str) -> bool:
    """Whether ``comment`` holds a ``type: ignore`` without its error codes,
    or without a comment after it saying why."""
    match = _IGNORE.search(comment)
    return match is not None and (match["codes"] is None or re.match(r"\s*#\s*\S", match["rest"]) is None)


@pytest.mark.parametrize("comment, unexplained", [
    ("# type: ignore[arg-type]  # rdflib checked the positions", False),
    ("# type: ignore[union-attr,misc]  # why", False),
    ("# type: ignore[arg-type]", True),
    ("# type: ignore[arg-type]  ", True),
    ("# type: ignore  # no codes", True),
    ("# type: ignore", True),
    ("# type: ignore[arg-type] why, but not as a comment", True),
    ("# a plain comment", False),
])
def test_an_ignore_is_explained_by_a_comment_after_its_codes(comment: str, unexplained: bool) -> None:
    assert unexplained_ignore(comment) is unexplained


def test_every_type_ignore_in_the_package_names_its_codes_and_says_why() -> None:
    """Like ``# type: ignore[attr-defined]  # pyoxigraph's stubs lack it``; a
    debt a whole module has goes into pyproject.toml's overrides, with a
    comment there."""
    found = [f"{where}: {text}" for where, text in comments(ROOT / "coapkb") if unexplained_ignore(text)]
    assert found == [], "\n".join(found)
