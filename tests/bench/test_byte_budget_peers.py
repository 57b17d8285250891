"""experiments/byte_budget_peers.py and the peers' path through
experiments/byte_budget.py: QUIC headers and frames, RTPS submessages,
IPv4 fragments, the rows, tables and CSV of the comparison (crafted bytes,
and small loopback captures of each peer in data/peers/; no root)."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path
from typing import Any

import dpkt
import pytest
from support import require

from coapkb.bench.linkemu.capture import CapturedFrame
from experiments import byte_budget as bb

pp = bb.peers

HOSTS = {"10.77.0.1": "Robot1", "10.77.0.2": "Robot2", "10.77.0.3": "Robot3", "10.77.0.4": "feeder"}
IP = {name: ip for ip, name in HOSTS.items()}


def ip_frame(src: str, dst: str, body: bytes, *, proto: int = 17, ident: int = 0, more: bool = False,
             offset: int = 0) -> bytes:
    word = (0x2000 if more else 0) | (offset // 8)
    ip = (bytes([0x45, 0]) + (20 + len(body)).to_bytes(2, "big") + ident.to_bytes(2, "big") + word.to_bytes(2, "big")
          + bytes([64, proto]) + b"\0\0" + bytes(int(x) for x in IP[src].split("."))
          + bytes(int(x) for x in IP[dst].split(".")))
    return b"\x02" * 12 + b"\x08\x00" + ip + body


def udp_frame(src: str, sport: int, dst: str, dport: int, payload: bytes) -> bytes:
    udp = sport.to_bytes(2, "big") + dport.to_bytes(2, "big") + (8 + len(payload)).to_bytes(2, "big") + b"\0\0"
    return ip_frame(src, dst, udp + payload)


def needs_tshark() -> None:
    """RTPS is dissected by Wireshark's dissector, run as tshark (`make test` installs it)."""
    require(shutil.which("tshark") is not None, "tshark is not installed (Debian: tshark)")


def dg(t: float, src: str, dst: str, payload: bytes, sport: int = 7447, dport: int = 40000,
       proto: str = "quic", lost: bool = False) -> Any:
    return bb.Datagram(t, src, dst, sport, dport, 42 + len(payload), 42, payload, proto=proto, lost=lost)


# --------------------------------------------------------------------------- QUIC


def v(n: int) -> bytes:
    """A QUIC variable-length integer."""
    if n < 64:
        return bytes([n])
    if n < 16384:
        return (0x4000 | n).to_bytes(2, "big")
    return (0x80000000 | n).to_bytes(4, "big")


def long_packet(kind: int, dcid: bytes, scid: bytes, pn: int, payload: bytes, token: bytes = b"") -> bytes:
    b0 = 0xC0 | (kind << 4)  # 1-byte packet number
    head = bytes([b0]) + (1).to_bytes(4, "big") + bytes([len(dcid)]) + dcid + bytes([len(scid)]) + scid
    if kind == 0:
        head += v(len(token)) + token
    return head + v(1 + len(payload)) + bytes([pn]) + payload


def short_packet(dcid: bytes, pn: int, payload: bytes) -> bytes:
    return bytes([0x41]) + dcid + pn.to_bytes(2, "big") + payload  # 2-byte packet number


def ack(largest: int) -> bytes:
    return b"\x02" + v(largest) + v(3) + v(0) + v(0)


def stream(sid: int, offset: int, data: bytes) -> bytes:
    return b"\x0e" + v(sid) + v(offset) + v(len(data)) + data


def crypto(offset: int, data: bytes) -> bytes:
    return b"\x06" + v(offset) + v(len(data)) + data


KEEP_ALIVE = (1).to_bytes(2, "little") + b"\x04"
FRAME = (5).to_bytes(2, "little") + b"\x05abcd"
C_CID, S_CID = b"\xcc" * 8, b"\x5e" * 4


