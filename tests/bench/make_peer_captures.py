"""Makes the small loopback captures of tests/bench/data/peers/: one client
and one server of each peer transport on 127.0.0.1, a few requests, an
observation and a large answer, captured on ``lo`` with dumpcap (Wireshark's
capture tool; root or the wireshark group).  Run again only to replace them:

    .venv/bin/python tests/bench/make_peer_captures.py tests/bench/data/peers
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from coapkb.security import AccessPolicy, generate_team, load_identity
from coapkb.security.keys import default_members
from coapkb.security.mechanisms import client_security, server_security
from coapkb.transport import Endpoint, open_client, serve
from coapkb.transport.base import ResourceInfo, Service
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status

#: Capture name -> (scheme, secured with the team's keys).
CAPTURES = {"zenoh-udp": ("zenoh+udp", False), "zenoh-quic": ("zenoh+quic", True),
            "zenoh-tls": ("zenoh", True), "dds": ("dds", False)}


class Counter(Service):
    """``/counter`` (observable) and ``/big`` (a 3 kB answer)."""

    def __init__(self) -> None:
        self.value = 0
        self.subscribers: list[Callable[[], None]] = []

    def resources(self) -> list[ResourceInfo]:
        return [ResourceInfo("/counter", obs=True), ResourceInfo("/big")]

    async def handle(self, request: Request) -> Response:
        if request.path == "/big":
            return Response(Status.CONTENT, bytes(range(256)) * 12, ContentFormat.CBOR)
        return Response(Status.CONTENT, str(self.value).encode(), ContentFormat.TEXT)

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        self.subscribers.append(on_change)
        return lambda: self.subscribers.remove(on_change)

    def bump(self) -> None:
        self.value += 1
        for f in list(self.subscribers):
            f()


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def exchange(scheme: str, port: int, team: Path | None) -> None:
    service = Counter()
    ssec = csec = None
    if team is not None:
        ssec = server_security(scheme, load_identity(team, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
        csec = client_security(scheme, load_identity(team, "Robot2"))
    server = await serve(service, Endpoint(scheme, "127.0.0.1", port), security=ssec)
    client = await open_client(scheme, security=csec)
    try:
        for _ in range(3):
            await client.request(server.endpoint, Request(Method.GET, "/counter"), timeout=10)
        await client.request(server.endpoint, Request(Method.GET, "/big"), timeout=10)
        async with contextlib.aclosing(client.observe(server.endpoint, Request(Method.GET, "/counter"),
                                                      timeout=10)) as updates:
            n = 0
            async for _ in updates:
                n += 1
                if n == 3:
                    break
                service.bump()
        await asyncio.sleep(0.5)
    finally:
        await client.aclose()
        await server.aclose()
    await asyncio.sleep(0.5)


def capture(name: str, out: Path, team: Path) -> None:
    scheme, secured = CAPTURES[name]
    port = free_port(socket.SOCK_STREAM if scheme == "zenoh" else socket.SOCK_DGRAM)
    path = out / f"{name}.pcap"
    # Cyclone sends from sockets of its own (not the port it listens on): DDS's by the RTPS magic.
    bpf = "udp[8:4] = 0x52545053" if scheme == "dds" else f"port {port}"
    dumpcap = subprocess.Popen(["dumpcap", "-q", "-i", "lo", "-F", "pcap", "-f", bpf, "-w", str(path)],
                               stderr=subprocess.PIPE, text=True)
    assert dumpcap.stderr is not None
    while "Capturing on" not in dumpcap.stderr.readline():
        if dumpcap.poll() is not None:
            raise SystemExit(f"dumpcap exited: {dumpcap.stderr.read()}")
    time.sleep(1.0)  # it says so a little before its filter is in place
    try:
        asyncio.run(exchange(scheme, port, team if secured else None))
    finally:
        dumpcap.send_signal(2)
        dumpcap.wait(10)
    print(f"{path}: {path.stat().st_size} bytes")


def main(argv: list[str]) -> None:
    out = Path(argv[0] if argv else "tests/bench/data/peers")
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        team = Path(tmp) / "team"
        generate_team(team, default_members(2))
        for name in argv[1:] or CAPTURES:
            capture(name, out, team)


if __name__ == "__main__":
    main(sys.argv[1:])
