"""The feeder's side of the team's security."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from ..security import client_security, load_identity
from ..transport import ClientSecurity

#: The member name the feeder's key has in a team directory (``coapkb keys``).
FEEDER_IDENTITY = "feeder"


def feeder_security(transport: str, team_dir: Path | None, expected: Mapping[str, str]) -> ClientSecurity | None:
    """The feeder's client side of ``transport``'s security (OSCORE/EDHOC,
    CurveZMQ or mTLS) with its key from ``team_dir``, or None for an
    insecure team.  ``expected``: HOST:PORT -> the member that must answer there."""
    if team_dir is None:
        return None
    return client_security(transport, load_identity(team_dir, FEEDER_IDENTITY), dict(expected))