def test_varints_and_frames_in_clear() -> None:
    assert pp.varint(v(37) + b"x", 0) == (37, 1) and pp.varint(v(15293), 0) == (15293, 2)
    assert pp.varint(v(494878333), 0) == (494878333, 4)
    with pytest.raises(ValueError):
        pp.varint(b"\x40", 0)
    frames = pp.parse_quic_frames(ack(7) + b"\x01" + stream(4, 300, b"hello") + crypto(0, b"\x01\x02") + b"\0" * 5
                                  + b"\x18" + v(1) + v(0) + bytes([8]) + b"c" * 8 + b"t" * 16 + b"\x1e")
    assert [(f.name, f.size) for f in frames] == [("ACK", 5), ("PING", 1), ("STREAM", 1 + 1 + 2 + 1 + 5),
                                                  ("CRYPTO", 1 + 1 + 1 + 2), ("PADDING", 5),
                                                  ("NEW_CONNECTION_ID", 1 + 1 + 1 + 1 + 8 + 16),
                                                  ("HANDSHAKE_DONE", 1)]
    s = frames[2]
    assert (s.stream, s.offset, s.data, s.chunk) == (4, 300, 5, b"hello")
    with pytest.raises(ValueError):
        pp.parse_quic_frames(b"\x3f")  # no such frame type
    with pytest.raises(ValueError):
        pp.parse_quic_frames(stream(0, 0, b"abc")[:-1])  # its data cut short


def test_long_headers_coalesced_and_short_headers_in_clear() -> None:
    initial = long_packet(0, S_CID, C_CID, 0, crypto(0, b"\x02" * 90) + ack(0), token=b"")
    handshake = long_packet(2, S_CID, C_CID, 0, crypto(0, b"\x0b" * 200))
    one_rtt = short_packet(S_CID, 1, ack(3))
    packets = pp.parse_quic_datagram(initial + handshake + one_rtt, dcid_len=4, plaintext=True)
    assert [(p.type, p.size) for p in packets] == [("Initial", len(initial)), ("Handshake", len(handshake)),
                                                   ("1-RTT", len(one_rtt))]
    # Initial: flags 1, version 4, DCID 1+4, SCID 1+8, token length 1, Length 2, packet number 1.
    assert packets[0].header == 1 + 4 + 5 + 9 + 1 + 2 + 1 and packets[0].dcid == S_CID and packets[0].scid == C_CID
    assert packets[2].header == 1 + 4 + 2 and packets[2].number == 1
    assert [f.name for f in packets[0].frames or []] == ["CRYPTO", "ACK"]
    retry = bytes([0xF0]) + (1).to_bytes(4, "big") + bytes([4]) + S_CID + bytes([8]) + C_CID + b"tok" + b"\0" * 16
    assert [(p.type, p.protected) for p in pp.parse_quic_datagram(retry)] == [("Retry", 3 + 16)]
    with pytest.raises(ValueError):
        pp.parse_quic_datagram(bytes([0xC0]) + (0x1234).to_bytes(4, "big") + b"\0\0")  # not a QUIC version
    with pytest.raises(ValueError):
        pp.parse_quic_datagram(initial[:-1] + b"", plaintext=True)[0].frames  # noqa: B018 - Length past the datagram


def test_protected_packets_keep_their_number_frames_and_tag_hidden() -> None:
    sealed = short_packet(C_CID, 9, b"\x99" * 40)
    [p] = pp.parse_quic_datagram(sealed, dcid_len=8)
    assert (p.type, p.header, p.protected, p.frames, p.number) == ("1-RTT", 9, len(sealed) - 9, None, None)
    d = dg(1.0, "Robot1", "Robot2", sealed)
    pp.classify_quic([d], plaintext=False)  # no long header seen: an 8-byte DCID, as quinn's
    assert d.kind == "QUIC 1-RTT small" and d.parts["crypto"] == pp.QUIC_TAG
    assert d.parts["encrypted"] == len(sealed) - 9 - pp.QUIC_TAG and sum(d.parts.values()) == d.frame
    big = dg(1.1, "Robot1", "Robot2", short_packet(C_CID, 10, b"\x99" * 400))
    pp.classify_quic([big], plaintext=False)
    assert big.kind == "QUIC 1-RTT large"


