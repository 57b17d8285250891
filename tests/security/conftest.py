"""Fixtures of the security tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from coapkb.security import generate_team
from coapkb.security.keys import default_members


@pytest.fixture
def team_dir(tmp_path: Path) -> Path:
    """A team of three robots (and feeder, central, operator): ``coapkb keys``'s files."""
    generate_team(tmp_path / "team", default_members(3))
    return tmp_path / "team"

