"""A team's key material: each member's EDHOC credential and the trust list.

One directory per team (``coapkb keys --team-dir DIR --robots N``):

``team.json``
    The trust list (public): every member's name, role and credential, a
    CWT Claims Set (CCS, RFC 9528 section 3.5.2, the ``kccs`` form of
    RFC 8392/9052) carrying a P-256 public key and a one-byte key id.  A
    robot admits an EDHOC peer only if its credential is in this file.
``NAME.key``
    One member's private key as a COSE_Key (RFC 9052: kty EC2, crv P-256,
    d), CBOR, mode 0600; the format aiocoap's ``private_key_file`` reads, so
    ``aiocoap-client --credentials`` can use the same file.
``NAME.curve``
    The same member's CurveZMQ (RFC 26 / Curve25519) secret key, Z85, mode
    0600, for the ZeroMQ transport; its public key is in ``team.json``.
    (A P-256 key cannot be turned into a Curve25519 one; each member has
    both, and the trust list binds them to one name and role.)
``team-ca.pem``, ``NAME.tls.pem``, ``NAME.tls.key``
    The team's X.509 CA certificate and the member's certificate and key
    (mode 0600) for TLS with mutual authentication, for the Zenoh transport
    (:mod:`.tls`); ``team.json`` pins their SHA-256.

Roles decide what a member may do on a robot (:mod:`.policy`): ``robot``
(query, observe, post decisions if it is its cluster's decider), ``feeder``
(also post tasks), ``server`` (the central KB server of the baseline) and
``client`` (an operator's ``coapkb query``: read only).

Private keys are written once (``O_EXCL``) with mode 0600 and never logged;
loading refuses a key file that others may read, as aiocoap does.
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cbor2

from .errors import SecurityError

if TYPE_CHECKING:
    from .tls import TlsFiles

TRUST_FILE = "team.json"
TRUST_FORMAT = "coapkb-team/1"
ROLES = ("robot", "feeder", "server", "client")
#: EDHOC cipher suite 2 (AES-CCM-16-64-128, SHA-256, P-256): the one lakers
#: and aiocoap 0.4.17 implement, and the one RFC 9528 makes mandatory for
#: constrained nodes.
CIPHER_SUITE = 2
#: EDHOC method 3: both sides authenticate with static Diffie-Hellman keys
#: (the shortest messages, RFC 9528 section 3.2).
EDHOC_METHOD = 3

# COSE / CWT labels (RFC 9052, RFC 8392, RFC 8747)
_KTY, _KID, _CRV, _X, _Y, _D = 1, 2, -1, -2, -3, -4
_KTY_EC2, _CRV_P256 = 2, 1
_CWT_SUB, _CWT_CNF, _CNF_COSE_KEY = 2, 8, 1


@dataclass(frozen=True)
class TeamMember:
    """One entry of the trust list."""

    name: str
    role: str
    #: The credential's key id (``kid`` of its COSE_Key): EDHOC sends it by
    #: reference as ``ID_CRED_x = {4: kid}``.
    kid: bytes
    #: The CCS (without the ``kccs`` wrapper), canonical CBOR: what EDHOC
    #: authenticates (CRED_I / CRED_R).
    ccs: bytes
    #: CurveZMQ public key, Z85 (40 characters); None in a team made without.
    curve_public: str | None = None
    #: SHA-256 (hex) of the member's X.509 certificate; None in a team made without.
    tls_sha256: str | None = None

    def ccs_map(self) -> dict[Any, Any]:
        ccs: dict[Any, Any] = cbor2.loads(self.ccs)
        return ccs

    def aiocoap_cred(self) -> dict[int, dict[Any, Any]]:
        """The credential as aiocoap's ``own_cred`` / ``peer_cred``: ``{14: CCS}``."""
        return {14: self.ccs_map()}


@dataclass(frozen=True)
class TeamTrust:
    """The trust list: who is in the team."""

    members: tuple[TeamMember, ...]
    #: SHA-256 (hex) of the team CA's certificate; None in a team made without TLS.
    tls_ca_sha256: str | None = None

    def by_name(self, name: str) -> TeamMember | None:
        return next((m for m in self.members if m.name == name), None)

    def by_kid(self, kid: bytes) -> TeamMember | None:
        return next((m for m in self.members if m.kid == kid), None)

    def by_ccs(self, ccs: bytes) -> TeamMember | None:
        return next((m for m in self.members if m.ccs == ccs), None)

    def by_curve(self, public_z85: str) -> TeamMember | None:
        return next((m for m in self.members if m.curve_public is not None and m.curve_public == public_z85), None)


