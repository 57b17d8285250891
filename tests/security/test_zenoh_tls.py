"""Zenoh over TLS with mutual authentication by the team's certificates (real
TCP sockets on 127.0.0.1): only members connect, and the team's policy holds
per resource as over CoAP and ZeroMQ."""

from __future__ import annotations

import asyncio
import contextlib
import json
from pathlib import Path

import pytest
from support import ONTOLOGIES, ServerProcess, coapkb, free_tcp_port, recording_router

from coapkb.security import AccessPolicy, SecurityError, generate_team, load_identity
from coapkb.security.keys import default_members
from coapkb.security.zenoh_tls import ZenohClientSecurity, ZenohServerSecurity
from coapkb.transport import Endpoint, PeerUnreachable, open_client, serve
from coapkb.transport.messages import Method, Request, Response, Status
from coapkb.transport.router import Router
from coapkb.transport.zenoh.mapping import RequestHeader, decode_response_header, encode_request_header


@pytest.fixture
async def robot1(team_dir: Path):
    router, calls = recording_router("/robot/state")
    security = ZenohServerSecurity(load_identity(team_dir, "Robot1"), AccessPolicy(lambda: {"Robot2"}))
    server = await serve(router, Endpoint("zenoh", "127.0.0.1", 0), security=security)
    yield server, calls
    await server.aclose()


async def _ask(security, peer: Endpoint, method: Method, path: str, timeout: float = 5.0) -> Response:
    client = await open_client("zenoh", security=security)
    try:
        return await client.request(peer, Request(method, path, payload=b"x" if method == Method.POST else b""),
                                    timeout=timeout)
    finally:
        await client.aclose()


def _member(team_dir: Path, name: str) -> ZenohClientSecurity:
    return ZenohClientSecurity(load_identity(team_dir, name))


async def test_members_get_what_their_role_allows(robot1, team_dir: Path) -> None:
    """/tasks only for the feeder's certificate and /decisions only for robots'
    (Zenoh's access control drops the query: no answer at all), then the
    team's policy per request (the deciding robot)."""
    server, calls = robot1
    dropped = None
    cases = [
        ("feeder", Method.POST, "/tasks", Status.CHANGED),
        ("Robot2", Method.POST, "/tasks", dropped),
        ("operator", Method.GET, "/tasks", dropped),  # stricter than over CoAP: Zenoh's ACL cannot tell GET from POST
        ("Robot2", Method.POST, "/decisions", Status.CHANGED),
        ("Robot3", Method.POST, "/decisions", Status.FORBIDDEN),
        ("feeder", Method.POST, "/decisions", dropped),
        ("operator", Method.GET, "/robot/state", Status.CONTENT),
    ]
    for who, method, path, expected in cases:
        if expected is dropped:
            with pytest.raises(PeerUnreachable, match=f"access control refuses {path}"):
                await _ask(_member(team_dir, who), server.endpoint, method, path, timeout=3)
        else:
            assert (await _ask(_member(team_dir, who), server.endpoint, method, path)).status == expected, (who, path)
    assert calls == [("POST", "/tasks"), ("POST", "/decisions"), ("GET", "/robot/state")]


async def test_observe_over_tls(robot1, team_dir: Path) -> None:
    server, _ = robot1
    client = await open_client("zenoh", security=_member(team_dir, "Robot2"))
    try:
        async with contextlib.aclosing(client.observe(server.endpoint, Request(Method.GET, "/robot/state"), timeout=5)) as stream:
            first = await anext(stream)
        assert first.status == Status.CONTENT
    finally:
        await client.aclose()


async def test_no_certificate_or_another_teams_never_gets_through(robot1, team_dir: Path, tmp_path: Path) -> None:
    server, calls = robot1
    # A plain (tcp/) client: the server listens on tls/ only.
    with pytest.raises(PeerUnreachable):
        await _ask(None, server.endpoint, Method.POST, "/tasks", timeout=2)
    # A certificate named "feeder", from another team's CA: the handshake fails both ways.
    generate_team(tmp_path / "other", default_members(3))
    with pytest.raises(PeerUnreachable, match="cannot reach"):
        await _ask(_member(tmp_path / "other", "feeder"), server.endpoint, Method.POST, "/tasks", timeout=2)
    assert calls == []
    # The server survived both and still serves the team.
    assert (await _ask(_member(team_dir, "feeder"), server.endpoint, Method.POST, "/tasks")).status == Status.CHANGED


