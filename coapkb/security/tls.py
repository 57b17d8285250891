"""X.509 material for TLS with the team's trust (Zenoh's ``tls/`` links).

``coapkb keys`` writes, next to the EDHOC and Curve keys:

``team-ca.pem``
    The team's CA certificate (public; P-256, self-signed).  Its private key
    signs every member's certificate in :func:`generate_tls` and is then
    dropped, never written: nobody can mint a team certificate later (a team
    is never extended in place anyway; see :func:`.keys.generate_team`).
``NAME.tls.pem``
    The member's certificate: subject CN = the member's name (what Zenoh's
    link reports as its auth identifier), issued by the team CA, good for
    both TLS server and client authentication.  Its SHA-256 is pinned in
    ``team.json``.
``NAME.tls.key``
    The member's TLS private key, PKCS#8 PEM, mode 0600.  A key of its own
    rather than the EDHOC key: that one is a static Diffie-Hellman key, and a
    key should serve one algorithm (ECDH there, ECDSA here).

Zenoh reads the files itself (its config names paths, so keys never pass
through a config string that Zenoh might log).
"""

from __future__ import annotations

import datetime
import hashlib
import os
import stat
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from .errors import SecurityError

CA_FILE = "team-ca.pem"
#: Long enough for a fleet's life; a team re-keys by making a new directory.
VALIDITY = datetime.timedelta(days=3650)


def cert_file(team_dir: Path, name: str) -> Path:
    return team_dir / f"{name}.tls.pem"


def key_file(team_dir: Path, name: str) -> Path:
    return team_dir / f"{name}.tls.key"


def fingerprint(pem: bytes) -> str:
    """SHA-256 of the certificate's DER, hex: what ``team.json`` pins."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    der = x509.load_pem_x509_certificate(pem).public_bytes(serialization.Encoding.DER)
    return hashlib.sha256(der).hexdigest()


def generate_tls(team_dir: Path, names: Iterable[str]) -> tuple[str, dict[str, str]]:
    """Write the CA certificate and each member's certificate and key.

    Returns the CA's and every member's certificate fingerprint."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)  # clock skew
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"coapkb team CA {os.urandom(4).hex()}")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name).issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now).not_valid_after(now + VALIDITY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    ca_pem = ca.public_bytes(serialization.Encoding.PEM)
    _write(team_dir / CA_FILE, ca_pem, 0o644)
    pins: dict[str, str] = {}
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now).not_valid_after(now + VALIDITY)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            # rustls' verifier wants a subjectAltName; the name is a member's, not a host's
            # (clients do not check host names: see ZenohTls).
            .add_extension(x509.SubjectAlternativeName([x509.DNSName(_dns_label(name))]), critical=False)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        pem = cert.public_bytes(serialization.Encoding.PEM)
        key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                    serialization.NoEncryption())
        _write(key_file(team_dir, name), key_pem, 0o600)
        _write(cert_file(team_dir, name), pem, 0o644)
        pins[name] = fingerprint(pem)
    return fingerprint(ca_pem), pins


def _dns_label(name: str) -> str:
    """A DNS-shaped form of a member name (SAN dNSName must be ASCII LDH)."""
    label = "".join(c if c.isascii() and (c.isalnum() or c == "-") else "-" for c in name.lower()).strip("-")
    return f"{label or 'member'}.coapkb.invalid"


def _write(path: Path, data: bytes, mode: int) -> None:
    # Created with its mode in one step (no window where a key is readable), never overwritten.
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:
        raise SecurityError(f"{path} already exists; use a new directory") from None
    except OSError as exc:
        raise SecurityError(f"cannot write {path}: {exc.strerror}") from None
    try:
        with open(fd, "wb") as out:
            out.write(data)
    except BaseException:
        path.unlink(missing_ok=True)
        raise


@dataclass(frozen=True)
class TlsFiles:
    """Paths Zenoh reads: the team CA, one member's certificate and key."""

    ca: Path
    cert: Path
    key: Path


def check_tls(team_dir: Path, name: str, ca_pin: str, cert_pin: str) -> TlsFiles:
    """``name``'s TLS files, checked now (so a robot stops at start-up with one
    line, not at its first TLS handshake): present, the key private, the
    certificates the ones ``team.json`` pins, the key the certificate's."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    files = TlsFiles(team_dir / CA_FILE, cert_file(team_dir, name), key_file(team_dir, name))
    for path, pin in ((files.ca, ca_pin), (files.cert, cert_pin)):
        try:
            pem = path.read_bytes()
        except OSError as exc:
            raise SecurityError(f"cannot read certificate {path}: {exc.strerror}") from None
        try:
            ok = fingerprint(pem) == pin
        except ValueError:
            raise SecurityError(f"{path}: not a PEM X.509 certificate") from None
        if not ok:
            raise SecurityError(f"{path}: not the certificate team.json names")
    try:
        mode = files.key.stat().st_mode
        if mode & 0o077:
            raise SecurityError(f"{files.key}: private key is readable by group or others (chmod 600 it)")
        if not stat.S_ISREG(mode):
            raise SecurityError(f"{files.key}: not a regular file")
        key = serialization.load_pem_private_key(files.key.read_bytes(), password=None)
    except OSError as exc:
        raise SecurityError(f"cannot read private key {files.key}: {exc.strerror}") from None
    except (ValueError, TypeError):
        raise SecurityError(f"{files.key}: not an unencrypted PEM private key") from None
    cert = x509.load_pem_x509_certificate(files.cert.read_bytes())
    if key.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo) != \
            cert.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo):
        raise SecurityError(f"{files.key}: the key does not match {files.cert}")
    return files
