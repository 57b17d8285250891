"""The ``[security]`` section of a robot's TOML configuration::

    [security]
    credentials = "team/"     # the team directory of `coapkb keys`
    identity = "Robot1"       # whose key to use; default: the robot's id

Without the section the robot runs unprotected (``coapkb team --insecure``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .keys import TRUST_FILE


@dataclass(frozen=True)
class SecurityConfig:
    #: The team directory: ``team.json`` and the members' ``NAME.key`` files.
    credentials: Path
    #: The member whose private key this process uses (None: the robot's id).
    identity: str | None = None

    def to_dict(self) -> dict[str, Any]:
        data: dict[str, Any] = {"credentials": str(self.credentials.resolve())}
        if self.identity is not None:
            data["identity"] = self.identity
        return data


def parse_security(data: Any, base_dir: Path) -> SecurityConfig:
    """Validate the section; raises ``ValueError`` with the field's name
    (``config.py`` turns it into a ConfigError).  The key itself is read at
    start-up (:func:`~coapkb.security.keys.load_identity`)."""
    if not isinstance(data, Mapping):
        raise ValueError("security: expected a table")
    unknown = sorted(set(data) - {"credentials", "identity"})
    if unknown:
        raise ValueError(f"security.{unknown[0]}: unknown field (known: credentials, identity)")
    raw = data.get("credentials")
    if not isinstance(raw, str) or not raw:
        raise ValueError("security.credentials: expected the team directory's path")
    path = Path(raw) if Path(raw).is_absolute() else base_dir / raw
    if not (path / TRUST_FILE).is_file():
        raise ValueError(
            f"security.credentials: no {TRUST_FILE} in {path}; make the team's keys with: coapkb keys --team-dir {path}"
        )
    identity = data.get("identity")
    if identity is not None and (not isinstance(identity, str) or not identity):
        raise ValueError("security.identity: expected a member name")
    return SecurityConfig(path, identity)