async def test_a_query_that_names_no_session_or_dodges_the_acl_is_refused(robot1, team_dir: Path) -> None:
    """mTLS let it in, but the server cannot tell which member asks: 4.01;
    Robot2 reaching /tasks by a key Zenoh's ACL does not name: 4.00; nothing changes."""
    import zenoh

    from coapkb.transport.zenoh.transport import session_config

    server, calls = robot1

    def post(who: str, key: str) -> list:
        # A task post as the transport sends it, but without source_info; in a
        # thread, since Zenoh's blocking API would stall the server's loop.
        config = session_config("client", connect=(f"tls/{server.endpoint.hostport}",))
        _member(team_dir, who).configure(config)
        session = zenoh.open(config)
        try:
            attachment = encode_request_header(RequestHeader(Method.POST))
            return list(session.get(key, payload=b"x", attachment=attachment, timeout=5))
        finally:
            session.close()

    replies = await asyncio.to_thread(post, "feeder", "coapkb/tasks")
    assert len(replies) == 1 and replies[0].ok is not None
    assert decode_response_header(replies[0].ok.attachment.to_bytes()).status == Status.UNAUTHORIZED
    for key in ("coapkb/%74asks", "coapkb/*", "coapkb/**"):
        replies = await asyncio.to_thread(post, "Robot2", key)
        assert len(replies) == 1 and replies[0].err is not None, key
        assert replies[0].err.payload.to_bytes().startswith(b"4.00 not the canonical key"), key
    assert calls == []


async def test_udp_cannot_be_secured(team_dir: Path) -> None:
    router = Router()
    with pytest.raises(SecurityError, match="reliable UDP, QUIC without encryption or authentication, and cannot be secured"):
        await serve(router, Endpoint("zenoh+udp", "127.0.0.1", 0),
                    security=ZenohServerSecurity(load_identity(team_dir, "Robot1")))
    client = await open_client("zenoh+udp", security=_member(team_dir, "feeder"))
    try:
        with pytest.raises(SecurityError, match="cannot be secured; use zenoh\\+quic://"):
            await client.request(Endpoint("zenoh+udp", "127.0.0.1", 1), Request(Method.GET, "/tasks"), timeout=1)
    finally:
        await client.aclose()


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "Robot1.tls.key").unlink(), r"cannot read private key .*Robot1\.tls\.key: No such file"),
    (lambda d: (d / "team-ca.pem").unlink(), r"cannot read certificate .*team-ca\.pem"),
    (lambda d: (d / "Robot1.tls.key").chmod(0o644), "readable by group or others"),
    (lambda d: (d / "Robot1.tls.pem").write_bytes((d / "Robot2.tls.pem").read_bytes()), "not the certificate team.json"),
    (lambda d: (d / "team.json").write_text(json.dumps(
        {**json.loads((d / "team.json").read_text()), "tls": None})), "no TLS certificates"),
])
def test_tls_files_are_checked_at_start_up(team_dir: Path, damage, message: str) -> None:
    damage(team_dir)
    with pytest.raises(SecurityError, match=message):
        ZenohServerSecurity(load_identity(team_dir, "Robot1"))


def test_no_key_in_the_public_files(team_dir: Path) -> None:
    key = (team_dir / "Robot1.tls.key").read_text()
    assert (team_dir / "Robot1.tls.key").stat().st_mode & 0o777 == 0o600
    body = "".join(key.splitlines()[1:-1])
    assert body not in (team_dir / "team.json").read_text() and body not in (team_dir / "team-ca.pem").read_text()
    assert not list(team_dir.glob("*ca*.key"))  # the CA's key is never written


