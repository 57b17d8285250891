"""Security end to end: `coapkb keys`, a robot's start-up with bad keys, a
team of robot processes with OSCORE on (the default), `coapkb query`."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import cbor2
import pytest
from support import ONTOLOGIES, ServerProcess, coapkb, free_udp_port

from coapkb.harness.team import Team, TeamSpec
from coapkb.security import load_identity
from coapkb.security.coap import ClientSecurity
from coapkb.security.curve import ZmqClientSecurity
from coapkb.security.zenoh_tls import ZenohClientSecurity
from coapkb.transport import PeerUnreachable, open_client
from coapkb.transport.messages import ContentFormat, Method, Request, Status


async def test_keys_command_and_a_missing_key_at_start_up(tmp_path: Path) -> None:
    team_dir = tmp_path / "team"
    code, out, err = await coapkb("keys", "--team-dir", str(team_dir), "--robots", "3")
    assert code == 0, err
    for name in ("Robot1", "Robot2", "Robot3", "feeder", "operator"):
        assert (team_dir / f"{name}.key").stat().st_mode & 0o777 == 0o600
        assert load_identity(team_dir, name).private_d.hex() not in out + err  # keys never printed
    code, _, err = await coapkb("keys", "--team-dir", str(team_dir))
    assert code != 0 and err.startswith("coapkb: ") and "already holds a team" in err

    port = free_udp_port()
    (tmp_path / "robot1.toml").write_text(f"""
