"""CurveZMQ with the team's keys on the ZeroMQ transport (real TCP sockets):
only members connect, the same policy as over CoAP."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from support import recording_router

from coapkb.security import AccessPolicy, TeamTrust, generate_team, load_identity
from coapkb.security.curve import ZmqClientSecurity, ZmqServerSecurity
from coapkb.security.keys import default_members
from coapkb.transport import Endpoint, PeerUnreachable, open_client, serve
from coapkb.transport.messages import Method, Request, Response, Status


@pytest.fixture
async def robot1(team_dir: Path):
    router, calls = recording_router()
    security = ZmqServerSecurity(load_identity(team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
    server = await serve(router, Endpoint("zmq", "127.0.0.1", 0), security=security)
    yield server.endpoint, calls
    await server.aclose()


async def _ask(identity, peer: Endpoint, method: Method, path: str, timeout: float = 5.0) -> Response:
    security = None if identity is None else ZmqClientSecurity(identity, {peer.hostport: "Robot1"})
    client = await open_client("zmq", security=security)
    try:
        return await client.request(peer, Request(method, path, payload=b"x" if method == Method.POST else b""),
                                    timeout=timeout)
    finally:
        await client.aclose()


async def test_members_get_what_their_role_allows(robot1, team_dir: Path) -> None:
    peer, calls = robot1
    cases = [
        ("feeder", Method.POST, "/tasks", Status.CHANGED),
        ("Robot2", Method.POST, "/tasks", Status.FORBIDDEN),
        ("Robot2", Method.POST, "/decisions", Status.CHANGED),
        ("Robot3", Method.POST, "/decisions", Status.FORBIDDEN),
        ("operator", Method.GET, "/tasks", Status.CONTENT),
    ]
    for who, method, path, expected in cases:
        assert (await _ask(load_identity(team_dir, who), peer, method, path)).status == expected, (who, path)
    assert calls == [("POST", "/tasks"), ("POST", "/decisions"), ("GET", "/tasks")]


async def test_no_curve_or_a_stranger_never_gets_through(robot1, team_dir: Path, tmp_path: Path) -> None:
    peer, calls = robot1
    with pytest.raises(PeerUnreachable):
        await _ask(None, peer, Method.POST, "/tasks", timeout=1.5)
    generate_team(tmp_path / "other", default_members(3))
    stranger = load_identity(tmp_path / "other", "feeder")
    # It knows Robot1's public key (so its handshake is well formed); Robot1 does not know it.
    ours = load_identity(team_dir, "feeder").trust
    stranger = replace(stranger, trust=TeamTrust(ours.members))
    stranger = replace(stranger, member=replace(stranger.member, name="feeder"))
    with pytest.raises(PeerUnreachable):
        await _ask(stranger, peer, Method.POST, "/tasks", timeout=1.5)
    assert calls == []


async def test_a_client_that_does_not_know_the_server_is_refused(team_dir: Path) -> None:
    """CurveZMQ needs the server's key: an endpoint no member is known at is a clear error."""
    client = await open_client("zmq", security=ZmqClientSecurity(load_identity(team_dir, "feeder"), {}))
    try:
        with pytest.raises(Exception, match="no team member is known to serve"):
            await client.request(Endpoint("zmq", "127.0.0.1", 1), Request(Method.GET, "/tasks"), timeout=1)
    finally:
        await client.aclose()