async def test_serve_and_query_over_tls_from_the_command_line(tmp_path: Path) -> None:
    team_dir = tmp_path / "team"
    code, out, err = await coapkb("keys", "--team-dir", str(team_dir), "--robots", "1")
    assert code == 0, err
    assert "PRIVATE KEY" not in out + err  # the TLS keys stay in their files
    kbs = [str(ONTOLOGIES / f"{n}.owl") for n in ("Object", "Location", "Capability")]
    server = await ServerProcess.start("--kb", *kbs, "--bind", f"127.0.0.1:{free_tcp_port()}",
                                       "--transport", "zenoh", "--credentials", str(team_dir))
    try:
        uri = f"{server.uri}/kb/q/object-exists?name=Gucci_bag_14"
        assert uri.startswith("zenoh://")
        code, out, err = await coapkb("query", uri, "--credentials", str(team_dir), "--format", "json")
        assert code == 0 and "Gucci_bag_14" in out, err
        code, out, err = await coapkb("query", uri, "--timeout", "3")
        assert code != 0 and "Traceback" not in err and "cannot reach" in err, err
        # Still serving the team after a stranger's attempt.
        code, out, err = await coapkb("query", uri, "--credentials", str(team_dir), "--format", "json")
        assert code == 0 and "Gucci_bag_14" in out, err
    finally:
        await server.stop()
    (team_dir / "central.tls.key").unlink()
    code, out, err = await coapkb("serve", "--kb", *kbs, "--bind", f"127.0.0.1:{free_tcp_port()}",
                                   "--transport", "zenoh", "--credentials", str(team_dir))
    assert code != 0 and err.splitlines() == [
        f"coapkb: error: cannot read private key {team_dir / 'central.tls.key'}: No such file or directory"]


async def test_a_member_cannot_answer_or_notify_in_the_robots_name(robot1, team_dir: Path) -> None:
    """Zenoh routes between a peer's clients: Robot3's session declares a
    queryable on coapkb/** and publishes on an observer's notification key;
    Robot1's access control keeps both out, so Robot2 gets Robot1's answer
    and only Robot1's notifications."""
    import zenoh

    from coapkb.transport.zenoh.transport import session_config

    server, _ = robot1

    def open_as(who: str) -> zenoh.Session:
        config = session_config("client", connect=(f"tls/{server.endpoint.hostport}",))
        _member(team_dir, who).configure(config)
        return zenoh.open(config)

    def through_the_server(session: zenoh.Session) -> list[bytes]:
        """A query answered by Robot1: its final reply comes after the server
        took everything ``session`` sent before it (one link, in order)."""
        replies = session.get("coapkb/robot/state", timeout=3, source_info=zenoh.SourceInfo(session.id, 0))
        return [r.ok.payload.to_bytes() for r in replies if r.ok]

    def attack() -> tuple[list[bytes], list[bytes]]:
        victim, rogue = open_as("Robot2"), open_as("Robot3")
        try:
            forged = rogue.declare_queryable("coapkb/**", lambda q: q.reply(q.key_expr, b"forged"))
            through_the_server(rogue)  # the forged queryable's declaration reached the server
            seen: list[bytes] = []
            sub = victim.declare_subscriber("coapkb-obs/victim/0", lambda s: seen.append(s.payload.to_bytes()))
            answers = through_the_server(victim)  # after the subscriber's declaration, on the same link
            rogue.put("coapkb-obs/victim/0", b"forged")
            through_the_server(rogue)  # the server took the put ...
            through_the_server(victim)  # ... and sent the victim what it routes before this answer
            forged.undeclare()
            sub.undeclare()
            return answers, seen
        finally:
            victim.close()
            rogue.close()

    answers, seen = await asyncio.to_thread(attack)
    assert answers == [b"ok"] and seen == []


async def test_the_client_checks_which_member_serves_an_endpoint(robot1, team_dir: Path) -> None:
    """As with EDHOC and CurveZMQ: the certificate at an endpoint must be the
    member the client's configuration puts there."""
    server, calls = robot1
    peer = server.endpoint
    identity = load_identity(team_dir, "feeder")
    right = ZenohClientSecurity(identity, {peer.hostport: "Robot1"})
    assert (await _ask(right, peer, Method.POST, "/tasks")).status == Status.CHANGED
    wrong = ZenohClientSecurity(identity, {peer.hostport: "Robot2"})
    with pytest.raises(PeerUnreachable, match="presented Robot1's certificate, not Robot2's"):
        await _ask(wrong, peer, Method.POST, "/tasks")
    assert calls == [("POST", "/tasks")]
