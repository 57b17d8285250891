"""TLS material for a QUIC link without the team's keys (``zenoh+quic://``
with ``--insecure`` or no ``--credentials``).

Zenoh opens a ``quic/`` listener only with a certificate and key, and its
QUIC client always verifies the listener's certificate chain (against
``root_ca_certificate`` or else the WebPKI roots); Zenoh 1.10 has no switch
to skip that.  Without team keys a client knows nothing to verify against,
so every coapkb process builds the same *public* CA: its private key is
derived from the published label :data:`LABEL`, so anyone can build it and
sign with it.  A listener signs a fresh certificate for an ephemeral key of
its own with it; a client trusts that CA and checks no name.

This authenticates nobody, on purpose: it is how a client "does not verify"
with Zenoh's QUIC, and the protection is that of plain ``zenoh://``
(none against an active attacker).  QUIC's TLS 1.3 still encrypts each
connection with fresh keys, which keeps out a passive listener only.  With
team keys the secured transport (``coapkb.security.zenoh_tls``) replaces all
of this: mutual TLS, the team CA, per-member certificates.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import json

import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = ["LABEL", "configure_connector", "configure_listener", "public_ca_key"]

#: What the public CA's private key is derived from (SHA-256, reduced mod the P-256 order).
LABEL = b"coapkb anonymous QUIC CA, v1: a public key pair, it authenticates nobody"
_CA_NAME = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "coapkb anonymous QUIC CA (public key pair)")])
_LISTENER_NAME = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "coapkb anonymous QUIC listener")])
#: The order of P-256's group.
_P256_N = 0xFFFFFFFF00000000FFFFFFFFFFFFFFFFBCE6FAADA7179E84F3B9CAC2FC632551
#: Certificates are made per session, so a day is plenty; 5 minutes back for clock skew.
_VALIDITY = datetime.timedelta(days=1)
_SKEW = datetime.timedelta(minutes=5)
_TLS = "transport/link/tls/"


def public_ca_key() -> ec.EllipticCurvePrivateKey:
    """The public CA's key: the same in every process, known to everyone."""
    d = int.from_bytes(hashlib.sha256(LABEL).digest(), "big") % (_P256_N - 1) + 1
    return ec.derive_private_key(d, ec.SECP256R1())


def _ca_certificate(key: ec.EllipticCurvePrivateKey, now: datetime.datetime) -> x509.Certificate:
    # Each process builds its own copy; rustls trusts an anchor by its name and
    # public key, which every copy shares (serial and validity differ).
    return (
        x509.CertificateBuilder()
        .subject_name(_CA_NAME).issuer_name(_CA_NAME)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _SKEW).not_valid_after(now + _VALIDITY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )


def _listener_certificate(ca_key: ec.EllipticCurvePrivateKey, key: ec.EllipticCurvePrivateKey,
                          now: datetime.datetime) -> x509.Certificate:
    return (
        x509.CertificateBuilder()
        .subject_name(_LISTENER_NAME).issuer_name(_CA_NAME)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _SKEW).not_valid_after(now + _VALIDITY)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        # rustls' verifier wants a subjectAltName; clients check no name (see configure_connector).
        .add_extension(x509.SubjectAlternativeName([x509.DNSName("listener.coapkb.invalid")]), critical=False)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )


def _pem64(pem: bytes) -> str:
    """Zenoh's ``*_base64`` keys take the PEM text base64-encoded (no file on disk)."""
    return base64.b64encode(pem).decode("ascii")


def _insert(config: zenoh.Config, key: str, value: object) -> None:
    config.insert_json5(_TLS + key, json.dumps(value))


def configure_listener(config: zenoh.Config) -> None:
    """Give a listening session an ephemeral key and a certificate the public CA signed."""
    now = datetime.datetime.now(datetime.UTC)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = _listener_certificate(public_ca_key(), key, now)
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    _insert(config, "listen_private_key_base64", _pem64(key_pem))
    _insert(config, "listen_certificate_base64", _pem64(cert.public_bytes(serialization.Encoding.PEM)))


def configure_connector(config: zenoh.Config) -> None:
    """Make a connecting session accept any listener the public CA signed, whatever its name."""
    ca = _ca_certificate(public_ca_key(), datetime.datetime.now(datetime.UTC))
    _insert(config, "root_ca_certificate_base64", _pem64(ca.public_bytes(serialization.Encoding.PEM)))
    _insert(config, "verify_name_on_connect", False)
