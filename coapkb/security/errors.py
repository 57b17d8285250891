"""The security package's error: every module of it raises this (below keys
and TLS alike, so neither imports the other for it)."""

from __future__ import annotations

from ..errors import CoapkbError


class SecurityError(CoapkbError):
    """Key material missing, unreadable or malformed; a request not allowed."""
