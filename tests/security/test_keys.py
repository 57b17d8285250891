"""Team key material: files, permissions, the trust list, the [security] section."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from coapkb.config import ConfigError, parse_config
from coapkb.security import SecurityError, generate_team, load_identity, load_trust
from coapkb.security.keys import curve_public, default_members


def test_keys_are_private_and_the_trust_list_public(team_dir: Path) -> None:
    trust = load_trust(team_dir)
    assert [m.name for m in trust.members] == ["Robot1", "Robot2", "Robot3", "feeder", "central", "operator"]
    assert len({m.kid for m in trust.members}) == len(trust.members)
    for m in trust.members:
        assert (team_dir / f"{m.name}.key").stat().st_mode & 0o777 == 0o600
        assert (team_dir / f"{m.name}.curve").stat().st_mode & 0o777 == 0o600
    document = (team_dir / "team.json").read_text()
    identity = load_identity(team_dir, "Robot2")
    assert identity.private_d.hex() not in document  # no private key in the public file
    assert identity.curve_secret and identity.curve_secret not in document
    assert identity.private_d.hex() not in repr(identity) and identity.curve_secret not in repr(identity)
    assert identity.member.role == "robot" and load_identity(team_dir, "feeder").member.role == "feeder"


def test_a_team_directory_is_never_overwritten(team_dir: Path) -> None:
    with pytest.raises(SecurityError, match="already holds a team"):
        generate_team(team_dir, default_members(3))


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "Robot1.key").unlink(), "cannot read private key .*Robot1.key: No such file"),
    (lambda d: os.chmod(d / "Robot1.key", 0o644), "readable by group or others"),
    (lambda d: (d / "Robot1.key").write_bytes(b"\xff\x00garbage"), "not a CBOR COSE_Key"),
    (lambda d: os.replace(d / "Robot2.key", d / "Robot1.key"), "does not match Robot1's credential"),
    (lambda d: (d / "team.json").unlink(), "cannot read the team's trust list"),
    (lambda d: (d / "Robot1.curve").unlink(), "cannot read private key .*Robot1.curve"),
    (lambda d: os.replace(d / "Robot2.curve", d / "Robot1.curve"), "does not match Robot1's Curve key"),
    (lambda d: (d / "Robot1.curve").write_bytes(b"~" * 40), "Robot1.curve: not a Z85 Curve25519 secret key"),
    (lambda d: (d / "Robot1.curve").write_bytes(b"abc"), "Robot1.curve: not a Z85 Curve25519 secret key"),
    (lambda d: (d / "team.json").write_text(json.dumps({"format": "other"})), "not a coapkb trust list"),
])
def test_bad_key_material_is_one_clear_error(team_dir: Path, damage, message: str) -> None:
    damage(team_dir)
    with pytest.raises(SecurityError, match=message) as info:
        load_identity(team_dir, "Robot1")
    assert "\n" not in str(info.value)


def test_the_curve_public_key_is_zeromqs() -> None:
    zmq = pytest.importorskip("zmq")
    for _ in range(50):
        public, secret = zmq.curve_keypair()
        assert curve_public(secret) == public.decode("ascii")
    for malformed in (b"", b"#" * 40, b"0" * 39, b"~" * 40):
        with pytest.raises(ValueError):
            curve_public(malformed)


def test_a_stranger_is_not_in_the_trust_list(team_dir: Path) -> None:
    with pytest.raises(SecurityError, match="not in the team's trust list"):
        load_identity(team_dir, "Robot9")


def _config(security: object) -> dict:
    return {
        "robot_id": "Robot1", "bind": "coap://127.0.0.1:5701",
        "team": {"Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Object", "Location", "Capability"]}},
        "security": security,
    }


def test_security_section_is_validated(team_dir: Path, tmp_path: Path) -> None:
    config = parse_config(_config({"credentials": "team"}), base_dir=tmp_path)
    assert config.security is not None and config.security.credentials == team_dir
    with pytest.raises(ConfigError, match="security.credentials: no team.json"):
        parse_config(_config({"credentials": "nowhere"}), base_dir=tmp_path)
    with pytest.raises(ConfigError, match="security.key: unknown field"):
        parse_config(_config({"credentials": "team", "key": "x"}), base_dir=tmp_path)
    with pytest.raises(ConfigError, match="security.identity"):
        parse_config(_config({"credentials": "team", "identity": 3}), base_dir=tmp_path)
    with pytest.raises(ConfigError, match="security: expected a table"):
        parse_config(_config("team"), base_dir=tmp_path)
