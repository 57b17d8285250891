"""experiments/byte_budget.py: frames, the join with the wire traces, kinds,
copies, parts, the exact window, the minimum and the tables (no root: the
runs are made up here)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import aiocoap
import pytest
from aiocoap.numbers.codes import Code
from aiocoap.numbers.types import ACK, CON, NON

from coapkb.bench.linkemu.capture import CapturedFrame
from coapkb.transport.coap.wire_trace import OSCORE_OPTION, split_coap
from experiments import byte_budget as bb

HOSTS = {"10.77.0.1": "Robot1", "10.77.0.2": "Robot2", "10.77.0.3": "Robot3", "10.77.0.4": "feeder"}
IP = {name: ip for ip, name in HOSTS.items()}


def frame(src: str, sport: int, dst: str, dport: int, payload: bytes, proto: int = 17) -> bytes:
    """An Ethernet/IPv4/UDP frame (or another IP protocol) from host ``src`` to ``dst``."""
    udp = sport.to_bytes(2, "big") + dport.to_bytes(2, "big") + (8 + len(payload)).to_bytes(2, "big") + b"\0\0"
    body = (udp + payload) if proto == 17 else payload
    ip = (bytes([0x45, 0]) + (20 + len(body)).to_bytes(2, "big") + b"\0\0\0\0" + bytes([64, proto]) + b"\0\0"
          + bytes(int(x) for x in IP[src].split(".")) + bytes(int(x) for x in IP[dst].split(".")))
    return b"\x02" * 6 + b"\x02" * 6 + b"\x08\x00" + ip + body


def coap(mtype: int, code: Any, mid: int, token: bytes, uri: str | None = None, payload: bytes = b"",
         oscore: bytes | None = None, observe: int | None = None) -> bytes:
    m = aiocoap.Message(code=code, payload=payload, **({"uri": uri} if uri else {}))
    m.mtype, m.mid, m.token = mtype, mid, token
    if oscore is not None:
        m.opt.oscore = oscore
    if observe is not None:
        m.opt.observe = observe
    return m.encode()


def test_parse_frame_and_the_headers_it_counts() -> None:
    data = coap(NON, Code.GET, 7, b"\x01", "coap://h/kb/q/pick-facts?name=X")
    f = frame("Robot1", 40000, "Robot2", 5683, data)
    assert bb.parse_frame(f) == ("10.77.0.1", "10.77.0.2", 40000, 5683, 42, data)
    assert bb.parse_frame(frame("Robot1", 0, "Robot2", 0, b"\x03\x03" + b"\0" * 30, proto=1)) is None
    assert bb.parse_frame(b"\0" * 20) is None


def test_capture_in_and_out_frames_give_datagrams_losses_and_others() -> None:
    a = frame("Robot1", 40000, "Robot2", 5683, coap(NON, Code.GET, 1, b"\x01", "coap://h/robot/state"))
    b = frame("Robot2", 5683, "Robot1", 40000, coap(NON, Code.CONTENT, 9, b"\x01", payload=b"s"))
    icmp = frame("Robot3", 0, "Robot1", 0, b"\x03\x03" + b"\0" * 30, proto=1)
    frames = [CapturedFrame(1.0, "p-Robot1", "in", a), CapturedFrame(1.1, "p-Robot2", "out", a),
              CapturedFrame(1.2, "p-Robot2", "in", b), CapturedFrame(1.3, "p-Robot3", "in", icmp)]
    sent, others = bb.datagrams_from_capture(frames, HOSTS)
    assert [(d.src, d.dst, d.lost, d.delivered_t) for d in sent] == [("Robot1", "Robot2", False, 1.1),
                                                                      ("Robot2", "Robot1", True, None)]
    assert sent[0].coap is not None and sent[0].coap.mid == 1
    assert [(o.src, o.dst, o.icmp, o.frame) for o in others] == [("Robot3", "Robot1", True, len(icmp))]


def test_parts_add_up_to_the_frame_plain_and_protected() -> None:
    plain = coap(NON, Code.CONTENT, 3, b"\xab\xcd", payload=b"x" * 40)
    d = bb.Datagram(0.0, "Robot2", "Robot1", 5683, 40000, 42 + len(plain), 42, plain, coap=split_coap(plain))
    parts = bb.parts(d)
    assert parts == {"headers": 42, "coap": 6, "options": 1, "oscore": 0, "inner_options": 0, "payload": 40}
    assert sum(parts[p] for p in ("headers", "coap", "options", "oscore", "payload")) == d.frame
    # Protected: 1 inner code + 3 inner option bytes + marker + 40 payload, and the tag.
    ciphertext = b"\0" * (1 + 3 + 1 + 40 + bb.AEAD_TAG)
    outer = coap(NON, Code.CHANGED, 4, b"\xab", payload=ciphertext, oscore=b"\x09\x05", observe=12)
    d = bb.Datagram(0.0, "Robot2", "Robot1", 5683, 40000, 42 + len(outer), 42, outer, coap=split_coap(outer))
    d.plain = {"code": "2.05", "payload": 40}
    parts = bb.parts(d)
    assert parts["coap"] == 5 and parts["options"] == 2  # Observe 12: one header byte and one value byte
    assert parts["inner_options"] == 1 + 3 + 1 and parts["payload"] == 40
    assert parts["oscore"] == (1 + 2) + 1 + bb.AEAD_TAG + parts["inner_options"]  # option, marker, tag, inner
    assert sum(parts[p] for p in ("headers", "coap", "options", "oscore", "payload")) == d.frame


@pytest.mark.parametrize(("plain", "kind"), [
    ({"code": "POST", "path": "/.well-known/edhoc", "edhoc": 1}, ("EDHOC message_1", "")),
    ({"code": "POST", "path": "/.well-known/edhoc", "edhoc": 3}, ("EDHOC message_3", "")),
    ({"code": "GET", "path": "/kb/q/pick-place", "query": "name=X"}, ("query", "pick-place")),
    ({"code": "FETCH", "path": "/kb/sparql"}, ("query", "sparql")),
    ({"code": "GET", "path": "/robot/plan", "observe": 0}, ("registration", "/robot/plan")),
    ({"code": "POST", "path": "/robot/plan", "query": "of=Robot2&at=3"}, ("hearsay", "/robot/plan")),
    ({"code": "GET", "path": "/robot/state"}, ("liveness", "/robot/state")),
    ({"code": "GET", "path": "/robot/lease", "query": "r=Robot1"}, ("lease", "/robot/lease")),
    ({"code": "POST", "path": "/tasks", "query": "qh=12"}, ("task post", "")),
    ({"code": "POST", "path": "/decisions"}, ("decision post", "")),
    ({"code": "GET", "path": "/robot/stats"}, ("stats", "")),
    ({"code": "PATCH", "path": "/kb", "query": "wid=Robot1.7.3"}, ("write", "")),
    ({"code": "iPATCH", "path": "/kb"}, ("write", "")),
    ({"code": "POST", "path": "/kb/sync"}, ("replication", "")),
    ({"code": "GET", "path": "/kb"}, ("other request", "GET /kb")),
    ({"code": "GET", "path": "/elsewhere"}, ("other request", "GET /elsewhere")),
])
def test_request_kinds(plain: dict[str, Any], kind: tuple[str, str]) -> None:
    assert bb.request_kind(plain) == kind


def _dg(t: float, src: str, sport: int, dst: str, dport: int, mtype: int, code: int, mid: int, token: bytes,
        plain: dict[str, Any] | None = None, delivered: float | None = None, payload: int = 0) -> bb.Datagram:
    split = bb.CoapSplit(mtype, code, mid, token, ((OSCORE_OPTION, 2),), 1 if payload else 0, payload)
    d = bb.Datagram(t, src, dst, sport, dport, 42 + split.total, 42, b"", coap=split, lost=delivered is None,
                    delivered_t=delivered)
    if plain is not None:
        d.record = {"t": t, **plain, "inner_code": plain["code"]}
    return d


GET, POST, FETCH, CHANGED, CONTENT, UNAUTH = 1, 2, 5, 68, 69, 129
Q = {"code": "GET", "path": "/kb/q/pick-facts", "query": "name=X", "payload": 0}
QA = {"code": "2.05", "payload": 30, "req": {"code": "GET", "path": "/kb/q/pick-facts", "query": "name=X"}}


def test_copies_retries_hedges_and_answers() -> None:
    r1, r2, r3 = ("Robot1", 40000), ("Robot2", 5683), ("Robot3", 5683)
    sent = [
        _dg(0.00, *r1, *r2, NON, GET, 1, b"\x01", Q, delivered=0.01),        # first try
        _dg(0.02, *r1, *r2, NON, GET, 2, b"\x02", Q, delivered=0.03),        # its hedged copy (25 ms later)
        _dg(0.50, *r1, *r2, NON, GET, 3, b"\x03", Q, delivered=0.51),        # a retry after its timeout
        _dg(0.55, *r2, *r1, NON, CHANGED, 9, b"\x03", QA, delivered=0.56),   # the retry's answer
        _dg(0.60, *r1, *r2, NON, GET, 3, b"\x03", Q, delivered=0.61),        # the retry's Message ID again
        _dg(1.00, *r1, *r2, NON, GET, 4, b"\x04", Q, delivered=1.01),        # asked again after an answer
        _dg(1.10, *r1, *r3, NON, GET, 5, b"\x05", Q, delivered=1.11),        # the same query to another holder
        _dg(1.20, *r2, *r1, NON, UNAUTH, 10, b"\x04", {"code": "4.01", "payload": 0}, delivered=1.21),
    ]
    bb.classify(sent)
    assert [(d.kind, d.detail, d.copy) for d in sent] == [
        ("query", "pick-facts", "first"), ("query", "pick-facts", "hedge"), ("query", "pick-facts", "retry"),
        ("answer", "pick-facts", "retry"), ("query", "pick-facts", "retransmission"),
        ("query", "pick-facts", "first"), ("query", "pick-facts", "hedge"),
        ("error answer", "4.01 to query pick-facts", "first")]


def test_the_same_post_to_each_robot_is_no_copy_and_an_icmp_error_makes_a_retry() -> None:
    post = {"code": "POST", "path": "/tasks", "query": "qh=aa", "payload": 30}
    feeder = ("feeder", 50000)
    sent = [_dg(0.001 * i, *feeder, robot, 5683, NON, POST, 20 + i, bytes([i]), post, delivered=1.0)
            for i, robot in enumerate(("Robot1", "Robot2", "Robot3"))]
    m1 = {"code": "POST", "path": "/.well-known/edhoc", "edhoc": 1, "payload": 38}
    sent += [_dg(2.000, "Robot1", 40000, "Robot3", 5683, NON, POST, 30, b"\x30", m1),
             _dg(2.003, "Robot1", 40000, "Robot3", 5683, NON, POST, 31, b"\x31", m1, delivered=2.01)]
    icmp = bb.OtherFrame(2.001, "Robot3", "Robot1", 70, True)
    bb.classify(sent, [icmp])
    assert [d.copy for d in sent] == ["first", "first", "first", "first", "retry"]
    bb.classify(sent)  # without the ICMP error, 3 ms later is a hedged copy
    assert sent[-1].copy == "hedge"


def test_registration_answer_notifications_and_acks() -> None:
    reg = {"code": "GET", "path": "/robot/plan", "observe": 0, "payload": 0}
    note = {"code": "2.05", "observe": 0, "payload": 70, "req": {"code": "GET", "path": "/robot/plan", "observe": 0}}
    c, s = ("Robot1", 40000), ("Robot2", 5683)
    sent = [
        _dg(0.0, *c, *s, NON, FETCH, 1, b"\x07", reg, delivered=0.1),
        _dg(0.2, *s, *c, CON, CONTENT, 50, b"\x07", note, delivered=0.3),
        _dg(0.3, *c, *s, ACK, 0, 50, b"", {"code": "0.00"}, delivered=0.4),
        _dg(1.0, *s, *c, CON, CONTENT, 51, b"\x07", note),                  # lost
        _dg(1.5, *s, *c, CON, CONTENT, 51, b"\x07", note, delivered=1.6),   # retransmitted
        _dg(1.6, *c, *s, ACK, 0, 51, b"", {"code": "0.00"}),                # its ACK, lost
        _dg(2.0, *s, *c, CON, CONTENT, 51, b"\x07", note, delivered=2.1),
        _dg(2.1, *c, *s, ACK, 0, 51, b"", {"code": "0.00"}, delivered=2.2),  # the same ACK again
    ]
    for d in sent:
        if d.coap.code == 0:
            d.record = None
            d.coap = bb.CoapSplit(ACK, 0, d.coap.mid, b"", (), 0, 0)
    bb.classify(sent)
    assert [(d.kind, d.copy) for d in sent] == [
        ("registration", "first"), ("registration answer", "first"), ("empty ACK", "first"),
        ("notification", "first"), ("notification", "retransmission"), ("empty ACK", "first"),
        ("notification", "retransmission"), ("empty ACK", "retransmission")]
    assert bb._kind_label(sent[3]) == "notification /robot/plan"
    assert sent[2].detail == "registration answer /robot/plan" and sent[5].detail == "notification /robot/plan"
    assert [bb.breakdown_of(d) for d in sent[:4]] == [
        "robots' registrations: plans, pushed facts", "needed items, as sent", "acknowledgements of plan notifications",
        "needed items, as sent"]
    assert bb.breakdown_of(sent[4]) == "copies: retransmissions, retries, hedged copies"


def test_an_unprotected_requests_line_names_its_method_by_number() -> None:
    d = _dg(0.0, "feeder", 50000, "Robot1", 5683, NON, POST, 1, b"\x01")
    d.record = {"t": 0.0, "code": "0.02", "path": "/tasks", "query": "qh=ab", "payload": 30}
    assert bb.plaintext(d) == {"code": "POST", "path": "/tasks", "query": "qh=ab", "payload": 30}
    bb.classify([d])
    assert (d.kind, bb.breakdown_of(d)) == ("task post", "needed items, as sent")


def test_join_takes_each_trace_line_once_in_order() -> None:
    data = coap(CON, Code.CONTENT, 5, b"\x09", payload=b"abc")
    d1 = bb.Datagram(1.0, "Robot2", "Robot1", 5683, 40000, 42 + len(data), 42, data, coap=split_coap(data))
    d2 = bb.Datagram(2.0, "Robot2", "Robot1", 5683, 40000, 42 + len(data), 42, data, coap=split_coap(data))
    line = {"port": 5683, "dst": "10.77.0.1:40000", "mid": 5, "token": "09", "len": len(data)}
    records = [{**line, "t": 0.99, "n": 1}, {**line, "t": 1.98, "n": 2}, {**line, "t": 5.0, "mid": 6, "n": 3}]
    left = bb.join_traces([d1, d2], records, HOSTS)
    assert (d1.record or {})["n"] == 1 and (d2.record or {})["n"] == 2
    assert [r["n"] for r in left] == [3]


def _write_run(directory: Path, *, before: dict[str, tuple[int, int]], end: dict[str, tuple[int, int]],
               frames: list[CapturedFrame], lines: list[dict[str, Any]]) -> None:
    directory.mkdir()
    (directory / "wire").mkdir()
    (directory / "wire" / "wire-1.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines), encoding="utf-8")
    (directory / "capture.jsonl").write_text("".join(json.dumps(
        {"t": f.t, "port": f.port, "dir": f.direction, "frame": f.frame.hex()}) + "\n" for f in frames), encoding="utf-8")

    def counters(values: dict[str, tuple[int, int]]) -> dict[str, Any]:
        return {h: {"tx_bytes": b, "tx_packets": p} for h, (b, p) in values.items()}

    meta = {"row": {"loss_pct": 2.0, "security": "oscore", "tasks": 2, "wire_bytes": 0},
            "hosts": {h: IP[h] for h in before},
            "readings": [{"t0": 10.0, "t1": 10.5, "counters": counters(before)},
                         {"t0": 20.0, "t1": 20.5, "counters": counters(end)}],
            "path_stats": {"retries": 0}}
    (directory / "run.json").write_text(json.dumps(meta), encoding="utf-8")


def test_a_run_directory_is_cut_exactly_where_the_counters_read(tmp_path: Path) -> None:
    q = coap(NON, Code.POST, 1, b"\x01", payload=b"\0" * 20, oscore=b"\x09\x00\x01")
    a = coap(NON, Code.CHANGED, 2, b"\x01", payload=b"\0" * 30, oscore=b"")
    early = coap(NON, Code.POST, 3, b"\x03", "coap://h/.well-known/edhoc", payload=b"\xf5" + b"\0" * 37)
    fq, fa, fe = (frame("Robot1", 40000, "Robot2", 5683, q), frame("Robot2", 5683, "Robot1", 40000, a),
                  frame("Robot1", 40000, "Robot2", 5683, early))
    # The EDHOC message went out at 10.4 s, while the first reading was under way,
    # and was counted in it: it is not the run's, though its time is inside.
    frames = [CapturedFrame(10.4, "p-Robot1", "in", fe), CapturedFrame(10.6, "p-Robot1", "in", fq),
              CapturedFrame(10.61, "p-Robot2", "out", fq), CapturedFrame(10.7, "p-Robot2", "in", fa),
              CapturedFrame(10.71, "p-Robot1", "out", fa)]
    lines = [{"t": 10.59, "pid": 1, "role": "client", "port": 40000, "dst": "10.77.0.2:5683", "type": "NON", "mid": 1,
              "token": "01", "code": "0.02", "len": len(q), "oscore": True, "inner_code": "GET",
              "path": "/kb/q/pick-place", "query": "name=X", "payload": 0},
             {"t": 10.69, "pid": 2, "role": "server", "port": 5683, "dst": "10.77.0.1:40000", "type": "NON", "mid": 2,
              "token": "01", "code": "2.04", "len": len(a), "oscore": True, "inner_code": "2.05", "payload": 17,
              "req": {"code": "GET", "path": "/kb/q/pick-place", "query": "name=X"}}]
    before = {"Robot1": (len(fe), 1), "Robot2": (0, 0)}
    end = {"Robot1": (len(fe) + len(fq), 2), "Robot2": (len(fa), 1)}
    _write_run(tmp_path / "exact", before=before, end=end, frames=frames, lines=lines)
    run = bb.load_run(tmp_path / "exact")
    assert run.exact and [d.kind for d in run.datagrams] == ["query", "answer"]
    assert run.counted == {"Robot1": (len(fq), 1), "Robot2": (len(fa), 1)}
    e = bb.explained(run)
    assert e["robots_explained_pct"] == 100.0 and e["untraced_protected"] == 0 and e["unmatched_trace_lines"] == 0
    answer = run.datagrams[1]
    assert answer.parts["payload"] == 17 and answer.parts["inner_options"] == 30 - bb.AEAD_TAG - 17
    # Counters that do not add up to the frames: the readings' times decide.
    _write_run(tmp_path / "approx", before={"Robot1": (1, 1), "Robot2": (0, 0)}, end=end, frames=frames, lines=lines)
    run = bb.load_run(tmp_path / "approx")
    assert not run.exact and [d.kind for d in run.datagrams] == ["query", "answer"]


def _minimal_run(tasks: int = 2) -> bb.Run:
    fact = {"code": "2.05", "payload": 80, "req": {"code": "GET", "path": "/kb/q/pick-facts", "query": "name=X"}}
    state = {"code": "2.05", "payload": 70, "observe": 0, "req": {"code": "GET", "path": "/robot/plan", "observe": 0}}
    post = {"code": "POST", "path": "/tasks", "query": "qh=1", "payload": 30}
    ds = []
    for i, (src, dst, plain, kind, detail) in enumerate([
        ("Robot2", "Robot1", fact, "answer", "pick-facts"), ("Robot2", "Robot1", fact, "answer", "pick-facts"),
        ("Robot2", "Robot3", fact, "answer", "pick-facts"), ("Robot1", "Robot2", state, "notification", "/robot/plan"),
        ("feeder", "Robot1", post, "task post", ""), ("feeder", "Robot1", post, "task post", ""),
    ]):
        d = _dg(float(i), src, 1, dst, 2, NON, CONTENT, i, bytes([i]), plain, delivered=float(i))
        d.plain, d.kind, d.detail = plain, kind, detail
        ds.append(d)
    return bb.Run("r", 2.0, True, tasks, ["Robot1", "Robot2", "Robot3"], {}, (0.0, 1.0), {}, ds)


def test_the_minimum_counts_each_fact_once_every_state_and_every_post() -> None:
    needs = {n.what: n for n in bb.minimum(_minimal_run(tasks=2))}
    assert needs["fact: pick-facts"].count == 2 and needs["fact: pick-facts"].payload == 80  # Robot1 once, Robot3
    assert needs["teammate's planned state"].count == 2 * 3 * 2 and needs["teammate's planned state"].payload == 70
    assert needs["task post"].count == 2 * 3 and needs["task post"].payload == 30
    one = needs["task post"]
    assert one.packets(True) == 6 and one.bytes(True) == 6 * (42 + bb.MIN_FRAMING_SECURE + 30)
    assert one.bytes(False) == 6 * (42 + bb.MIN_FRAMING_PLAIN + 30)
    big = bb.Need("fact: layout", 1, 3000.0)
    assert big.packets(True) == 3 and big.bytes(True) == 3 * (42 + bb.MIN_FRAMING_SECURE) + 3000


def test_tables_csv_round_trip_and_the_doc_sections(tmp_path: Path) -> None:
    run = _minimal_run()
    for d in run.datagrams:
        payload = (d.plain or {})["payload"]
        d.frame = 42 + 5 + 20 + payload
        d.parts = {"headers": 42, "coap": 5, "options": 0, "oscore": 20, "inner_options": 5, "payload": payload}
    run.counted = {"Robot1": (300, 3), "Robot2": (200, 2), "Robot3": (0, 0), "feeder": (100, 1)}
    settings = {"loss2": [run]}
    table = bb.budget_table([run])
    assert "| answer pick-facts | 1.5 |" in table and "| **total** | **3.0** |" in table
    bb.write_packets(settings, tmp_path / "p.csv")
    bb.write_runs(settings, tmp_path / "r.csv")
    again = bb.read_packets(tmp_path / "p.csv", tmp_path / "r.csv")
    assert bb.budget_table(again["loss2"]) == table
    assert bb.minimum_table(again) == bb.minimum_table(settings)
    assert bb.gap_table(again) == bb.gap_table(settings)
    assert bb.breakdown_table(again) == bb.breakdown_table(settings)
    assert "| **minimum** |" in bb.breakdown_table(settings)
    doc = "intro\n<!-- budget:gap -->\nold\n<!-- /budget:gap -->\nend\n"
    assert bb.replace_section(doc, "gap", "new\n") == "intro\n<!-- budget:gap -->\nnew\n<!-- /budget:gap -->\nend\n"
    with pytest.raises(ValueError):
        bb.replace_section(doc, "minimum", "x")


def tcp_frame(src: str, sport: int, dst: str, dport: int, flags: int, seq: int, payload: bytes = b"") -> bytes:
    """An Ethernet/IPv4/TCP frame with 12 bytes of TCP options (timestamps, as Linux sends them)."""
    tcp = (sport.to_bytes(2, "big") + dport.to_bytes(2, "big") + seq.to_bytes(4, "big") + b"\0\0\0\0"
           + bytes([(32 // 4) << 4, flags]) + b"\xff\xff\0\0\0\0" + b"\x01\x01\x08\x0a" + b"\0" * 8 + payload)
    return frame(src, 0, dst, 0, tcp, proto=6)


def test_tcp_segments_get_tcps_roles_and_data_retransmissions(tmp_path: Path) -> None:
    syn, ack, psh, fin = 0x02, 0x10, 0x18, 0x11
    frames = [tcp_frame("Robot1", 40000, "Robot2", 5555, syn, 1),
              tcp_frame("Robot1", 40000, "Robot2", 5555, psh, 2, b"z" * 60),
              tcp_frame("Robot2", 5555, "Robot1", 40000, ack, 9),
              tcp_frame("Robot1", 40000, "Robot2", 5555, psh, 2, b"z" * 60),
              tcp_frame("Robot1", 40000, "Robot2", 5555, fin, 62)]
    sent, others = bb.datagrams_from_capture(
        [CapturedFrame(float(i), "p-x", "in", f) for i, f in enumerate(frames)], HOSTS)
    assert not others and all(d.tcp is not None for d in sent)
    bb.classify(sent)
    assert [(d.kind, d.copy) for d in sent] == [("TCP handshake", "first"), ("TCP data", "first"),
                                               ("TCP ACK", "first"), ("TCP data", "retransmission"),
                                               ("TCP close", "first")]
    assert sent[1].parts["headers"] == 14 + 20 + 32 and sent[1].parts["payload"] == 60
    assert sum(sent[1].parts[p] for p in ("headers", "coap", "options", "oscore", "payload")) == sent[1].frame
    run = bb.Run("z", 2.0, True, 1, ["Robot1", "Robot2"], {}, (0.0, 1.0), {}, sent)
    assert "Eth+IP+TCP" in bb.budget_table([run]) and bb.minimum(run) == []
    assert bb.gap_table({"zmq": [run]}).count("\n") == 2  # the head only: no minimum without plaintext
    run.counted = {"Robot1": (1, 1), "Robot2": (1, 1)}
    bb.write_packets({"zmq": [run]}, tmp_path / "p.csv")
    bb.write_runs({"zmq": [run]}, tmp_path / "r.csv")
    again = bb.read_packets(tmp_path / "p.csv", tmp_path / "r.csv")["zmq"]
    assert bb.budget_table(again) == bb.budget_table([run])
    assert "same TCP sequence number" in bb.budget_table(again)
