"""Holders linked in memory: a sync request reaches the replicator it is
addressed to at once, sent as the robot that asks (``Request.peer``)."""

from __future__ import annotations

import asyncio
from dataclasses import replace

from coapkb.kb.replication import Replicator
from coapkb.transport.base import ClientTransport, Endpoint, PeerUnreachable
from coapkb.transport.messages import Request, Response


class Links(ClientTransport):
    """In memory: a push reaches the replicator at the endpoint's host, sent
    by ``me``; a robot in ``down`` is unreachable at once, one in ``silent``
    never answers."""

    def __init__(self, me: str, robots: dict[str, Replicator], down: set[str], silent: set[str]) -> None:
        self.me, self.robots, self.down, self.silent = me, robots, down, silent

    async def request(self, peer: Endpoint, request: Request, *, timeout: float) -> Response:
        if peer.host in self.down:
            raise PeerUnreachable(f"{peer.host} is down")
        if peer.host in self.silent:
            await asyncio.Event().wait()  # never answers: the caller's own timeout ends the wait
        return await self.robots[peer.host].handle_sync(replace(request, peer=self.me))

    def observe(self, peer: Endpoint, request: Request):  # type: ignore[no-untyped-def]
        raise NotImplementedError

    async def aclose(self) -> None:
        pass


def at(name: str) -> Endpoint:
    return Endpoint("coap", name, 5683)
