"""coapkb messages to and from Zenoh queries, replies and samples: pure, no I/O.

A :class:`~coapkb.transport.messages.Request` becomes one Zenoh query:

* **key expression**: ``coapkb`` + the path, each path segment percent-encoded
  so Zenoh's wildcard and selector characters (``* $ # ?``) cannot appear
  (``/kb/q/object-exists`` -> ``coapkb/kb/q/object-exists``, ``/`` -> ``coapkb``);
* **selector parameters**: the URI query, ``k=v`` joined by ``;`` with keys
  and values percent-encoded (Zenoh does not escape ``;``/``=`` itself);
* **payload** and **encoding**: the body and its CoAP Content-Format
  (:func:`encoding_for`);
* **attachment**: a CBOR array ``[method, accept, etags, observe, notify-key]``
  (CoAP method codes, trailing defaults left out; a plain GET has none).

A :class:`~coapkb.transport.messages.Response` becomes one reply on the
query's key: its payload and encoding, and an attachment
``[status, max-age, etag, seq]`` (trailing defaults left out; none at all for
a bare 2.05).  An observation's notifications are samples with the same
attachment, ``seq`` numbering them from 0 (the registration's reply).

Decoding untrusted input raises :class:`MappingError` (a ``ValueError``) and
nothing else, so the server can count and drop garbage with one ``except``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any
from urllib.parse import quote, unquote

import cbor2

from ...errors import CoapkbError
from ..base import Endpoint
from ..messages import Method, Request, Response, Status

__all__ = [
    "KEY_ROOT",
    "NOTIFY_ROOT",
    "LINK_PROTOCOLS",
    "Link",
    "MappingError",
    "Observe",
    "RequestHeader",
    "ResponseHeader",
    "content_format_of",
    "decode_request_header",
    "decode_response_header",
    "encode_request_header",
    "encode_response_header",
    "encoding_for",
    "key_for_path",
    "link_for",
    "locator",
    "parameters_text",
    "path_for_key",
    "query_from_parameters",
    "request_from_query",
    "response_from_reply",
]

#: Every robot resource lives under this key; a server's one queryable is ``coapkb/**``.
KEY_ROOT = "coapkb"
#: Observation notifications go to ``coapkb-obs/<client session id>/<n>``, a key
#: outside the queryable's, chosen by the observing client.
NOTIFY_ROOT = "coapkb-obs"


@dataclass(frozen=True)
class Link:
    """The Zenoh link an endpoint scheme stands for."""

    #: Zenoh's link protocol, the locator's prefix.
    protocol: str
    #: The locator's metadata (after ``?``), e.g. ``rel=1``.
    metadata: str = ""
    #: Listens on a UDP socket (else TCP).
    datagram: bool = False
    #: Zenoh opens it only with TLS material (a certificate and key), secured or not.
    needs_tls: bool = False


#: Endpoint scheme -> Zenoh link: the one place that says which locator a
#: scheme means (docs/zenoh.md).  ``udp/h:p?rel=1`` is Zenoh's *reliable* UDP,
#: QUIC streams without TLS (``?rel=1`` is locator metadata; ``#rel=1`` would be
#: link configuration, silently ignored, and give the plain UDP link, which
#: retransmits nothing); ``quic/h:p`` is QUIC with TLS 1.3.
LINK_PROTOCOLS: dict[str, Link] = {
    "zenoh": Link("tcp"),
    "zenoh+udp": Link("udp", "rel=1", datagram=True),
    "zenoh+quic": Link("quic", datagram=True, needs_tls=True),
}

_METHOD_CODES = {
    Method.GET: 1, Method.POST: 2, Method.PUT: 3, Method.DELETE: 4, Method.FETCH: 5, Method.PATCH: 6, Method.IPATCH: 7,
}
_METHODS_BY_CODE = {code: m for m, code in _METHOD_CODES.items()}
#: Characters left as they are in key chunks and parameters (RFC 3986
#: unreserved plus a few harmless ones); everything else is %-encoded.
_SAFE = "-._~!'()+,:@"
#: CoAP Content-Formats with a Zenoh encoding of their own (sent as a 1-2 byte id).
_ENCODINGS = {0: "text/plain", 50: "application/json", 60: "application/cbor"}
_FORMATS = {name: cf for cf, name in _ENCODINGS.items()}
_OTHER_FORMAT = "zenoh/bytes;ct="


class MappingError(CoapkbError, ValueError):
    """Bytes or names from the network that are not a coapkb message."""


class Observe(enum.IntEnum):
    """RFC 7641's values: what an observe request asks for."""

    REGISTER = 0
    DEREGISTER = 1