def test_quic_datagrams_by_frames_with_the_short_headers_dcid_learnt_and_data_sent_again() -> None:
    client, server = ("Robot1", 40000), ("Robot2", 7447)

    def c2s(t: float, payload: bytes) -> Any:
        return dg(t, client[0], server[0], payload, client[1], server[1])

    def s2c(t: float, payload: bytes) -> Any:
        return dg(t, server[0], client[0], payload, server[1], client[1])

    init = long_packet(0, b"\x11" * 16, C_CID, 0, crypto(0, b"\x01" * 60) + b"\0" * 900)
    sent = [
        c2s(0.0, init),
        s2c(0.1, long_packet(0, C_CID, S_CID, 0, crypto(0, b"\x02" * 90) + ack(0))
            + long_packet(2, C_CID, S_CID, 0, crypto(0, b"\x0b" * 300))),
        c2s(0.2, long_packet(2, S_CID, C_CID, 0, crypto(0, b"\x14" * 36) + ack(0))),
        c2s(0.3, short_packet(S_CID, 1, stream(0, 0, (3).to_bytes(2, "little") + b"\x01ab"))),   # Zenoh INIT
        s2c(0.4, short_packet(C_CID, 1, b"\x1e" + ack(1))),                                       # HANDSHAKE_DONE
        c2s(0.5, short_packet(S_CID, 2, stream(0, 5, FRAME))),
        c2s(0.9, short_packet(S_CID, 3, stream(0, 5, FRAME))),                                   # sent again
        s2c(1.0, short_packet(C_CID, 2, ack(3))),
        c2s(3.5, short_packet(S_CID, 4, stream(0, 12, KEEP_ALIVE) + ack(2))),
        s2c(3.6, short_packet(C_CID, 3, b"\x01")),
        s2c(3.7, short_packet(C_CID, 4, b"\x1c" + v(0) + v(0) + v(2) + b"by")),
    ]
    sent[-1].lost = True
    pp.classify_quic(sent, plaintext=True)
    assert [(d.kind, d.copy) for d in sent] == [
        ("QUIC Initial", "first"), ("QUIC Initial", "first"), ("QUIC Handshake", "first"),
        ("QUIC 1-RTT Zenoh session set-up", "first"), ("QUIC 1-RTT control", "first"),
        ("QUIC 1-RTT stream data", "first"), ("QUIC 1-RTT stream data", "retransmission"),
        ("QUIC 1-RTT ACK only", "first"), ("QUIC 1-RTT Zenoh keep-alive", "first"), ("QUIC 1-RTT PING", "first"),
        ("QUIC 1-RTT close", "first")]
    assert sent[1].detail == "Initial+Handshake" and sent[6].quic_again == len(FRAME)
    for d in sent:
        assert sum(d.parts.values()) == d.frame, d.kind
    five = sent[5].parts
    # A short header's DCID is the receiver's own connection id, learnt from its long headers.
    assert five["payload"] == len(FRAME) and five["transport"] == 1 + len(S_CID) + 2 + (1 + 1 + 1 + 1)
    assert sent[0].parts["control"] == 900 and sent[0].parts["crypto"] == 1 + 1 + 1 + 60
    rows = pp.quic_packet_table(sent, 1)
    assert {r["type"]: r["packets"] for r in rows} == {"Initial": 2, "Handshake": 2, "1-RTT": 8}
    assert {r["type"]: r.get("coalesced", 0) for r in rows} == {"Initial": 1, "Handshake": 1, "1-RTT": 0}
    c = pp.quic_connections(sent)
    assert c["connections"] == 1 and c["long_packets_per_connection"] == 4 and c["coalesced_datagrams"] == 1
    assert pp.size_bins(sent) == {"<= 48": 8}
    idle = pp.idle_gaps(sent)
    assert idle["idle_datagrams"] == 1 and idle["gap_list"] == [pytest.approx(2.5, abs=0.2), pytest.approx(2.6)]


# --------------------------------------------------------------------------- RTPS

PREFIX_A, PREFIX_B = b"\xaa" * 12, b"\xbb" * 12
REQUEST_WRITER, REPLY_WRITER = 0x00000103, 0x00000203


def rtps(prefix: bytes, *subs: bytes) -> bytes:
    return b"RTPS" + bytes([2, 1]) + b"\x01\x10" + prefix + b"".join(subs)


def sub(sid: int, flags: int, body: bytes, length: int | None = None) -> bytes:
    return bytes([sid, flags | 0x01]) + struct.pack("<H", len(body) if length is None else length) + body


def data(writer: int, sn: int, payload: bytes, reader: int = 0, flags: int = 0x04, qos: bytes = b"") -> bytes:
    body = (b"\0\0" + struct.pack("<H", 16) + reader.to_bytes(4, "big") + writer.to_bytes(4, "big")
            + struct.pack("<iI", 0, sn) + qos + payload)
    return sub(0x15, flags | (0x02 if qos else 0), body)


def sample(client: str, token: int, body: bytes) -> bytes:
    """A Request/Reply sample in XCDR1, little-endian (as the ``body`` length check expects)."""
    s = client.encode() + b"\0"
    out = struct.pack("<I", len(s)) + s
    out += b"\0" * (-len(out) % 8) + struct.pack("<Q", token) + struct.pack("<I", len(body)) + body
    pad = -len(out) % 4
    return b"\x00\x01\x00" + bytes([pad]) + out + b"\0" * pad