@dataclass(frozen=True)
class TeamIdentity:
    """What one member holds: its own entry, its private key, the trust list."""

    member: TeamMember
    #: The P-256 private scalar, 32 bytes.  Never logged; ``repr`` hides it.
    private_d: bytes
    trust: TeamTrust
    team_dir: Path
    #: The CurveZMQ secret key, Z85; None if the team has no Curve keys.
    curve_secret: str | None = None

    @property
    def name(self) -> str:
        return self.member.name

    @property
    def key_file(self) -> Path:
        return self.team_dir / f"{self.member.name}.key"

    def tls(self) -> TlsFiles:
        """The member's TLS certificate and key and the team CA (Zenoh's ``tls/``
        links), checked now: one :class:`SecurityError` line if not usable."""
        from .tls import check_tls

        if self.trust.tls_ca_sha256 is None or self.member.tls_sha256 is None:
            raise SecurityError(f"{self.team_dir}: the team has no TLS certificates (make it again with coapkb keys)")
        return check_tls(self.team_dir, self.member.name, self.trust.tls_ca_sha256, self.member.tls_sha256)

    def __repr__(self) -> str:
        return f"TeamIdentity({self.member.name!r}, role={self.member.role!r}, team_dir={str(self.team_dir)!r})"


def _public_ccs(name: str, kid: bytes, d: bytes) -> bytes:
    from cryptography.hazmat.primitives.asymmetric import ec

    public = ec.derive_private_key(int.from_bytes(d, "big"), ec.SECP256R1()).public_key().public_numbers()
    cose_key = {_KTY: _KTY_EC2, _KID: kid, _CRV: _CRV_P256, _X: public.x.to_bytes(32, "big"), _Y: public.y.to_bytes(32, "big")}
    return cbor2.dumps({_CWT_SUB: name, _CWT_CNF: {_CNF_COSE_KEY: cose_key}}, canonical=True)


def _write_private(path: Path, d: bytes) -> None:
    # Created 0600 in one step (no window where it is readable), never overwritten.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with open(fd, "wb") as out:
            cbor2.dump({_KTY: _KTY_EC2, _CRV: _CRV_P256, _D: d}, out)
    except BaseException:
        path.unlink(missing_ok=True)
        raise