def link_for(endpoint: Endpoint) -> Link:
    """The Zenoh link of ``endpoint``'s scheme (``ValueError`` for a scheme that is not Zenoh's)."""
    try:
        return LINK_PROTOCOLS[endpoint.scheme]
    except KeyError:
        raise ValueError(f"{endpoint} is not a zenoh endpoint ({', '.join(LINK_PROTOCOLS)})") from None


def locator(endpoint: Endpoint) -> str:
    """Zenoh's locator for ``endpoint``: ``zenoh://h:p`` -> ``tcp/h:p``,
    ``zenoh+udp://h:p`` -> ``udp/h:p?rel=1``, ``zenoh+quic://h:p`` -> ``quic/h:p``."""
    link = link_for(endpoint)
    return f"{link.protocol}/{endpoint.hostport}" + (f"?{link.metadata}" if link.metadata else "")


# --------------------------------------------------------------------------- key and parameters


def key_for_path(path: str) -> str:
    """The key expression of a resource path (``ValueError`` for empty segments)."""
    if path in ("", "/"):
        return KEY_ROOT
    segments = path.removeprefix("/").split("/")
    if any(not s for s in segments):
        raise ValueError(f"path {path!r} has an empty segment, which no key expression can carry")
    return "/".join([KEY_ROOT, *(quote(s, safe=_SAFE) for s in segments)])


def path_for_key(key: str) -> str:
    """The inverse of :func:`key_for_path`."""
    if key == KEY_ROOT:
        return "/"
    if not key.startswith(KEY_ROOT + "/"):
        raise MappingError(f"key {key[:80]!r} is not under {KEY_ROOT}/")
    try:
        return "/" + "/".join(unquote(s, errors="strict") for s in key[len(KEY_ROOT) + 1 :].split("/"))
    except UnicodeDecodeError as exc:
        raise MappingError(f"key {key[:80]!r} is not UTF-8 once decoded") from exc


def parameters_text(query: dict[str, str] | Any) -> str:
    """The selector parameters of a URI query (``""`` when it is empty)."""
    return ";".join(f"{quote(k, safe=_SAFE)}={quote(v, safe=_SAFE)}" for k, v in query.items())


def query_from_parameters(text: str) -> dict[str, str]:
    """The inverse of :func:`parameters_text`; a key without ``=`` has value ``""``."""
    query: dict[str, str] = {}
    for item in text.split(";"):
        if not item:
            continue
        key, _, value = item.partition("=")
        try:
            query[unquote(key, errors="strict")] = unquote(value, errors="strict")
        except UnicodeDecodeError as exc:
            raise MappingError(f"parameter {item[:80]!r} is not UTF-8 once decoded") from exc
    return query


# --------------------------------------------------------------------------- content formats


def encoding_for(content_format: int | None) -> str | None:
    """The Zenoh encoding of a CoAP Content-Format (None: no encoding sent)."""
    if content_format is None:
        return None
    return _ENCODINGS.get(content_format, f"{_OTHER_FORMAT}{content_format}")


def content_format_of(encoding: str | None) -> int | None:
    """The inverse of :func:`encoding_for`; Zenoh's default ``zenoh/bytes`` is None."""
    if encoding is None or encoding == "zenoh/bytes":
        return None
    if encoding in _FORMATS:
        return _FORMATS[encoding]
    digits = encoding[len(_OTHER_FORMAT) :]
    # ASCII only: str.isdigit() is true for "²", which int() refuses (a ValueError, not ours)
    if encoding.startswith(_OTHER_FORMAT) and digits.isascii() and digits.isdigit():
        value = int(digits)
        if value < 65536:
            return value
    raise MappingError(f"encoding {encoding[:80]!r} is no CoAP Content-Format")


# --------------------------------------------------------------------------- attachments


@dataclass(frozen=True)
class RequestHeader:
    """What a request carries besides key, parameters, payload and encoding."""

    method: Method = Method.GET
    accept: int | None = None
    etags: tuple[bytes, ...] = ()
    observe: Observe | None = None
    #: Where the server publishes an observation's notifications (observe requests only).
    notify_key: str | None = None
    #: If-Match (RFC 7252 section 5.10.8.1): a conditional write.
    if_match: tuple[bytes, ...] = ()


@dataclass(frozen=True)
class ResponseHeader:
    status: Status = Status.CONTENT
    max_age: int | None = None
    etag: bytes | None = None
    #: An observation's sequence number (None: not part of one).
    seq: int | None = None