robot_id = "Robot1"
bind = "coap://127.0.0.1:{port}"
kb = ["{ONTOLOGIES / 'Object.owl'}", "{ONTOLOGIES / 'Location.owl'}", "{ONTOLOGIES / 'Capability.owl'}"]
[security]
credentials = "team"
[team.Robot1]
endpoint = "coap://127.0.0.1:{port}"
kbs = ["Object", "Location", "Capability"]
""")
    (team_dir / "Robot1.key").unlink()
    code, out, err = await coapkb("agent", "--config", str(tmp_path / "robot1.toml"))
    assert code != 0 and "Traceback" not in err
    assert err.splitlines() == [f"coapkb: error: cannot read private key {team_dir / 'Robot1.key'}: No such file or directory"]


def _client_security(transport: str, identity, expected: dict[str, str]):
    if transport == "coap":
        return ClientSecurity(identity, expected)
    if transport == "zmq":
        return ZmqClientSecurity(identity, expected)
    return ZenohClientSecurity(identity)


@pytest.mark.parametrize("transport", ["coap", "zmq", "zenoh", "zenoh+quic"])
async def test_a_secure_team_runs_and_keeps_others_out(transport: str) -> None:
    """OSCORE/EDHOC over CoAP, CurveZMQ over ZeroMQ, mTLS over Zenoh (TCP and QUIC): a plain
    client gets 4.01 (CoAP) or no connection at all (ZeroMQ, Zenoh), a robot
    posting a task 4.03 (over Zenoh no answer: its access control drops it)."""
    spec = TeamSpec(robots=3, query_timeout_s=5.0, transport=transport)
    assert spec.secure  # on by default
    tasks = ["Gucci_bag_14", "Canon_tv_538", "Nonexistent_widget_1"]
    async with asyncio.timeout(120):
        async with Team.launch(spec) as team:
            assert team.team_dir is not None
            record = await team.run(tasks)
            body = cbor2.dumps({"seq": 4, "object": "Gucci_bag_187"})
            task = Request(Method.POST, "/tasks", payload=body, content_format=ContentFormat.CBOR)
            expected = {e.hostport: r for r, e in team.endpoints.items()}
            identity = load_identity(team.team_dir, "Robot2")
            plain = await open_client(transport)
            robot2 = await open_client(transport, security=_client_security(transport, identity, expected))
            try:
                for r, endpoint in team.endpoints.items():
                    if transport == "coap":
                        assert (await plain.request(endpoint, task, timeout=5)).status == Status.UNAUTHORIZED, r
                    else:
                        with pytest.raises(PeerUnreachable):
                            await plain.request(endpoint, task, timeout=1.5)
                    if transport in ("zenoh", "zenoh+quic"):  # Zenoh's ACL drops it: only the feeder's certificate
                        with pytest.raises(PeerUnreachable, match="access control"):
                            await robot2.request(endpoint, task, timeout=5)
                    else:
                        assert (await robot2.request(endpoint, task, timeout=5)).status == Status.FORBIDDEN, r
                    state = await robot2.request(endpoint, Request(Method.GET, "/robot/state"), timeout=5)
                    assert state.status == Status.CONTENT
            finally:
                await plain.aclose()
                await robot2.aclose()
    assert len(record.tasks) == 3 and not record.disputed
    assert [t.assigned_to is not None for t in record.tasks] == [True, True, False]
    assert all(not t.errors for t in record.tasks)


async def test_query_command_with_credentials(tmp_path: Path) -> None:
    team_dir = tmp_path / "team"
    assert (await coapkb("keys", "--team-dir", str(team_dir), "--robots", "1")).code == 0
    server = await ServerProcess.start(
        "--kb", *(str(ONTOLOGIES / f"{n}.owl") for n in ("Object", "Location", "Capability")),
        "--bind", f"127.0.0.1:{free_udp_port()}", "--credentials", str(team_dir),
    )
    try:
        uri = f"{server.uri}/kb/q/object-exists?name=Gucci_bag_14"
        code, out, err = await coapkb("query", uri, "--credentials", str(team_dir), "--format", "json")
        assert code == 0, err
        assert "Gucci_bag_14" in out
        code, out, err = await coapkb("query", uri)
        assert code != 0 and ("4.01" in err or "Unauthorized" in err), err
    finally:
        await server.stop()


async def test_aiocoap_client_with_a_team_credential(tmp_path: Path) -> None:
    """A standard client: aiocoap-client with the credentials file `coapkb keys --aiocoap-client` writes
    (it runs EDHOC itself, with message_3 combined into its first OSCORE request, RFC 9668)."""
    client = Path(sys.executable).parent / "aiocoap-client"
    team_dir = tmp_path / "team"
    assert (await coapkb("keys", "--team-dir", str(team_dir), "--robots", "1")).code == 0
    server = await ServerProcess.start(
        "--kb", *(str(ONTOLOGIES / f"{n}.owl") for n in ("Object", "Location", "Capability")),
        "--bind", f"127.0.0.1:{free_udp_port()}", "--credentials", str(team_dir),
    )
    try:
        code, diag, err = await coapkb("keys", "--team-dir", str(team_dir), "--aiocoap-client", "operator", "central",
                                        server.uri)
        assert code == 0, err
        (tmp_path / "operator.diag").write_text(diag)
        uri = f"{server.uri}/kb/q/object-exists?name=Gucci_bag_14"
        for credentials, expected in ((["--credentials", str(tmp_path / "operator.diag")], b"Gucci_bag_14"),
                                      ([], b"OSCORE with a team credential required")):
            proc = await asyncio.create_subprocess_exec(str(client), *credentials, uri, stdout=asyncio.subprocess.PIPE,
                                                        stderr=asyncio.subprocess.PIPE)
            out, err = await asyncio.wait_for(proc.communicate(), 30)
            assert expected in out + err, (out, err)
    finally:
        await server.stop()


async def test_a_restarted_robot_rejoins_a_secure_team() -> None:
    """Robot3 is killed and started again: it has no OSCORE contexts any more,
    its teammates' and the feeder's requests meet 4.01, they run EDHOC again
    and the run goes on (no request may leave unprotected meanwhile: that
    one would be refused by the robot's policy)."""
    from coapkb.harness.team import Fault

    spec = TeamSpec(robots=3, query_timeout_s=5.0,
                    faults=(Fault("kill", "Robot3", 0.5), Fault("restart", "Robot3", 2.0)))
    async with asyncio.timeout(120):
        async with Team.launch(spec) as team:
            record = await team.run(["Gucci_bag_14", "Canon_tv_538", "Dell_monitor_986", "Gucci_bag_187"] * 2)
    assert not record.disputed
    assert all(not t.errors for t in record.tasks), [t.errors for t in record.tasks if t.errors]
