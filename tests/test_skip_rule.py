"""The one rule for skips (support.require and the report hook): a skip on a
developer's machine, a failure in CI, whatever way the test asked to skip;
but a case that cannot apply (support.not_applicable) is skipped in CI too."""

from __future__ import annotations

import pytest
from support import in_ci

pytest_plugins = ["pytester"]

#: A test folder with the project's rule (the hook as tests/conftest.py registers it)
#: and one test per way of skipping.
CONFTEST = "from support import pytest_runtest_makereport  # noqa: F401\n"
INI = "[pytest]\nasyncio_default_fixture_loop_scope = function\n"
SKIPPING = """
import pytest
from support import not_applicable, require

@pytest.fixture(scope="module")
def missing_tool():
    require(False, "the tool is not installed")

def test_require():
    require(False, "no IPv6 loopback")

def test_require_met():
    require(True, "never shown")

@pytest.mark.skipif(True, reason="a marker")
def test_marker():
    pass

def test_fixture_a(missing_tool):
    pass

def test_fixture_b(missing_tool):
    pass

def test_not_applicable():
    not_applicable("DDS cannot be secured")

@pytest.mark.xfail(reason="known bug", strict=True)
def test_expected_failure():
    assert False
"""


@pytest.mark.parametrize(
    ("value", "on"),
    [("true", True), ("1", True), ("yes", True), ("TRUE", True), ("on", True),
     ("false", False), ("0", False), ("no", False), ("", False), (None, False)],
)
def test_ci_is_on_for_a_true_value_only(value: str | None, on: bool) -> None:
    assert in_ci({} if value is None else {"CI": value}) is on


def test_skips_skip_outside_ci(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CI", "false")
    pytester.makeini(INI)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(SKIPPING)
    result = pytester.runpytest("-p", "no:cacheprovider", "-rs")
    result.assert_outcomes(passed=1, skipped=5, xfailed=1)
    result.stdout.fnmatch_lines(["*no IPv6 loopback*", "*does not apply: DDS cannot be secured*"])


def test_every_kind_of_skip_fails_in_ci(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CI", "true")
    pytester.makeini(INI)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(SKIPPING)
    result = pytester.runpytest("-p", "no:cacheprovider", "-rs")
    # a skip in the test fails it; one in set-up (a marker, a fixture) is an error; an expected failure stays
    # one, and a case that does not apply stays skipped
    result.assert_outcomes(passed=1, failed=1, errors=3, skipped=1, xfailed=1)
    result.stdout.fnmatch_lines([
        "*required in CI: a marker*",
        "*required in CI: the tool is not installed*",
        "*required in CI: no IPv6 loopback*",
        "SKIPPED *test_every_kind_of_skip_fails_in_ci.py:*: does not apply: DDS cannot be secured",
    ])
