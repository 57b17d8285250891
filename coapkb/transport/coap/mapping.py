"""Between coapkb's transport-neutral messages and aiocoap's: pure mappings."""

from __future__ import annotations

import hashlib

import aiocoap
from aiocoap.numbers.codes import Code

from ..base import Endpoint, TransportError
from ..messages import Method, Request, Response, Status

#: URI-Query parameter carrying a hash of the request body.  Our client adds
#: it to a request with a body whose answer may come in blocks (a FETCH, or
#: a POST asking for a representation by Accept: SPARQL text, a sync), so
#: that even a body-less follow-up block request names its query; a task
#: post or a write (PATCH, iPATCH: answered with a status and a line, or
#: its few bytes of CBOR) spares those 16 bytes.  The server never requires
#: it (standard clients do not send it).
BODY_HASH_PARAM = "qh"

METHOD_CODES = {m: getattr(Code, m.value) for m in Method}


def body_hash(payload: bytes) -> str:
    return hashlib.blake2s(payload, digest_size=6).hexdigest()


def status_to_code(status: Status) -> Code:
    return Code((status // 100) << 5 | status % 100)


def code_to_status(code: Code) -> Status:
    try:
        return Status(code.class_ * 100 + (int(code) & 0x1F))
    except ValueError:
        raise TransportError(f"unexpected CoAP response code {code.dotted}") from None


def request_from_message(path: str, msg: aiocoap.Message) -> Request:
    """The request a resource at ``path`` received (raises ValueError for an
    unknown method code)."""
    query: dict[str, str] = {}
    for item in msg.opt.uri_query:
        key, _, value = item.partition("=")
        if key != BODY_HASH_PARAM:  # transport-level; the service never sees it
            query[key] = value
    return Request(
        method=Method(str(msg.code)),
        path=path,
        query=query,
        payload=msg.payload,
        content_format=None if msg.opt.content_format is None else int(msg.opt.content_format),
        accept=None if msg.opt.accept is None else int(msg.opt.accept),
        etags=tuple(msg.opt.etags),
        if_match=tuple(m for m in msg.opt.if_match if isinstance(m, bytes)),
    )


def message_from_response(response: Response) -> aiocoap.Message:
    msg = aiocoap.Message(code=status_to_code(response.status), payload=response.payload)
    if response.content_format is not None:
        msg.opt.content_format = response.content_format
    if response.max_age is not None:
        msg.opt.max_age = response.max_age
    if response.etag is not None:
        msg.opt.etag = response.etag
    return msg


def message_from_request(peer: Endpoint, request: Request, *, observe: bool = False) -> aiocoap.Message:
    """The aiocoap message for ``request`` to ``peer`` (no transport tuning set)."""
    msg = aiocoap.Message(
        code=METHOD_CODES[request.method],
        uri=f"coap://{peer.hostport}{request.path}",
        payload=request.payload,
    )
    query = [f"{k}={v}" for k, v in request.query.items()]
    if request.payload and (request.method == Method.FETCH or (
            request.method == Method.POST and request.accept is not None)):
        query.append(f"{BODY_HASH_PARAM}={body_hash(request.payload)}")
    msg.opt.uri_query = tuple(query)
    if request.content_format is not None:
        msg.opt.content_format = request.content_format
    if request.accept is not None:
        msg.opt.accept = request.accept
    if request.etags:
        msg.opt.etags = request.etags
    if request.if_match:
        msg.opt.if_match = request.if_match
    if observe:
        msg.opt.observe = 0
    return msg


def response_from_message(msg: aiocoap.Message) -> Response:
    return Response(
        status=code_to_status(msg.code),
        payload=msg.payload,
        content_format=None if msg.opt.content_format is None else int(msg.opt.content_format),
        max_age=msg.opt.max_age,
        etag=msg.opt.etag,
    )