def generate_team(team_dir: str | Path, members: Iterable[tuple[str, str]]) -> TeamTrust:
    """Make a team directory: a private key per ``(name, role)`` and the trust list.

    Refuses a directory that already holds a team (keys are never replaced
    in place: a robot running with the old ones would lock itself out)."""
    from cryptography.hazmat.primitives.asymmetric import ec

    team_dir = Path(team_dir)
    members = list(members)
    names = [n for n, _ in members]
    if len(set(names)) != len(names):
        raise SecurityError("team members must have distinct names")
    if len(members) > 255:
        raise SecurityError("at most 255 team members (one-byte key ids)")
    for name, role in members:
        if role not in ROLES:
            raise SecurityError(f"{name}: role {role!r} is not one of {', '.join(ROLES)}")
        if not name or "/" in name or name.startswith("."):
            raise SecurityError(f"{name!r} is not a usable member name")
    try:
        team_dir.mkdir(parents=True, exist_ok=True)
        os.chmod(team_dir, 0o700)
    except OSError as exc:
        raise SecurityError(f"cannot create team directory {team_dir}: {exc.strerror}") from None
    if (team_dir / TRUST_FILE).exists():
        raise SecurityError(f"{team_dir} already holds a team ({TRUST_FILE}): its keys are kept; use them, "
                            f"or remove the directory (every member then needs the new keys)")
    import zmq

    entries = []
    for index, (name, role) in enumerate(members):
        d = ec.generate_private_key(ec.SECP256R1()).private_numbers().private_value.to_bytes(32, "big")
        # kid 0x00..0x17 encode as one-byte CBOR ints in EDHOC's compact ID_CRED;
        # larger ones still work, one byte longer.
        kid = bytes([index])
        try:
            _write_private(team_dir / f"{name}.key", d)
        except FileExistsError:
            raise SecurityError(f"{team_dir / (name + '.key')} already exists; use a new directory") from None
        except OSError as exc:
            raise SecurityError(f"cannot write {team_dir / (name + '.key')}: {exc.strerror}") from None
        curve_public, curve_secret = zmq.curve_keypair()
        try:
            fd = os.open(team_dir / f"{name}.curve", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with open(fd, "wb") as out:
                out.write(curve_secret + b"\n")
        except OSError as exc:
            raise SecurityError(f"cannot write {team_dir / (name + '.curve')}: {exc.strerror}") from None
        entries.append(TeamMember(name, role, kid, _public_ccs(name, kid, d), curve_public.decode("ascii")))
    from .tls import generate_tls

    ca_pin, pins = generate_tls(team_dir, [m.name for m in entries])
    entries = [replace(m, tls_sha256=pins[m.name]) for m in entries]
    trust = TeamTrust(tuple(entries), ca_pin)
    document = {
        "format": TRUST_FORMAT,
        "edhoc": {"suite": CIPHER_SUITE, "method": EDHOC_METHOD},
        "tls": {"ca_sha256": ca_pin},
        "members": [{"name": m.name, "role": m.role, "kid": m.kid.hex(), "ccs": m.ccs.hex(), "curve": m.curve_public,
                     "tls_sha256": m.tls_sha256} for m in entries],
    }
    (team_dir / TRUST_FILE).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    return trust


def load_trust(team_dir: str | Path) -> TeamTrust:
    path = Path(team_dir) / TRUST_FILE
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise SecurityError(f"cannot read the team's trust list {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise SecurityError(f"{path}: not JSON: {exc}") from None
    if not isinstance(document, dict) or document.get("format") != TRUST_FORMAT:
        raise SecurityError(f"{path}: not a coapkb trust list (format {TRUST_FORMAT})")
    members = []
    try:
        for raw in document["members"]:
            member = TeamMember(raw["name"], raw["role"], bytes.fromhex(raw["kid"]), bytes.fromhex(raw["ccs"]),
                                raw.get("curve"), raw.get("tls_sha256"))
            if member.curve_public is not None and len(member.curve_public) != 40:
                raise ValueError(f"member {member.name}: curve is not a Z85 public key")
            ccs = member.ccs_map()
            if ccs[_CWT_CNF][_CNF_COSE_KEY][_KID] != member.kid or member.role not in ROLES:
                raise ValueError(f"member {member.name}: kid or role inconsistent")
            members.append(member)
    except (KeyError, TypeError, ValueError, cbor2.CBORDecodeError) as exc:
        raise SecurityError(f"{path}: malformed trust list: {exc}") from None
    kids = [m.kid for m in members]
    if len(set(kids)) != len(kids) or len({m.name for m in members}) != len(members):
        raise SecurityError(f"{path}: duplicate member names or key ids")
    tls = document.get("tls")
    ca_pin = tls.get("ca_sha256") if isinstance(tls, dict) else None
    return TeamTrust(tuple(members), ca_pin if isinstance(ca_pin, str) else None)


def load_identity(team_dir: str | Path, name: str) -> TeamIdentity:
    """``name``'s private key and the trust list from ``team_dir``.

    Every failure is one :class:`SecurityError` line naming the file."""
    team_dir = Path(team_dir)
    trust = load_trust(team_dir)
    member = trust.by_name(name)
    if member is None:
        raise SecurityError(f"{name} is not in the team's trust list {team_dir / TRUST_FILE}")
    path = team_dir / f"{name}.key"
    try:
        mode = path.stat().st_mode
        if mode & 0o077:
            # As aiocoap: a private key others can read is compromised or about to be.
            raise SecurityError(f"{path}: private key is readable by group or others (chmod 600 it)")
        if not stat.S_ISREG(mode):
            raise SecurityError(f"{path}: not a regular file")
        key = cbor2.loads(path.read_bytes())
    except OSError as exc:
        raise SecurityError(f"cannot read private key {path}: {exc.strerror}") from None
    except (ValueError, cbor2.CBORDecodeError):
        raise SecurityError(f"{path}: not a CBOR COSE_Key") from None
    if not isinstance(key, dict) or key.get(_KTY) != _KTY_EC2 or key.get(_CRV) != _CRV_P256 \
            or not isinstance(key.get(_D), bytes) or len(key[_D]) != 32:
        raise SecurityError(f"{path}: expected a P-256 COSE_Key with d")
    if _public_ccs(member.name, member.kid, key[_D]) != member.ccs:
        raise SecurityError(f"{path}: the key does not match {name}'s credential in {TRUST_FILE}")
    return TeamIdentity(member, key[_D], trust, team_dir, _load_curve(team_dir, member))


def _load_curve(team_dir: Path, member: TeamMember) -> str | None:
    """The member's CurveZMQ secret key, checked against its public key."""
    if member.curve_public is None:
        return None
    path = team_dir / f"{member.name}.curve"
    try:
        if path.stat().st_mode & 0o077:
            raise SecurityError(f"{path}: private key is readable by group or others (chmod 600 it)")
        secret = path.read_bytes().strip()
        public = curve_public(secret)
    except OSError as exc:
        raise SecurityError(f"cannot read private key {path}: {exc.strerror}") from None
    except ValueError:
        raise SecurityError(f"{path}: not a Z85 Curve25519 secret key") from None
    if public != member.curve_public:
        raise SecurityError(f"{path}: the key does not match {member.name}'s Curve key in {TRUST_FILE}")
    return secret.decode("ascii")


#: Z85's alphabet (ZeroMQ RFC 32), digit values 0..84 in order.
_Z85 = "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#"
_Z85_VALUE = {c: v for v, c in enumerate(_Z85.encode("ascii"))}


def curve_public(secret_z85: bytes) -> str:
    """The CurveZMQ public key (Z85) of a Z85 secret key, as ``zmq.curve_public``.

    Computed with cryptography's X25519, which OSCORE loads anyway, so that
    loading an identity does not load ZeroMQ into every robot.  ValueError
    if ``secret_z85`` is not 40 Z85 characters."""
    from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey

    if len(secret_z85) != 40:
        raise ValueError("a Curve25519 secret key is 40 Z85 characters")
    secret = bytearray()
    for start in range(0, 40, 5):
        value = 0
        for char in secret_z85[start:start + 5]:
            if char not in _Z85_VALUE:
                raise ValueError(f"{chr(char)!r} is not a Z85 character")
            value = value * 85 + _Z85_VALUE[char]
        if value >= 1 << 32:
            raise ValueError("not a Z85 encoding")
        secret += value.to_bytes(4, "big")
    public = X25519PrivateKey.from_private_bytes(bytes(secret)).public_key().public_bytes_raw()
    chars = []
    for start in range(0, 32, 4):
        value = int.from_bytes(public[start:start + 4], "big")
        chars += [_Z85[value // 85 ** power % 85] for power in range(4, -1, -1)]
    return "".join(chars)


def default_members(robots: int, extra_robots: Iterable[str] = ()) -> list[tuple[str, str]]:
    """Robot1..RobotN, the feeder, the central server and an operator."""
    names = [(f"Robot{i}", "robot") for i in range(1, robots + 1)] + [(n, "robot") for n in extra_robots]
    return names + [("feeder", "feeder"), ("central", "server"), ("operator", "client")]


def aiocoap_client_credentials(team_dir: str | Path, identity: str, peer: str, uri: str) -> str:
    """A credentials file for ``aiocoap-client --credentials FILE.diag``
    (CBOR diagnostic notation): ``identity`` talks EDHOC/OSCORE to the
    member ``peer`` serving at ``uri``.  It names the private key file; it
    does not contain the key."""
    import cbor_diag

    team_dir = Path(team_dir).resolve()
    me = load_identity(team_dir, identity)  # checks the key file now, not at the first request
    them = me.trust.by_name(peer)
    if them is None:
        raise SecurityError(f"{peer} is not in the team's trust list {team_dir / TRUST_FILE}")
    entry = {
        "edhoc-oscore": {
            "suite": CIPHER_SUITE, "method": EDHOC_METHOD, "own_cred_style": "by-key-id",
            "own_cred": me.member.aiocoap_cred(), "private_key_file": str(me.key_file), "peer_cred": them.aiocoap_cred(),
        }
    }
    return cbor_diag.cbor2diag(cbor2.dumps({uri.rstrip("/") + "/*": entry})) + "\n"
