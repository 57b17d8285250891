"""The wire trace (COAPKB_WIRE_TRACE): the CoAP parts it splits a datagram
into, and what a team of robot processes on loopback writes with it on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import aiocoap
import pytest
from aiocoap.numbers.codes import Code
from aiocoap.numbers.types import CON, NON
from aiocoap.optiontypes import BlockOption
from support import ROOT

from coapkb.transport.coap import wire_trace
from coapkb.transport.coap.wire_trace import OSCORE_OPTION, describe, split_coap


def _message(mtype: int = NON, **kwargs: object) -> aiocoap.Message:
    message = aiocoap.Message(**kwargs)  # type: ignore[arg-type]
    message.mtype, message.mid, message.token = mtype, 0x1234, b"\x0a\x0b"
    return message


def test_split_adds_up_to_the_datagram_and_names_each_option() -> None:
    m = _message(code=Code.GET, mtype=NON, uri="coap://10.0.0.1/kb/q/pick-facts?name=Gucci_bag_14", observe=0)
    m.opt.accept = 60
    data = m.encode()
    s = split_coap(data)
    assert (s.mtype, s.code, s.mid, s.token) == (1, 1, 0x1234, b"\x0a\x0b")
    assert [n for n, _ in s.options] == [6, 11, 11, 11, 15, 17]  # Observe, Uri-Path x3, Uri-Query, Accept
    assert s.option_size(6) == 1  # Observe 0: delta 6, no value
    assert s.option_size(17) == 2  # Accept 60: delta 2, one byte
    assert (s.marker, s.payload) == (0, 0)
    assert s.total == len(data) and s.header == 4


def test_split_of_long_options_and_a_payload() -> None:
    m = _message(code=Code.CONTENT, mtype=CON, payload=b"x" * 300)
    m.opt.etag = b"12345678"
    m.opt.oscore = b"\x09\x01\x02"
    m.opt.uri_query = ("q=" + "a" * 300,)  # a 302-byte option value: 2 extension bytes for its length
    data = m.encode()
    s = split_coap(data)
    assert s.option_size(OSCORE_OPTION) == 1 + 3
    assert s.option_size(15) == 1 + 2 + 302
    assert (s.marker, s.payload) == (1, 300)
    assert s.total == len(data)


@pytest.mark.parametrize("data", [b"", b"\x40\x01", b"\x80\x01\x00\x00", b"\x49\x01\x00\x00", b"\x40\x01\x00\x00\xff",
                                  b"\x40\x01\x00\x00\xf1", b"\x40\x01\x00\x00\x35ab"])
def test_split_refuses_what_is_not_coap(data: bytes) -> None:
    with pytest.raises(ValueError):
        split_coap(data)


def test_describe_names_requests_answers_blocks_and_edhoc() -> None:
    get = _message(code=Code.GET, uri="coap://h/robot/plan?of=Robot2&at=3", observe=0)
    assert describe(get) == {"code": "GET", "path": "/robot/plan", "query": "of=Robot2&at=3", "observe": 0,
                             "payload": 0}
    answer = _message(code=Code.CONTENT, payload=b"abc")
    answer.opt.block2 = BlockOption.BlockwiseTuple(2, True, 6)
    assert describe(answer) == {"code": "2.05", "block2": [2, 1, 6], "payload": 3}
    m1 = _message(code=Code.POST, uri="coap://h/.well-known/edhoc", payload=b"\xf5\x03")
    m3 = _message(code=Code.POST, uri="coap://h/.well-known/edhoc", payload=b"\x0d\x58")
    assert describe(m1)["edhoc"] == 1 and describe(m3)["edhoc"] == 3


def test_the_trace_is_off_without_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(wire_trace.ENV, raising=False)
    noted: list[str] = []
    assert wire_trace.tracer(lambda attribute, describe: noted.append(attribute)) is None
    assert noted == []  # and OSCORE left as it is


def _traces(directory: Path) -> dict[int, list[dict[str, object]]]:
    out = {}
    for path in directory.glob("wire-*.jsonl"):
        lines = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
        out[int(path.stem.removeprefix("wire-"))] = lines
    return out


def test_a_team_on_loopback_writes_every_datagram_with_its_plaintext(tmp_path: Path) -> None:
    """Three robot processes and the feeder, OSCORE keyed by EDHOC: every
    process writes its datagrams, protected ones with what they carry."""
    trace_dir, record_file = tmp_path / "wire", tmp_path / "record.json"
    result = subprocess.run(
        [sys.executable, "-m", "coapkb", "team", "--robots", "3", "--tasks", "2", "--quiet", "--record", str(record_file)],
        cwd=ROOT, capture_output=True, text=True, timeout=120, env={**os.environ, wire_trace.ENV: str(trace_dir)},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    traces = _traces(trace_dir)
    assert len(traces) == 4  # the robots and the team command (the feeder)
    lines = [line for ls in traces.values() for line in ls]
    for line in lines:
        assert {"t", "pid", "role", "port", "dst", "type", "mid", "token", "code", "len"} <= set(line), line
        assert line["type"] in ("CON", "NON", "ACK", "RST") and line["len"] >= 4
        assert "error" not in line, line
    servers = {line["port"] for line in lines if line["role"] == "server"}
    assert len(servers) == 3  # each robot's server port

    requests = [line for line in lines if line["code"].startswith("0.") and line["code"] != "0.00"]
    edhoc = Counter(line.get("edhoc") for line in requests if line.get("path") == "/.well-known/edhoc")
    # Each robot keys with its two teammates, the feeder with every robot: a message_3 from each
    # process to each it keys with (sent again if its answer was late on a busy machine, and
    # message_1 more often if a teammate was not listening yet).
    keyed = {(line["pid"], line["dst"]) for line in requests
             if line.get("path") == "/.well-known/edhoc" and line.get("edhoc") == 3}
    assert len(keyed) == 3 * 2 + 3 and edhoc[1] >= len(keyed)
    protected = [line for line in requests if line.get("oscore")]
    assert protected and all(line["code"] in ("0.02", "0.05") for line in protected)  # POST, or FETCH to observe
    paths = Counter(line["path"] for line in protected)
    assert paths["/tasks"] >= 3 * 2 and paths["/robot/outcome"] >= 3 and paths["/robot/plan"] >= 3 * 2
    assert any(p.startswith("/kb/q/") for p in paths), paths
    # PATCH: the robots write their picks and positions (a team's KB is writable by default).
    assert {line["inner_code"] for line in protected} <= {"GET", "POST", "FETCH", "PATCH", "iPATCH"}

    # Every answer says which request it answers, and a client sent that request with that token.
    asked = {(line["token"], line["port"]) for line in requests}
    answers = [line for line in lines if line["role"] == "server" and line["code"] >= "2."]
    assert answers
    for line in answers:
        assert "req" in line and line["req"]["code"] in ("GET", "POST", "FETCH", "PATCH", "iPATCH"), line
        client_port = int(line["dst"].rpartition(":")[2])
        assert (line["token"], client_port) in asked, line
    plan = [line for line in answers if line["req"].get("path") == "/robot/plan" and line.get("oscore")]
    assert plan and all(line["payload"] > 0 and line["observe"] == 0 for line in plan)
    # Protected: the datagram holds the plaintext's payload and the 8-byte tag.
    assert all(line["len"] > line["payload"] + 8 for line in plan)
    acks = [line for line in lines if line["code"] == "0.00"]
    assert acks and all(line["type"] == "ACK" and line["token"] == "" and line["len"] == 4 for line in acks)

    # Each robot's trace holds at least what its counters saw sent (the statistics
    # download that reads them comes after, and is traced too).
    record = json.loads(record_file.read_text(encoding="utf-8"))
    by_port = defaultdict(list)
    for pid_lines in traces.values():
        for line in pid_lines:
            by_port[line["pid"]].append(line)
    for robot, stats in record["robot_stats"].items():
        sent = stats["client"]["messages_sent"] + stats["server"]["messages_sent"]
        sent_bytes = stats["client"]["bytes_sent"] + stats["server"]["bytes_sent"]
        mine = [ls for ls in traces.values() if any(line["role"] == "server" for line in ls)
                and len(ls) >= sent and sum(int(line["len"]) for line in ls) >= sent_bytes]
        assert mine, f"no trace holds {robot}'s {sent} datagrams"
