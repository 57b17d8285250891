"""The CBOR envelope of the transports without CoAP's own framing (ZeroMQ, DDS): one CBOR array per message.

Pure functions, no I/O, so the envelope can be fuzzed and measured on its own.
Every request and response travels as exactly one ZeroMQ frame holding one
CBOR array of small integers and strings.  Field names are left out (arrays,
not maps) and CoAP's numeric codes are reused, because the messages cross slow
radio links and the CoAP transport carries the same information in a few
bytes of header; the ZeroMQ comparison should not lose on envelope size.

Layout (CDDL, RFC 8610)::

    request = [
        token:          uint .size 8,     ; chosen by the client, echoed back
        method:         1..5,             ; CoAP codes: GET=1 POST=2 PUT=3 DELETE=4 FETCH=5 (RFC 8132)
        path:           tstr,             ; "/sparql", "/.well-known/core", ...
        query:          { * tstr => tstr },
        content-format: uint / null,      ; IANA CoAP Content-Format of payload
        accept:         uint / null,
        payload:        bstr,
        ? observe:      0 / 1 / null,     ; RFC 7641 values: 0 register, 1 deregister
        ? etags:        [* bstr .size (1..8)],  ; RFC 7252 ETag options (validation)
        ? if-match:     [* bstr .size (0..8)],  ; RFC 7252 If-Match options (a conditional write)
    ]

    response = [
        token:          uint .size 8,     ; the request's token
        status:         uint,             ; CoAP code as class*100+detail: 205, 404, 500, ...
        content-format: uint / null,
        max-age:        uint / null,      ; seconds; null = protocol default
        etag:           bstr / null,
        payload:        bstr,
        ? seq:          uint,             ; present iff this is (the start of) an observation:
                                          ; 0 for the registration's answer, then 1, 2, ...
    ]

A request without ``observe`` is a plain request.  A response without ``seq``
to an observe request means the server did not register the observation
(like a CoAP response without the Observe option).  The empty query and the
nulls cost one byte each, which keeps decoding a fixed-shape check.

Decoding untrusted bytes raises :class:`WireError` (a ``ValueError``) and
nothing else, so the server can count and drop garbage with one ``except``.
"""

from __future__ import annotations

import enum
import io
from typing import Any

import cbor2

from ..errors import CoapkbError
from .messages import Method, Request, Response, Status

__all__ = [
    "WireError",
    "Observe",
    "MAX_TOKEN",
    "encode_request",
    "decode_request",
    "encode_response",
    "decode_response",
]

#: Tokens and sequence numbers are CBOR uints of at most 8 bytes.
MAX_TOKEN = 2**64 - 1

_METHOD_CODES: dict[Method, int] = {
    Method.GET: 1,
    Method.POST: 2,
    Method.PUT: 3,
    Method.DELETE: 4,
    Method.FETCH: 5,
    Method.PATCH: 6,
    Method.IPATCH: 7,
}
_METHODS_BY_CODE: dict[int, Method] = {code: m for m, code in _METHOD_CODES.items()}

_REQUEST_FIELDS = 7  # without the optional observe element
_RESPONSE_FIELDS = 6  # without the optional seq element


class WireError(CoapkbError, ValueError):
    """Bytes that are not a well-formed request or response envelope."""


class Observe(enum.IntEnum):
    """What a request asks about observation.

    ``NONE`` is falsy and ``REGISTER`` equals ``True``, so code that only cares
    "is this an observe request" may treat the value as a bool; deregistration
    is the extra case.  The wire values are RFC 7641's, not these.
    """

    NONE = 0
    REGISTER = 1
    DEREGISTER = 2


_OBSERVE_TO_WIRE = {Observe.REGISTER: 0, Observe.DEREGISTER: 1}
_OBSERVE_FROM_WIRE = {wire: obs for obs, wire in _OBSERVE_TO_WIRE.items()}