def sedp(writer_prefix: bytes, writer: int, topic: str) -> bytes:
    name = topic.encode() + b"\0"
    value = struct.pack("<I", len(name)) + name
    value += b"\0" * (-len(value) % 4)
    params = (struct.pack("<HH", 0x005A, 16) + writer_prefix + writer.to_bytes(4, "big")
              + struct.pack("<HH", 0x0005, len(value)) + value + struct.pack("<HH", 0x0001, 0))
    return data(0x000003C2, 1, b"\x00\x03\x00\x00" + params, reader=0x000003C7)


def heartbeat(writer: int, last: int) -> bytes:
    return sub(0x07, 0, (0).to_bytes(4, "big") + writer.to_bytes(4, "big") + struct.pack("<iIiIi", 0, 1, 0, last, 1))


def acknack(reader: int, writer: int, base: int) -> bytes:
    return sub(0x06, 0, reader.to_bytes(4, "big") + writer.to_bytes(4, "big") + struct.pack("<iIIi", 0, base, 0, 1))


INFO_TS = sub(0x09, 0, b"\x01" * 8)


def info_dst(prefix: bytes) -> bytes:
    return sub(0x0E, 0, prefix)


def test_rtps_header_and_submessages() -> None:
    needs_tshark()
    body = b"\xa1\x02coapkb"
    # The last submessage may say length 0 (it runs to the end of the message), but Wireshark 4.0 takes that
    # for an error in a DATA, and so does the budget (Cyclone DDS always sets the length).
    last = rtps(PREFIX_A, sub(0x15, 0x04, (b"\0\0" + struct.pack("<H", 16) + b"\0" * 16) + b"xyz", length=0))
    # Inline QoS (up to its sentinel) is framing, not payload.
    qos = struct.pack("<HHI", 0x0071, 4, 3) + struct.pack("<HH", 0x0001, 0)
    # INFO_SRC: the submessages after it are another participant's.
    info_src = sub(0x0C, 0, b"\0" * 4 + bytes([2, 1]) + b"\x01\x10" + PREFIX_B)
    msg, last_msg, unreg_msg, not_rtps, past_the_end, relayed = pp.rtps_messages([
        rtps(PREFIX_A, INFO_TS, info_dst(PREFIX_B), data(REQUEST_WRITER, 7, sample("c-1", 5, body)),
             heartbeat(REQUEST_WRITER, 7)),
        last, rtps(PREFIX_A, data(REQUEST_WRITER, 8, b"", flags=0, qos=qos)),
        b"RTPX" + b"\0" * 16, rtps(PREFIX_A, sub(0x07, 0, b"\0" * 28, length=40)),
        rtps(PREFIX_A, info_src, heartbeat(REPLY_WRITER, 3))])
    assert relayed is not None
    assert [(s.name, s.size, s.source) for s in relayed.submessages] == [("INFO_SRC", 24, PREFIX_A),
                                                                      ("HEARTBEAT", 32, PREFIX_B)]
    assert msg is not None and unreg_msg is not None and last_msg is None
    assert msg.guid_prefix == PREFIX_A and msg.version == (2, 1) and msg.vendor == 0x0110
    assert [(s.name, s.size) for s in msg.submessages] == [
        ("INFO_TS", 12), ("INFO_DST", 16), ("DATA", 4 + 20 + len(sample("c-1", 5, body))), ("HEARTBEAT", 32)]
    d = msg.submessages[2]
    assert (d.writer, d.sn, d.source, d.dest) == (REQUEST_WRITER, 7, PREFIX_A, PREFIX_B)
    assert pp.user_sample_body(d.payload) == len(body) and not d.key_only
    assert pp.entity_category(0x000100C2) == "SPDP" and pp.entity_category(0x000004C7) == "SEDP subscriptions"
    assert pp.entity_category(REQUEST_WRITER) == "user" and pp.entity_category(0x000001C1) == "other builtin"
    unreg = unreg_msg.submessages[0]
    assert unreg.inline_qos == len(qos) and unreg.key_only and unreg.payload == b""
    assert not_rtps is None and past_the_end is None


