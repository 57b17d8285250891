"""The code passes the lint: ruff over the package, the experiments, the
tests, the fuzzers and the tools, with the rules in pyproject.toml (each
ignore there, and each ``noqa`` left in the code, says why)."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from support import ROOT, comments


def test_ruff_finds_nothing() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise",
         "coapkb", "experiments", "tests", "fuzz", "tools"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


_NOQA = re.compile(r"#\s*noqa\b(?P<codes>:\s*[A-Z]+[0-9]+(?:\s*,\s*[A-Z]+[0-9]+)*)?(?P<rest>.*)", re.IGNORECASE)


def unexplained_noqa(comment: str) -> bool:
    """Whether ``comment`` holds a ``noqa`` without its rule codes, or
    without a reason after them (``# noqa: BLE001 - why``)."""
    match = _NOQA.search(comment)
    return match is not None and (match["codes"] is None or re.match(r"\s*(?:-{1,2}|:|#|\()?\s*\w", match["rest"]) is None)


@pytest.mark.parametrize("comment, unexplained", [
    ("# noqa: BLE001 - a trace must never break a send", False),
    ("# noqa: BLE001 -- reported by stop()", False),
    ("# noqa: E402, F401 - imported for its side effect", False),
    ("# noqa: E731", True),
    ("# noqa: E731  ", True),
    ("# noqa", True),
    ("# noqa - no codes", True),
    ("# a plain comment", False),
])
def test_a_noqa_is_explained_after_its_codes(comment: str, unexplained: bool) -> None:
    assert unexplained_noqa(comment) is unexplained


def test_every_noqa_in_the_package_names_its_codes_and_says_why() -> None:
    found = [f"{where}: {text}" for where, text in comments(ROOT / "coapkb") if unexplained_noqa(text)]
    assert found == [], "\n".join(found)