def _trimmed(items: list[Any], defaults: list[Any]) -> bytes | None:
    """CBOR of ``items`` without trailing defaults; None if nothing is left."""
    while items and items[-1] == defaults[len(items) - 1]:
        items.pop()
    return cbor2.dumps(items) if items else None


def encode_request_header(header: RequestHeader) -> bytes | None:
    """The attachment of a request; None (no attachment) for a plain GET."""
    items = [
        _METHOD_CODES[header.method],
        header.accept,
        list(header.etags),
        None if header.observe is None else int(header.observe),
        header.notify_key,
        list(header.if_match),
    ]
    return _trimmed(items, [1, None, [], None, None, []])


def _array(data: bytes | None, max_len: int, what: str) -> list[Any]:
    if data is None:
        return []
    try:
        items = cbor2.loads(data)
    except Exception as exc:  # noqa: BLE001 - cbor2 raises several types on garbage
        raise MappingError(f"{what} attachment is not CBOR: {exc}") from None
    if not isinstance(items, list) or len(items) > max_len:
        raise MappingError(f"{what} attachment is not an array of at most {max_len} items")
    return items


def _optional_uint(value: Any, limit: int, what: str) -> int | None:
    if value is None:
        return None
    if type(value) is not int or not 0 <= value < limit:
        raise MappingError(f"{what} must be an unsigned integer below {limit}, got {value!r}")
    return value


def decode_request_header(data: bytes | None) -> RequestHeader:
    items = _array(data, 6, "request")
    items += [1, None, [], None, None, []][len(items) :]
    method_code, accept, etags, observe, notify_key, if_match = items
    if type(method_code) is not int or method_code not in _METHODS_BY_CODE:
        raise MappingError(f"unknown method code {method_code!r}")
    if not isinstance(etags, list) or not all(isinstance(e, bytes) and 1 <= len(e) <= 8 for e in etags):
        raise MappingError("etags must be an array of 1-8 byte strings")
    if not isinstance(if_match, list) or not all(isinstance(m, bytes) and len(m) <= 8 for m in if_match):
        raise MappingError("if-match must be an array of 0-8 byte strings")
    if observe is not None and observe not in (0, 1):
        raise MappingError(f"observe must be 0 or 1, got {observe!r}")
    if observe is not None and not (isinstance(notify_key, str) and notify_key.startswith(NOTIFY_ROOT + "/")):
        raise MappingError(f"an observe request needs a notification key under {NOTIFY_ROOT}/")
    return RequestHeader(
        _METHODS_BY_CODE[method_code],
        _optional_uint(accept, 65536, "accept"),
        tuple(etags),
        None if observe is None else Observe(observe),
        notify_key if observe is not None else None,
        tuple(if_match),
    )


def encode_response_header(header: ResponseHeader) -> bytes | None:
    """The attachment of a reply or notification; None for a bare 2.05."""
    items = [int(header.status), header.max_age, header.etag, header.seq]
    return _trimmed(items, [int(Status.CONTENT), None, None, None])


def decode_response_header(data: bytes | None) -> ResponseHeader:
    items = _array(data, 4, "response")
    items += [int(Status.CONTENT), None, None, None][len(items) :]
    status, max_age, etag, seq = items
    if type(status) is not int or status not in Status._value2member_map_:
        raise MappingError(f"unknown status {status!r}")
    status = Status(status)
    if etag is not None and not (isinstance(etag, bytes) and 1 <= len(etag) <= 8):
        raise MappingError("etag must be a 1-8 byte string")
    return ResponseHeader(
        status, _optional_uint(max_age, 2**32, "max-age"), etag, _optional_uint(seq, 2**64, "seq")
    )


# --------------------------------------------------------------------------- whole messages


def request_from_query(
    key: str, parameters: str, payload: bytes, encoding: str | None, attachment: bytes | None
) -> tuple[Request, RequestHeader]:
    """The request a Zenoh query carries, and its header (for the observe fields)."""
    header = decode_request_header(attachment)
    request = Request(
        header.method,
        path_for_key(key),
        query_from_parameters(parameters),
        payload,
        content_format_of(encoding),
        header.accept,
        header.etags,
        header.if_match,
    )
    return request, header


def response_from_reply(payload: bytes, encoding: str | None, attachment: bytes | None) -> tuple[Response, int | None]:
    """The response a reply or notification carries, and its ``seq``."""
    header = decode_response_header(attachment)
    response = Response(header.status, payload, content_format_of(encoding), header.max_age, header.etag)
    return response, header.seq
