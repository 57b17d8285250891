"""The data folder from the configuration and the command line: ``data_dir``
in a robot's TOML, ``--data-dir`` on ``coapkb serve``, ``agent`` and
``team``; a served KB killed and started again on its folder; a corrupt
folder refused in one line."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
from support import ONTOLOGIES, ServerProcess, coapkb, free_udp_port

from coapkb.config import ConfigError, dump_config, load_config, parse_config
from coapkb.kb.client import KBClient
from coapkb.kb.results import expect_select
from coapkb.transport import open_client
from coapkb.transport.registry import parse_endpoint

LOC = "http://www.tcs.org/2018/Location#"
PREFIX = f"PREFIX loc: <{LOC}>\n"
CONFIG = {
    "robot_id": "Robot1",
    "bind": "coap://127.0.0.1:5701",
    "kb_writable": True,
    "team": {"Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Location", "Object", "Capability"]}},
}


def test_data_dir_is_read_beside_the_toml_and_written_back(tmp_path: Path) -> None:
    assert parse_config(CONFIG).data_dir is None
    config = parse_config({**CONFIG, "data_dir": "data/Robot1"}, base_dir=tmp_path)
    assert config.data_dir == tmp_path / "data" / "Robot1"
    toml = tmp_path / "elsewhere" / "robot.toml"
    toml.parent.mkdir()
    toml.write_text(dump_config(config), encoding="utf-8")
    assert load_config(toml) == config


@pytest.mark.parametrize(("value", "message"), [
    (3, "data_dir: expected str, got 3"),
    ("", "data_dir: must not be empty"),
    ("robot.toml", "data_dir: .*robot.toml is not a folder"),
])
def test_a_bad_data_dir_is_named(tmp_path: Path, value: object, message: str) -> None:
    (tmp_path / "robot.toml").write_text("", encoding="utf-8")
    with pytest.raises(ConfigError, match=message):
        parse_config({**CONFIG, "data_dir": value}, base_dir=tmp_path)


async def _written(uri: str) -> set[str]:
    client = await open_client("coap")
    try:
        result = await KBClient(client, timeout=10).sparql(parse_endpoint(uri),
                                                           PREFIX + "SELECT ?v WHERE { ?s loc:written ?v }")
        return {str(row["v"]) for row in expect_select(result, "written").as_dicts()}
    finally:
        await client.aclose()


@pytest.mark.timeout(120)
async def test_serve_keeps_its_writes_across_a_kill(tmp_path: Path) -> None:
    folder = tmp_path / "kept"
    args = ("--kb", str(ONTOLOGIES / "Location.owl"), "--writable", "--data-dir", str(folder))
    server = await ServerProcess.start(*args, "--bind", f"127.0.0.1:{free_udp_port()}")
    try:
        for i in range(3):
            done = await coapkb("update", server.uri, PREFIX + f'INSERT DATA {{ loc:w{i} loc:written "w{i}" }}')
            assert done.code == 0, done.stderr
    finally:
        server.proc.send_signal(signal.SIGKILL)
        await server.proc.wait()
    server = await ServerProcess.start(*args, "--bind", f"127.0.0.1:{free_udp_port()}")
    try:
        assert await _written(server.uri) == {"w0", "w1", "w2"}
    finally:
        await server.stop()

    journal = folder / "journal.0"
    data = bytearray(journal.read_bytes())
    data[40] ^= 0xFF  # inside the meta record, records after it
    journal.write_bytes(bytes(data))
    refused = await coapkb("serve", *args, "--bind", f"127.0.0.1:{free_udp_port()}")
    assert refused.code == 2
    assert refused.stderr.splitlines() == [
        f"coapkb: error: {journal}: corrupt at byte 8: a record fails its checksum and records follow it"
    ]


async def test_data_dir_needs_writes(tmp_path: Path) -> None:
    served = await coapkb("serve", "--kb", str(ONTOLOGIES / "Location.owl"), "--data-dir", str(tmp_path))
    assert served.code == 2 and "--data-dir keeps writes: it needs --writable" in served.stderr
    team = await coapkb("team", "--tasks", "1", "--read-only", "--data-dir", str(tmp_path))
    assert team.code == 2 and "--data-dir keeps the robots' writes: a --read-only team makes none" in team.stderr
