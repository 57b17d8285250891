"""The feeder's side of the team's security."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ..security import load_identity

#: The member name the feeder's key has in a team directory (``coapkb keys``).
FEEDER_IDENTITY = "feeder"


def feeder_security(transport: str, team_dir: Path | None, expected: Mapping[str, str]) -> Any:
    """The feeder's OSCORE/EDHOC, CurveZMQ or mTLS client side over
    ``transport`` with its key from ``team_dir``, or None for an insecure
    team.  ``expected``: HOST:PORT -> the member that must answer there."""
    if team_dir is None:
        return None
    if transport == "zmq":
        from ..security.curve import ZmqClientSecurity

        return ZmqClientSecurity(load_identity(team_dir, FEEDER_IDENTITY), dict(expected))
    if transport == "zenoh":
        from ..security.zenoh_tls import ZenohClientSecurity

        return ZenohClientSecurity(load_identity(team_dir, FEEDER_IDENTITY), dict(expected))
    from ..security.coap import ClientSecurity

    return ClientSecurity(load_identity(team_dir, FEEDER_IDENTITY), dict(expected))