def test_rtps_datagrams_discovery_or_user_data_request_or_reply_and_data_sent_again() -> None:
    needs_tshark()
    # Robot2 (PREFIX_B) serves; Robot1's client participant (PREFIX_A) asks.
    spdp = rtps(PREFIX_A, INFO_TS, data(0x000100C2, 1, b"\x00\x03\x00\x00" + b"\x01\x00\x00\x00"))
    pub_a = rtps(PREFIX_A, INFO_TS, sedp(PREFIX_A, REQUEST_WRITER, "coapkb/7400/request"), heartbeat(0x000003C2, 1))
    pub_b = rtps(PREFIX_B, INFO_TS, sedp(PREFIX_B, REPLY_WRITER, "coapkb/7400/reply"))
    req = rtps(PREFIX_A, info_dst(PREFIX_B), INFO_TS,
               data(REQUEST_WRITER, 1, sample("coapkb-0123", 9, b"q" * 30)))
    rep = rtps(PREFIX_B, info_dst(PREFIX_A), INFO_TS, data(REPLY_WRITER, 1, sample("coapkb-0123", 9, b"a" * 50)),
               heartbeat(REPLY_WRITER, 1))
    nack = rtps(PREFIX_A, info_dst(PREFIX_B), acknack(0x00000204, REPLY_WRITER, 2))
    part = rtps(PREFIX_A, heartbeat(0x000200C2, 3))
    both = rtps(PREFIX_A, data(0x000100C2, 2, b"\x00\x03\x00\x00"), data(REQUEST_WRITER, 2, sample("c", 1, b"")))
    sent = [dg(0.0, "Robot1", "Robot2", spdp, 40001, 7400, "rtps"), dg(0.1, "Robot1", "Robot2", pub_a, 40002, 7401, "rtps"),
            dg(0.2, "Robot2", "Robot1", pub_b, 7401, 40002, "rtps"), dg(1.0, "Robot1", "Robot2", req, 40002, 7401, "rtps"),
            dg(1.1, "Robot2", "Robot1", rep, 7401, 40002, "rtps"), dg(1.2, "Robot1", "Robot2", nack, 40002, 7401, "rtps"),
            dg(1.3, "Robot2", "Robot1", rep, 7401, 40002, "rtps"), dg(1.4, "Robot1", "Robot2", part, 40002, 7401, "rtps"),
            dg(1.5, "Robot1", "Robot2", both, 40002, 7401, "rtps"),
            dg(1.6, "Robot1", "Robot2", b"not rtps at all....", 40002, 7401, "rtps")]
    pp.classify_rtps(sent)
    assert [(d.kind, d.copy) for d in sent] == [
        ("RTPS SPDP DATA", "first"), ("RTPS SEDP publications DATA", "first"), ("RTPS SEDP publications DATA", "first"),
        ("RTPS request DATA", "first"), ("RTPS reply DATA", "first"), ("RTPS reply ACKNACK", "first"),
        ("RTPS reply DATA", "retransmission"), ("RTPS participant message HEARTBEAT", "first"),
        ("RTPS mixed DATA", "first"), ("other", "first")]
    assert sent[4].detail == "INFO_DST+INFO_TS+DATA+HEARTBEAT"
    for d in sent:
        assert sum(d.parts.values()) == d.frame, d.kind
    assert sent[3].parts["payload"] == 30 and sent[4].parts["payload"] == 50 and sent[4].parts["acks"] == 32
    assert sent[5].parts["acks"] == 4 + 24 and sent[5].parts["transport"] == 20 + 16
    assert sent[1].parts["payload"] == len(sent[1].rtps.submessages[1].payload)  # a parameter list, whole
    rows = {(r["endpoint"], r["submessage"]): r for r in pp.submessage_rows(sent, 1)}
    assert rows[("user", "DATA")]["count"] == 4 and rows[("(all)", "RTPS header")]["count"] == 9
    assert rows[("SEDP publications", "HEARTBEAT")]["bytes"] == 32
    assert rows[("(interpreter)", "INFO_TS")]["count"] == 6
    groups = [pp.compare_group(d.kind) for d in sent]
    assert groups[:8] == ["set-up and discovery"] * 3 + ["messages", "messages", "acknowledgements and keep-alives",
                                                        "messages", "acknowledgements and keep-alives"]


def test_ip_fragments_of_one_rtps_datagram_are_reassembled_and_its_bytes_add_up() -> None:
    needs_tshark()
    big = rtps(PREFIX_B, INFO_TS, data(REPLY_WRITER, 4, sample("coapkb-0123", 9, b"s" * 2000)))
    udp = (7401).to_bytes(2, "big") + (40002).to_bytes(2, "big") + (8 + len(big)).to_bytes(2, "big") + b"\0\0" + big
    cut = 1480
    f1 = ip_frame("Robot2", "Robot1", udp[:cut], ident=77, more=True)
    f2 = ip_frame("Robot2", "Robot1", udp[cut:], ident=77, offset=cut)
    lone = ip_frame("Robot2", "Robot1", b"\0" * 100, ident=78, offset=1480)  # its first never seen
    frames = [CapturedFrame(1.0, "p-Robot2", "in", f1), CapturedFrame(1.001, "p-Robot2", "in", f2),
              CapturedFrame(1.01, "p-Robot1", "out", f1), CapturedFrame(2.0, "p-Robot2", "in", lone)]
    sent, others = bb.datagrams_from_capture(frames, HOSTS, "rtps")
    assert not others and len(sent) == 3
    head, tail, orphan = sent
    assert head.data == big and head.whole and head.fragments == 1 and tail.fragment_of is head
    assert not head.lost and tail.lost and not orphan.whole
    bb.classify(sent, [], "rtps")
    assert head.kind == tail.kind == "RTPS data DATA" and orphan.kind == "IP fragment"
    assert head.parts["payload"] == 2000
    assert sum(sum(d.parts.values()) for d in sent) == sum(d.frame for d in sent)
    assert tail.parts == dict.fromkeys(pp.PEER_PARTS, 0) | {"headers": 34}


