"""Fixtures for every test folder; the helpers themselves live in ``support``
(import them from there: several folders have a conftest of their own, and
``from support import`` would find whichever was loaded last)."""

from support import (
    kb_server,  # noqa: F401 -- registers the fixture
    pytest_runtest_makereport,  # noqa: F401 -- in CI, a skip is a failure
)
