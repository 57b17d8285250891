"""Finding the Resource Directory itself by multicast (RFC 9176 section 4.1:
``GET /.well-known/core?rt=core.rd*`` to All-CoAP-Nodes, RFC 7252 section 12.8).

Where multicast works (on loopback and in our emulated testbed: checked,
docs/discovery.md) a robot needs no address at all; where it does not (many
radio meshes and infrastructure links) the directory's address is
configured, and the team table is the last fallback.

The answer is not protected (multicast has no pairwise OSCORE context, and
``/.well-known/core`` is open anyway): it only says where to look.  The
robot then talks to that address under OSCORE and expects the directory's
credential there (``rd_identity``), so a forged answer can make discovery
fail, not make a robot trust an impostor.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import secrets
import socket
import struct
from typing import Any

import aiocoap
from aiocoap.util.linkformat import Link, LinkFormat, parse

from ..transport.base import Endpoint
from ..transport.registry import parse_endpoint

log = logging.getLogger(__name__)

#: All-CoAP-Nodes (RFC 7252 section 12.8), IPv4; the CoAP port.
ALL_COAP_NODES = "224.0.1.187"
COAP_PORT = 5683
RD_RT = "core.rd"


def _socket(interface: str, port: int) -> socket.socket:
    """A UDP socket on ``port`` of every address, in the group on ``interface``'s address."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)  # more than one listener per host
    sock.bind(("", port))
    membership = struct.pack("4s4s", socket.inet_aton(ALL_COAP_NODES), socket.inet_aton(interface))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
    sock.setblocking(False)
    return sock


class _Responder(asyncio.DatagramProtocol):
    def __init__(self, rd: Endpoint) -> None:
        self._links = str(LinkFormat([Link(f"coap://{rd.hostport}/rd", [("rt", RD_RT)])])).encode()
        self.transport: Any = None

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            request = aiocoap.Message.decode(data)
        except Exception:  # noqa: BLE001 - not CoAP: nothing to answer (RFC 7252 section 4.2)
            return
        wanted = [q.partition("=")[2] for q in request.opt.uri_query if q.startswith("rt=")]
        asks_rd = all(RD_RT.startswith(rt.rstrip("*")) if rt.endswith("*") else rt == RD_RT for rt in wanted)
        if request.code != aiocoap.GET or request.opt.uri_path != (".well-known", "core") or not asks_rd:
            return  # a multicast request that does not match gets no answer (RFC 7252 section 8.2)
        answer = aiocoap.Message(code=aiocoap.CONTENT, payload=self._links, content_format=40)
        answer.mtype, answer.mid, answer.token = aiocoap.NON, request.mid, request.token
        self.transport.sendto(answer.encode(), addr)


class MulticastAnnouncer:
    """Answers multicast discovery of the directory at ``rd`` on the
    interface with address ``interface`` (``port``: 5683, or another for
    tests sharing a host)."""

    def __init__(self, transport: Any) -> None:
        self._transport = transport

    @classmethod
    async def start(cls, rd: Endpoint, interface: str, port: int = COAP_PORT) -> MulticastAnnouncer:
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(lambda: _Responder(rd), sock=_socket(interface, port))
        return cls(transport)

    def close(self) -> None:
        self._transport.close()


class _Asker(asyncio.DatagramProtocol):
    def __init__(self, token: bytes) -> None:
        self.token = token
        self.found: asyncio.Future[Endpoint] = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            answer = aiocoap.Message.decode(data)
            links = parse(answer.payload.decode("utf-8")).links if answer.token == self.token else []
        except Exception:  # noqa: BLE001 - not an answer to us
            return
        for link in links:
            if RD_RT in str(dict(link.attr_pairs).get("rt", "")).split():
                try:
                    # A relative reference is the answering node's own (RFC 6690).
                    target = link.href if "://" in link.href else f"coap://{addr[0]}:{addr[1]}{link.href}"
                    endpoint = parse_endpoint(target)
                except ValueError:
                    continue
                if not self.found.done():
                    self.found.set_result(endpoint)
                return


async def find_directory(interface: str, *, port: int = COAP_PORT, timeout: float = 3.0) -> Endpoint | None:
    """The directory's endpoint from the first multicast answer on the
    interface with address ``interface``, or None within ``timeout``."""
    try:
        if ipaddress.ip_address(interface).version != 4:
            return None  # (ff02::fd would need a scope; the team's addresses are IPv4)
    except ValueError:
        return None  # a host name: no interface to send on
    request = aiocoap.Message(code=aiocoap.GET, uri_path=(".well-known", "core"), uri_query=(f"rt={RD_RT}*",))
    request.mtype, request.mid, request.token = aiocoap.NON, secrets.randbelow(1 << 16), secrets.token_bytes(4)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(interface))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)  # this link only
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)  # the directory may run on this host
    sock.bind((interface, 0))
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    transport, asker = await loop.create_datagram_endpoint(lambda: _Asker(request.token), sock=sock)
    try:
        async with asyncio.timeout(timeout):
            # NON: a lost request is sent again by the asker (three tries).
            for _ in range(3):
                transport.sendto(request.encode(), (ALL_COAP_NODES, port))
                done, _ = await asyncio.wait([asker.found], timeout=timeout / 3)
                if done:
                    return asker.found.result()
    except (TimeoutError, OSError) as exc:
        log.info("no directory answered on %s:%d from %s: %s", ALL_COAP_NODES, port, interface, exc or "timeout")
    finally:
        transport.close()
    return None