# --------------------------------------------------------------------------- rows, tables, CSV


def _write_run(directory: Path, transport: str, system: str, frames: list[CapturedFrame],
               counted: dict[str, tuple[int, int]]) -> None:
    directory.mkdir()
    (directory / "capture.jsonl").write_text("".join(json.dumps(
        {"t": f.t, "port": f.port, "dir": f.direction, "frame": f.frame.hex()}) + "\n" for f in frames), encoding="utf-8")
    zero = {h: {"tx_bytes": 0, "tx_packets": 0} for h in counted}
    end = {h: {"tx_bytes": b, "tx_packets": p} for h, (b, p) in counted.items()}
    meta = {"row": {"loss_pct": 2.0, "security": "none", "tasks": 1, "wire_bytes": sum(b for b, _ in counted.values()),
                    "system": system, "transport": transport, "ok": True, "wire_packets": 0, "completion_s": 1.0},
            "hosts": {h: IP[h] for h in counted},
            "readings": [{"t0": 0.0, "t1": 0.5, "counters": zero}, {"t0": 20.0, "t1": 20.5, "counters": end}]}
    (directory / "run.json").write_text(json.dumps(meta), encoding="utf-8")


def test_a_dds_run_directory_is_read_as_rtps_and_its_rows_tables_and_csv(tmp_path: Path) -> None:
    needs_tshark()
    req = rtps(PREFIX_A, info_dst(PREFIX_B), data(REQUEST_WRITER, 1, sample("c", 1, b"q" * 10)))
    rep = rtps(PREFIX_B, info_dst(PREFIX_A), data(REPLY_WRITER, 1, sample("c", 1, b"a" * 20)))
    fq, fa = udp_frame("Robot1", 40002, "Robot2", 7401, req), udp_frame("Robot2", 7401, "Robot1", 40002, rep)
    frames = [CapturedFrame(1.0, "p-Robot1", "in", fq), CapturedFrame(1.01, "p-Robot2", "out", fq),
              CapturedFrame(1.1, "p-Robot2", "in", fa)]
    _write_run(tmp_path / "dds", "dds", "dds-distributed", frames,
               {"Robot1": (len(fq), 1), "Robot2": (len(fa), 1)})
    run = bb.load_run(tmp_path / "dds")
    assert run.udp == "rtps" and run.exact and run.system == "dds-distributed"
    assert [d.kind for d in run.datagrams] == ["RTPS data DATA", "RTPS data DATA"]  # no SEDP seen: no topic
    assert run.datagrams[1].lost and bb.explained(run)["all_explained_pct"] == 100.0
    rows = pp.setting_rows("dds-distributed-loss2-insecure", [run], bb._kind_label)
    total = next(r for r in rows if r["table"] == "total")
    assert total["bytes"] == len(fq) + len(fa) and total["packets"] == 2 and total["lost"] == 1
    assert total["payload"] == 30 and sum(total[p] for p in pp.PEER_PARTS) == total["bytes"]
    pp.write_rows(rows, tmp_path / "p.csv")
    again = pp.read_rows(tmp_path / "p.csv")
    assert pp.kind_table(again) == pp.kind_table(rows) and "| RTPS data DATA | 2.0 |" in pp.kind_table(rows)
    assert "serialized payload" in pp.rtps_table(rows)
    bb.write_peer_runs({"dds-distributed-loss2-insecure": [run]}, tmp_path / "r.csv")
    text = (tmp_path / "r.csv").read_text(encoding="utf-8")
    assert "dds-distributed" in text and ",1," in text


