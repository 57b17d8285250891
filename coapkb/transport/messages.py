"""Transport-neutral request and response messages.

The vocabulary is CoAP's (RFC 7252 methods, response codes and
content-formats) because CoAP is the primary transport; the ZeroMQ
transport carries the very same messages, so the agent never knows which
transport it talks through.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field


class Method(enum.StrEnum):
    GET = "GET"
    POST = "POST"
    PUT = "PUT"
    DELETE = "DELETE"
    FETCH = "FETCH"  # RFC 8132
    PATCH = "PATCH"  # RFC 8132
    IPATCH = "iPATCH"  # RFC 8132: a patch that may be applied twice


class Status(enum.IntEnum):
    """CoAP response codes, written as class*100+detail (2.05 -> 205)."""

    CREATED = 201
    DELETED = 202
    VALID = 203
    CHANGED = 204
    CONTENT = 205
    BAD_REQUEST = 400
    UNAUTHORIZED = 401
    BAD_OPTION = 402
    FORBIDDEN = 403
    NOT_FOUND = 404
    METHOD_NOT_ALLOWED = 405
    NOT_ACCEPTABLE = 406
    REQUEST_ENTITY_INCOMPLETE = 408
    CONFLICT = 409
    PRECONDITION_FAILED = 412
    REQUEST_ENTITY_TOO_LARGE = 413
    UNSUPPORTED_CONTENT_FORMAT = 415
    UNPROCESSABLE_ENTITY = 422  # RFC 8132: well-formed, but not applicable
    INTERNAL_SERVER_ERROR = 500
    NOT_IMPLEMENTED = 501
    BAD_GATEWAY = 502
    SERVICE_UNAVAILABLE = 503
    GATEWAY_TIMEOUT = 504

    @property
    def is_success(self) -> bool:
        return 200 <= self < 300

    @property
    def dotted(self) -> str:
        return f"{self // 100}.{self % 100:02d}"


class ContentFormat(enum.IntEnum):
    """IANA CoAP Content-Formats used here."""

    TEXT = 0  # text/plain;charset=utf-8: SPARQL query text, diagnostics
    LINK_FORMAT = 40  # RFC 6690
    JSON = 50  # application/json: SPARQL 1.1 Query Results JSON
    CBOR = 60  # application/cbor: compact results (docs/compact-results.cddl)


@dataclass(frozen=True)
class Request:
    method: Method
    path: str
    query: Mapping[str, str] = field(default_factory=dict)
    payload: bytes = b""
    content_format: int | None = None
    accept: int | None = None
    #: ETags of representations the client holds (RFC 7252 section 5.10.6):
    #: if one still matches, the answer is 2.03 Valid without a payload.
    etags: tuple[bytes, ...] = ()
    #: If-Match (RFC 7252 section 5.10.8.1): apply only if the resource is
    #: at one of these versions (empty: unconditional).
    if_match: tuple[bytes, ...] = ()
    #: The team member the request came from, as the server's security layer
    #: authenticated it (OSCORE/EDHOC, CurveZMQ, mTLS): a claim set below the
    #: request interface, never read from the wire.  None if unprotected.
    peer: str | None = None


@dataclass(frozen=True)
class Response:
    status: Status
    payload: bytes = b""
    content_format: int | None = None
    #: Freshness in seconds (CoAP Max-Age); None leaves the protocol default.
    max_age: int | None = None
    etag: bytes | None = None
    #: As an Observe notification: one the observer must not miss, because
    #: nothing it waits for follows it (a robot that went idle).  A transport
    #: that sends notifications unconfirmed sends this one confirmed.
    confirm: bool = False

    @classmethod
    def error(cls, status: Status, message: str, max_age: int | None = None) -> Response:
        """An error with a UTF-8 diagnostic payload (RFC 7252 section 5.5.2)."""
        return cls(status, message.encode("utf-8"), ContentFormat.TEXT, max_age=max_age)

    def text(self) -> str:
        return self.payload.decode("utf-8", errors="replace")