# --------------------------------------------------------------------------- encoding


def _check_uint(name: str, value: int, maximum: int = MAX_TOKEN) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= maximum:
        raise ValueError(f"{name} must be an int in 0..{maximum}, got {value!r}")
    return value


def _opt_uint(name: str, value: int | None) -> int | None:
    return None if value is None else _check_uint(name, int(value))


def encode_request(req: Request, *, observe: bool | Observe = False, token: int) -> bytes:
    """Encode ``req`` with ``token``.

    ``observe`` is ``True``/``Observe.REGISTER`` to register an observation,
    ``Observe.DEREGISTER`` to cancel the observation registered under ``token``.
    Raises ``ValueError`` for values the envelope cannot carry.
    """
    _check_uint("token", token)
    try:
        method = _METHOD_CODES[Method(req.method)]
    except (KeyError, ValueError):
        raise ValueError(f"unsupported method {req.method!r}") from None
    query = dict(req.query)
    for k, v in query.items():
        if not isinstance(k, str) or not isinstance(v, str):
            raise ValueError(f"query must map str to str, got {k!r}: {v!r}")
    fields: list[Any] = [
        token,
        method,
        str(req.path),
        query,
        _opt_uint("content_format", req.content_format),
        _opt_uint("accept", req.accept),
        bytes(req.payload),
    ]
    obs = Observe(int(observe))
    etags = [bytes(e) for e in req.etags]
    if_match = [bytes(m) for m in req.if_match]
    if obs is not Observe.NONE or etags or if_match:
        fields.append(_OBSERVE_TO_WIRE[obs] if obs is not Observe.NONE else None)
    if etags or if_match:
        fields.append(etags)
    if if_match:
        fields.append(if_match)
    return cbor2.dumps(fields)


def encode_response(token: int, resp: Response, *, seq: int | None = None) -> bytes:
    """Encode ``resp`` as the answer to ``token``; ``seq`` marks an observation."""
    _check_uint("token", token)
    status = _check_uint("status", int(resp.status), 999)
    if resp.etag is not None and not isinstance(resp.etag, (bytes, bytearray)):
        raise ValueError(f"etag must be bytes or None, got {resp.etag!r}")
    fields: list[Any] = [
        token,
        status,
        _opt_uint("content_format", resp.content_format),
        _opt_uint("max_age", resp.max_age),
        None if resp.etag is None else bytes(resp.etag),
        bytes(resp.payload),
    ]
    if seq is not None:
        fields.append(_check_uint("seq", seq))
    return cbor2.dumps(fields)


# --------------------------------------------------------------------------- decoding


def _load_array(data: bytes | bytearray | memoryview, what: str, sizes: tuple[int, ...]) -> list[Any]:
    """One CBOR array spanning all of ``data``, of one of the lengths ``sizes``."""
    buf = bytes(data)
    fp = io.BytesIO(buf)
    try:
        item = cbor2.CBORDecoder(fp).decode()
    # cbor2 raises CBORDecodeError for most garbage but its semantic-tag
    # handlers (dates, decimals, sets, ...) can raise almost anything; the
    # contract of this module is "WireError and nothing else".
    except Exception as exc:
        raise WireError(f"{what}: not CBOR ({exc})") from exc
    if fp.tell() != len(buf):
        raise WireError(f"{what}: {len(buf) - fp.tell()} trailing bytes after the CBOR item")
    if not isinstance(item, list):
        raise WireError(f"{what}: expected a CBOR array, got {type(item).__name__}")
    if len(item) not in sizes:
        raise WireError(f"{what}: expected an array of {sizes[0]} or {sizes[1]} elements, got {len(item)}")
    return item


def _uint(what: str, name: str, value: Any, maximum: int = MAX_TOKEN) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= maximum:
        raise WireError(f"{what}: {name} must be a uint, got {value!r}"[:200])
    return value


def _opt(what: str, name: str, value: Any) -> int | None:
    return None if value is None else _uint(what, name, value)