def test_the_comparison_sets_each_peer_against_coap_at_the_same_loss_and_security() -> None:
    def setting(name: str, system: str, security: str, nbytes: int, kinds: dict[str, int]) -> list[dict[str, Any]]:
        common = {"setting": name, "system": system, "loss_pct": 2.0, "security": security, "runs": 1, "ok": 1,
                  "tasks": 10}
        zero = dict.fromkeys(pp.PEER_PARTS, 0.0)
        out = [{**common, **zero, "table": "total", "name": "total", "packets": 10.0, "lost": 0.0, "bytes": nbytes,
                "headers": 420.0, "payload": nbytes - 420.0}]
        out += [{**common, **zero, "table": "group", "name": pp.compare_group(k), "packets": 1.0, "lost": 0.0,
                 "bytes": float(b)} for k, b in kinds.items()]
        return out

    rows = (setting("loss2", "coap-distributed", "oscore", 1000, {"empty ACK": 100})
            + setting("loss2-insecure", "coap-distributed", "none", 800, {"EDHOC message_1": 0})
            + setting("zenoh-udp-distributed-loss2-insecure", "zenoh-udp-distributed", "none", 2000,
                      {"QUIC 1-RTT ACK only": 300})
            + setting("zenoh-quic-distributed-loss2", "zenoh-quic-distributed", "tls", 3000, {"QUIC Initial": 50}))
    table = pp.compare_table(rows)
    assert "| zenoh-udp-distributed-loss2-insecure | none | 1/1 | 200 | 2.50 |" in table
    assert "| zenoh-quic-distributed-loss2 | tls | 1/1 | 300 | 3.00 |" in table
    assert "| loss2 | oscore | 1/1 | 100 | 1.00 | 1.0 | 0.0 | 0.0 | 10 |" in table
    assert pp.compare_group("TCP ACK") == "acknowledgements and keep-alives"
    assert pp.compare_group("query pick-facts") == "messages" and pp.compare_group("EDHOC message_2") == "set-up and discovery"


def test_coap_parts_map_onto_the_peers_parts() -> None:
    d = bb.Datagram(0.0, "Robot1", "Robot2", 1, 2, 100, 42, b"")
    d.kind, d.parts = "query", {"headers": 42, "coap": 5, "options": 2, "oscore": 20, "inner_options": 9, "payload": 31}
    assert pp.peer_parts(d) == {"headers": 42, "transport": 16, "acks": 0, "crypto": 11, "control": 0, "encrypted": 0,
                                "payload": 31}
    d.kind, d.parts = "empty ACK", {"headers": 42, "coap": 4, "options": 0, "oscore": 0, "inner_options": 0,
                                    "payload": 0}
    assert pp.peer_parts(d)["acks"] == 4 and sum(pp.peer_parts(d).values()) == 46


