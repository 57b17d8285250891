"""Ask a robot's knowledge base: SPARQL text or a named query, decoded results."""

from __future__ import annotations

from typing import Mapping

from . import codec
from .messages import ContentFormat, Method, Request, Response
from .results import QueryResult
from .transport.base import ClientTransport, Endpoint, TransportError


class QueryFailed(Exception):
    """The robot answered with an error (4.xx/5.xx); ``str()`` is its diagnostic."""

    def __init__(self, response: Response) -> None:
        self.response = response
        super().__init__(f"{response.status.dotted} {response.status.name}: {response.text()}")


class KBClient:
    """Queries over any :class:`ClientTransport`."""

    def __init__(self, transport: ClientTransport, *, timeout: float = 30.0) -> None:
        self.transport = transport
        self.timeout = timeout

    async def sparql(
        self,
        peer: Endpoint,
        query: str,
        *,
        accept: ContentFormat = ContentFormat.CBOR,
        method: Method = Method.FETCH,
        timeout: float | None = None,
    ) -> QueryResult:
        """Run SPARQL text on ``peer`` (FETCH by default, RFC 8132)."""
        if method == Method.GET:
            request = Request(Method.GET, "/kb/sparql", {"q": query}, accept=accept)
        else:
            request = Request(method, "/kb/sparql", payload=query.encode("utf-8"),
                              content_format=ContentFormat.TEXT, accept=accept)
        return decode(await self.call(peer, request, timeout))

    async def named(
        self,
        peer: Endpoint,
        name: str,
        params: Mapping[str, str] | None = None,
        *,
        accept: ContentFormat = ContentFormat.CBOR,
        timeout: float | None = None,
    ) -> QueryResult:
        """Run the named query ``/kb/q/<name>?params`` on ``peer``: a few bytes on the wire."""
        request = Request(Method.GET, f"/kb/q/{name}", dict(params or {}), accept=accept)
        return decode(await self.call(peer, request, timeout))

    async def call(self, peer: Endpoint, request: Request, timeout: float | None = None) -> Response:
        response = await self.transport.request(peer, request, timeout=timeout or self.timeout)
        if not response.status.is_success:
            raise QueryFailed(response)
        return response


def decode(response: Response) -> QueryResult:
    """Decode a successful query response by its content-format."""
    if response.content_format == ContentFormat.CBOR:
        return codec.decode_cbor(response.payload)
    if response.content_format == ContentFormat.JSON:
        return codec.decode_json(response.payload)
    raise TransportError(f"unexpected content-format {response.content_format} in a query answer")