def _bstr(what: str, name: str, value: Any) -> bytes:
    if not isinstance(value, bytes):
        raise WireError(f"{what}: {name} must be a byte string, got {type(value).__name__}")
    return value


def decode_request(data: bytes | bytearray | memoryview) -> tuple[int, Request, Observe]:
    """Decode a request envelope into ``(token, request, observe)``.

    Raises :class:`WireError` for anything that is not a valid envelope.
    """
    what = "request"
    f = _load_array(data, what, (_REQUEST_FIELDS, _REQUEST_FIELDS + 1, _REQUEST_FIELDS + 2, _REQUEST_FIELDS + 3))
    token = _uint(what, "token", f[0])
    if isinstance(f[1], bool) or not isinstance(f[1], int) or f[1] not in _METHODS_BY_CODE:
        raise WireError(f"{what}: unknown method code {f[1]!r}"[:200])
    if not isinstance(f[2], str):
        raise WireError(f"{what}: path must be a text string, got {type(f[2]).__name__}")
    if not isinstance(f[3], dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in f[3].items()):
        raise WireError(f"{what}: query must be a map of text strings")
    observe = Observe.NONE
    if len(f) > _REQUEST_FIELDS and not (f[_REQUEST_FIELDS] is None and len(f) > _REQUEST_FIELDS + 1):
        wire = f[_REQUEST_FIELDS]
        if isinstance(wire, bool) or not isinstance(wire, int) or wire not in _OBSERVE_FROM_WIRE:
            raise WireError(f"{what}: observe must be 0 or 1, got {wire!r}"[:200])
        observe = _OBSERVE_FROM_WIRE[wire]
    etags: tuple[bytes, ...] = ()
    if len(f) > _REQUEST_FIELDS + 1:
        raw = f[_REQUEST_FIELDS + 1]
        if not isinstance(raw, list) or not all(isinstance(e, bytes) and len(e) <= 8 for e in raw):
            raise WireError(f"{what}: etags must be an array of byte strings of at most 8 bytes")
        etags = tuple(raw)
    if_match: tuple[bytes, ...] = ()
    if len(f) > _REQUEST_FIELDS + 2:
        raw = f[_REQUEST_FIELDS + 2]
        if not isinstance(raw, list) or not all(isinstance(m, bytes) and len(m) <= 8 for m in raw):
            raise WireError(f"{what}: if-match must be an array of byte strings of at most 8 bytes")
        if_match = tuple(raw)
    request = Request(
        method=_METHODS_BY_CODE[f[1]],
        path=f[2],
        query=f[3],
        content_format=_opt(what, "content-format", f[4]),
        accept=_opt(what, "accept", f[5]),
        payload=_bstr(what, "payload", f[6]),
        etags=etags,
        if_match=if_match,
    )
    return token, request, observe


def decode_response(data: bytes | bytearray | memoryview) -> tuple[int, Response, int | None]:
    """Decode a response envelope into ``(token, response, seq)``; ``seq`` is
    ``None`` outside observations.  Raises :class:`WireError` on bad input."""
    what = "response"
    f = _load_array(data, what, (_RESPONSE_FIELDS, _RESPONSE_FIELDS + 1))
    token = _uint(what, "token", f[0])
    code = _uint(what, "status", f[1], 999)
    try:
        status = Status(code)
    except ValueError:
        raise WireError(f"{what}: unknown status code {code}") from None
    etag = None if f[4] is None else _bstr(what, "etag", f[4])
    seq = _uint(what, "seq", f[_RESPONSE_FIELDS]) if len(f) > _RESPONSE_FIELDS else None
    response = Response(
        status=status,
        payload=_bstr(what, "payload", f[5]),
        content_format=_opt(what, "content-format", f[2]),
        max_age=_opt(what, "max-age", f[3]),
        etag=etag,
    )
    return token, response, seq