def test_peers_mode_reads_kept_runs_and_prints_their_tables(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    init = long_packet(0, b"\x11" * 8, C_CID, 0, crypto(0, b"\x01" * 60) + b"\0" * 100)
    data_ = short_packet(S_CID, 1, stream(0, 0, FRAME) + ack(1))
    f1, f2 = udp_frame("Robot1", 40000, "Robot2", 7447, init), udp_frame("Robot1", 40000, "Robot2", 7447, data_)
    frames = [CapturedFrame(0.1, "p-Robot1", "in", f1), CapturedFrame(1.0, "p-Robot1", "in", f2),
              CapturedFrame(1.01, "p-Robot2", "out", f2)]
    _write_run(tmp_path / "udp", "zenoh+udp", "zenoh-udp-distributed", frames, {"Robot1": (len(f1) + len(f2), 2)})
    meta = json.loads((tmp_path / "udp" / "run.json").read_text(encoding="utf-8"))
    meta["readings"][0]["counters"]["Robot1"] = {"tx_bytes": len(f1), "tx_packets": 1}  # the Initial came before
    (tmp_path / "udp" / "run.json").write_text(json.dumps(meta), encoding="utf-8")
    assert bb.main(["--peers", "--read", str(tmp_path / "udp"), "--no-csv"]) == 0
    out = capsys.readouterr().out
    assert "## peers-kinds-zenoh-udp-distributed-loss2-insecure" in out and "## peers-explained" in out
    # The server's long headers were not seen: its connection id's length is the one whose frames parse.
    assert "| QUIC 1-RTT stream data | 1.0 |" in out
    # In the window only the 1-RTT packet; the connection's Initial came before, in the whole capture.
    assert "| 1-RTT | 1.0 |" in out and "| Initial |" not in out
    assert "| 1.0 | 1.0 | 232 | 0.0 | 0.0 | 1 of 1 | 0.0 |" in out


def tcp(t: float, src: str, dst: str, flags: int, seq: int, payload: bytes = b"") -> Any:
    d = bb.Datagram(t, src, dst, 40000 if src == "Robot1" else 7447, 7447 if src == "Robot1" else 40000,
                    66 + len(payload), 66, payload, tcp=(flags, seq), proto="tcp")
    return d


def test_tls_records_over_tcp_are_split_into_headers_tags_and_data() -> None:
    hello = bytes([22, 3, 1]) + (100).to_bytes(2, "big") + b"h" * 100
    app = bytes([23, 3, 3]) + (60).to_bytes(2, "big") + b"z" * 43 + b"\x17" + b"t" * 16
    stream_ = hello + app
    isn = 1000
    first, second = stream_[:130], stream_[130:]
    sent = [tcp(0.0, "Robot1", "Robot2", 0x02, isn), tcp(0.1, "Robot1", "Robot2", 0x18, isn + 1, first),
            tcp(0.2, "Robot1", "Robot2", 0x18, isn + 1 + 130, second),
            tcp(0.9, "Robot1", "Robot2", 0x18, isn + 1 + 130, second),                       # sent again
            tcp(1.0, "Robot2", "Robot1", 0x18, 5, b"\xff" + b"\0" * 9 + b"\x7f")]            # ZMTP: not TLS
    bb.classify(sent)
    assert [(d.kind, d.copy) for d in sent] == [("TCP handshake", "first"), ("TCP data", "first"),
                                               ("TCP data", "first"), ("TCP data", "retransmission"),
                                               ("TCP data", "first")]
    a, b, c, z = (d.parts for d in sent[1:])
    assert a == dict.fromkeys(pp.PEER_PARTS, 0) | {"headers": 66, "transport": 5 + 5, "crypto": 100, "payload": 20}
    assert b == c == dict.fromkeys(pp.PEER_PARTS, 0) | {"headers": 66, "payload": 43 - 20, "crypto": 17}
    assert "crypto" not in z and pp.peer_parts(sent[4])["payload"] == 11
    for d in sent:
        assert sum(pp.peer_parts(d).values()) == d.frame


# --------------------------------------------------------------------------- real captures

PEER_CAPTURES = Path(__file__).parent / "data" / "peers"
#: Each capture's UDP protocol (byte_budget.UDP_PROTOCOL's names); Zenoh over TLS is TCP.
CAPTURE_UDP = {"zenoh-udp": "quic-plain", "zenoh-quic": "quic", "zenoh-tls": "coap", "dds": "rtps"}


def classified(name: str) -> list[Any]:
    """A capture of data/peers/ (made by make_peer_captures.py) read and
    classified as the budget reads a run's: every frame one a host sent."""
    with (PEER_CAPTURES / f"{name}.pcap").open("rb") as f:
        frames = [CapturedFrame(t, "lo", "in", bytes(buf)) for t, buf in dpkt.pcap.Reader(f)]
    sent, others = bb.datagrams_from_capture(frames, {"127.0.0.1": "lo"}, CAPTURE_UDP[name])
    assert not others
    bb.classify(sent, others, CAPTURE_UDP[name])
    return sent


def summary(datagrams: list[Any]) -> dict[str, Any]:
    """What the budget's tables are made of: each datagram's kind, detail,
    copy, stream bytes sent again and parts; the RTPS submessages and QUIC
    packets by type."""
    out = {"datagrams": [[d.kind, d.detail, d.copy, d.quic_again, [pp.peer_parts(d)[p] for p in pp.PEER_PARTS]]
                         for d in datagrams],
           "rtps-submessages": pp.submessage_rows(datagrams, 1), "quic-packets": pp.quic_packet_table(datagrams, 1)}
    return json.loads(json.dumps(out))


@pytest.mark.parametrize("name", CAPTURE_UDP)
def test_each_real_capture_is_classified_as_the_hand_written_dissectors_did(name: str) -> None:
    """data/peers/NAME.json: the classification of NAME.pcap by the budget's
    hand-written dissectors (QUIC, TLS records, RTPS, Ethernet/IPv4/UDP/TCP)
    before the kept ones replaced those that one covers; the same, datagram by datagram."""
    if CAPTURE_UDP[name] == "rtps":
        needs_tshark()
    expected = json.loads((PEER_CAPTURES / f"{name}.json").read_text(encoding="utf-8"))
    got = summary(classified(name))
    assert len(got["datagrams"]) == len(expected["datagrams"])
    for i, (g, e) in enumerate(zip(got["datagrams"], expected["datagrams"])):
        assert g == e, f"datagram {i + 1}"
    assert got == expected
