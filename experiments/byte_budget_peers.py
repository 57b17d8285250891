"""The byte budget of the peers of 2026: QUIC (Zenoh over QUIC and over its
reliable UDP) and RTPS (DDS), from the packets alone.

A sibling of ``experiments/byte_budget.py``, which runs, captures and joins
(and reads Ethernet, IPv4, UDP and TCP with dpkt); this module tells what the
peers' datagrams hold:

* **QUIC** (RFC 9000): every UDP datagram split into its QUIC packets
  (several when coalesced), each by its header: long (Initial, 0-RTT,
  Handshake, Retry, version negotiation) or short (1-RTT).  Over Zenoh's
  ``quic/`` link the packets are protected (TLS 1.3 keys): the packet
  number, the frames and the 16-byte AEAD tag are opaque, so a 1-RTT
  packet is told by its size only, and a retransmission cannot be seen.
  Zenoh's reliable UDP (``udp/...?rel=1``) runs QUIC with packet and header
  protection replaced by no-ops (no tag, no header mask): its packet numbers
  and frames (ACK, STREAM, CRYPTO, PING, ...) are parsed, the STREAM data
  is Zenoh's own bytes, and stream data sent again is seen.
* **RTPS** (DDS-RTPS 2.x, plaintext): the 20-byte header and every
  submessage (DATA, DATA_FRAG, HEARTBEAT, ACKNACK, GAP, INFO_TS, INFO_DST,
  NACK_FRAG, HEARTBEAT_FRAG, PAD, INFO_SRC, ...), each put with the entity it
  concerns: discovery (the builtin SPDP, SEDP and participant-message
  endpoints) or user data (coapkb's request and reply topics, named from
  the SEDP announcements), and a DATA sent again to the same host seen as
  a retransmission.

Each datagram gets a kind (the budget's line) and its bytes split into
:data:`PEER_PARTS`, which add up to the frame.

Dissected by a kept dissector where one covers the protocol:

* RTPS, its parameter lists and their strings (SEDP's topic names):
  Wireshark's RTPS dissector, one tshark run over a capture's RTPS datagrams
  (:func:`rtps_messages`; Debian's ``tshark``, which ``make test`` installs);
* TLS records over TCP: dpkt's (``dpkt.ssl``).

Hand-written, because none covers them:

* QUIC headers and frames: Wireshark tries to decrypt Zenoh's reliable UDP (its no-op protection is not QUIC's) and finds it malformed, and on Zenoh's QUIC loses the short headers whose connection id came in an encrypted frame (half of them); dpkt has no QUIC.
* Zenoh's batches in QUIC stream data (:func:`zenoh_batches`): neither Wireshark 4.0 nor dpkt has a dissector of Zenoh.
* The sender's TCP stream that TLS records are read from: dpkt does not reassemble TCP, and tshark places records in the stream it reassembles, not in the segments the budget splits.
* coapkb's own sample in an RTPS DATA (:func:`user_sample_body`): a type of coapkb's, which no dissector knows.
"""

from __future__ import annotations

import os
import shutil
import statistics
import struct
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dpkt

#: A peer datagram's bytes, by part (they add up to the frame):
#: ``headers`` Ethernet, IPv4, UDP or TCP; ``transport`` the protocol's own
#: headers (QUIC packet headers, packet numbers where visible, STREAM frame
#: headers; RTPS header, INFO_* submessages, DATA framing: submessage header,
#: entity ids, sequence number, inline QoS, CDR encapsulation and key
#: fields); ``acks`` acknowledgements (QUIC ACK frames; RTPS HEARTBEAT,
#: ACKNACK, GAP, NACK_FRAG, HEARTBEAT_FRAG); ``crypto`` QUIC's AEAD tags
#: and its TLS handshake (CRYPTO frames); ``control`` what else (PADDING,
#: PING, flow control, connection ids; RTPS PAD and vendor submessages);
#: ``encrypted`` what protection hides (a protected QUIC packet's number and
#: frames, not told apart); ``payload`` what the application handed over
#: (STREAM data: Zenoh's bytes; an RTPS sample's coapkb body, or a
#: discovery sample's parameter list; a TCP segment's payload).
PEER_PARTS = ("headers", "transport", "acks", "crypto", "control", "encrypted", "payload")

#: UDP payloads up to this size are a protected QUIC 1-RTT packet "small":
#: an ACK-only packet, a PING, a keep-alive or a tiny message (the reliable
#: UDP runs, in clear, show what such packets hold).
QUIC_SMALL = 64
#: AEAD tag of QUIC's packet protection (AES-GCM, ChaCha20-Poly1305).
QUIC_TAG = 16
#: Silence on a flow after which the next packet counts as idle traffic.
IDLE_GAP_S = 1.0


def link_headers(d: Any) -> int:
    """Ethernet, IPv4 and UDP (and link padding) of datagram ``d``; its
    ``data`` may be longer than its frame holds (the whole of a datagram
    sent in IPv4 fragments, in its first)."""
    return d.headers + max(0, d.frame - d.headers - len(d.data))


# =========================================================================== QUIC

QUIC_LONG_TYPES = ("Initial", "0-RTT", "Handshake", "Retry")


def varint(buf: bytes, i: int) -> tuple[int, int]:
    """A QUIC variable-length integer at ``buf[i]``: (value, next index)."""
    if i >= len(buf):
        raise ValueError("varint past the end")
    first = buf[i]
    n = 1 << (first >> 6)
    if i + n > len(buf):
        raise ValueError("varint past the end")
    value = first & 0x3F
    for b in buf[i + 1:i + n]:
        value = (value << 8) | b
    return value, i + n


@dataclass
class QuicFrame:
    """One QUIC frame: its name and size; a STREAM's id, offset and data length."""

    name: str
    size: int
    stream: int | None = None
    offset: int = 0
    data: int = 0
    fin: bool = False
    #: A STREAM's or CRYPTO's data bytes (for Zenoh's message ids).
    chunk: bytes = b""


_SIMPLE_FRAMES = {0x10: ("MAX_DATA", 1), 0x11: ("MAX_STREAM_DATA", 2), 0x12: ("MAX_STREAMS", 1),
                  0x13: ("MAX_STREAMS", 1), 0x14: ("DATA_BLOCKED", 1), 0x15: ("STREAM_DATA_BLOCKED", 2),
                  0x16: ("STREAMS_BLOCKED", 1), 0x17: ("STREAMS_BLOCKED", 1), 0x19: ("RETIRE_CONNECTION_ID", 1),
                  0x04: ("RESET_STREAM", 3), 0x05: ("STOP_SENDING", 2)}


def parse_quic_frames(payload: bytes) -> list[QuicFrame]:
    """The frames of a plaintext QUIC packet payload; ValueError if they do
    not parse to its end."""
    frames: list[QuicFrame] = []
    i = 0
    while i < len(payload):
        start = i
        ftype, i = varint(payload, i)
        if ftype == 0x00:  # PADDING: a run of zero bytes is one frame here
            while i < len(payload) and payload[i] == 0:
                i += 1
            frames.append(QuicFrame("PADDING", i - start))
            continue
        if ftype == 0x01:
            frames.append(QuicFrame("PING", i - start))
        elif ftype in (0x02, 0x03):
            _largest, i = varint(payload, i)
            _delay, i = varint(payload, i)
            ranges, i = varint(payload, i)
            _first, i = varint(payload, i)
            for _ in range(ranges):
                _gap, i = varint(payload, i)
                _len, i = varint(payload, i)
            if ftype == 0x03:
                for _ in range(3):
                    _ecn, i = varint(payload, i)
            frames.append(QuicFrame("ACK", i - start))
        elif ftype == 0x06:
            offset, i = varint(payload, i)
            length, i = varint(payload, i)
            if i + length > len(payload):
                raise ValueError("CRYPTO past the end")
            frames.append(QuicFrame("CRYPTO", i + length - start, None, offset, length,
                                    chunk=bytes(payload[i:i + length])))
            i += length
        elif ftype == 0x07:
            length, i = varint(payload, i)
            i += length
            frames.append(QuicFrame("NEW_TOKEN", i - start))
        elif 0x08 <= ftype <= 0x0F:
            stream, i = varint(payload, i)
            offset = 0
            if ftype & 0x04:
                offset, i = varint(payload, i)
            if ftype & 0x02:
                length, i = varint(payload, i)
            else:
                length = len(payload) - i
            if i + length > len(payload):
                raise ValueError("STREAM past the end")
            frames.append(QuicFrame("STREAM", i + length - start, stream, offset, length, bool(ftype & 0x01),
                                    bytes(payload[i:i + length])))
            i += length
        elif ftype in _SIMPLE_FRAMES:
            name, fields = _SIMPLE_FRAMES[ftype]
            for _ in range(fields):
                _v, i = varint(payload, i)
            frames.append(QuicFrame(name, i - start))
        elif ftype == 0x18:
            _seq, i = varint(payload, i)
            _retire, i = varint(payload, i)
            if i >= len(payload):
                raise ValueError("NEW_CONNECTION_ID past the end")
            i += 1 + payload[i] + 16
            frames.append(QuicFrame("NEW_CONNECTION_ID", i - start))
        elif ftype in (0x1A, 0x1B):
            i += 8
            frames.append(QuicFrame("PATH_CHALLENGE" if ftype == 0x1A else "PATH_RESPONSE", i - start))
        elif ftype in (0x1C, 0x1D):
            _code, i = varint(payload, i)
            if ftype == 0x1C:
                _frame, i = varint(payload, i)
            length, i = varint(payload, i)
            i += length
            frames.append(QuicFrame("CONNECTION_CLOSE", i - start))
        elif ftype == 0x1E:
            frames.append(QuicFrame("HANDSHAKE_DONE", i - start))
        elif ftype == 0x1F:
            frames.append(QuicFrame("IMMEDIATE_ACK", i - start))
        elif ftype in (0x30, 0x31):
            if ftype == 0x31:
                length, i = varint(payload, i)
            else:
                length = len(payload) - i
            i += length
            frames.append(QuicFrame("DATAGRAM", i - start))
        elif ftype == 0xAF:  # ACK_FREQUENCY (draft-ietf-quic-ack-frequency), as quinn sends it
            for _ in range(4):
                _v, i = varint(payload, i)
            frames.append(QuicFrame("ACK_FREQUENCY", i - start))
        else:
            raise ValueError(f"unknown QUIC frame type {ftype:#x}")
        if i > len(payload):
            raise ValueError("frame past the end")
    return frames


@dataclass
class QuicPacket:
    """One QUIC packet of a datagram."""

    type: str  # Initial, 0-RTT, Handshake, Retry, Version negotiation, 1-RTT
    size: int
    #: Header bytes: the long header up to its Length field (the packet
    #: number too when in clear), or the short header's flags and DCID (and
    #: packet number in clear).
    header: int
    dcid: bytes = b""
    scid: bytes = b""
    number: int | None = None
    #: The frames, when the packet is in clear.
    frames: list[QuicFrame] | None = None
    #: Protected bytes (packet number, frames, tag) when not in clear.
    protected: int = 0

    @property
    def long(self) -> bool:
        return self.type != "1-RTT"


def parse_quic_datagram(data: bytes, dcid_len: int = 8, plaintext: bool = False) -> list[QuicPacket]:
    """The QUIC packets of one UDP datagram (coalesced ones in order).
    ``dcid_len``: the length of the connection id a short header carries
    (the receiver's choice: see :class:`QuicFlows`).  ``plaintext``: the
    packets are in clear (Zenoh's reliable UDP): packet numbers and frames
    are parsed.  ValueError if it is not QUIC."""
    packets: list[QuicPacket] = []
    i = 0
    while i < len(data):
        b0 = data[i]  # the fixed bit (0x40) is not checked: quinn greases it
        if b0 & 0x80:
            if i + 7 > len(data):
                raise ValueError("long header cut short")
            version = struct.unpack_from("!I", data, i + 1)[0]
            j = i + 5
            dl = data[j]
            dcid = bytes(data[j + 1:j + 1 + dl])
            j += 1 + dl
            if j >= len(data):
                raise ValueError("long header cut short")
            sl = data[j]
            scid = bytes(data[j + 1:j + 1 + sl])
            j += 1 + sl
            if j > len(data) or dl > 20 or sl > 20:
                raise ValueError("bad connection id")
            if version not in (0, 1, 0x6B3343CF):
                raise ValueError(f"QUIC version {version:#x}")
            if version == 0:
                packets.append(QuicPacket("Version negotiation", len(data) - i, len(data) - i, dcid, scid))
                break
            kind = QUIC_LONG_TYPES[(b0 >> 4) & 0x03]
            if kind == "Retry":
                packets.append(QuicPacket("Retry", len(data) - i, j - i, dcid, scid,
                                          protected=len(data) - j))
                break
            if kind == "Initial":
                token, j = varint(data, j)
                j += token
            length, j = varint(data, j)
            end = j + length
            if end > len(data):
                raise ValueError("QUIC packet past the datagram")
            packet = QuicPacket(kind, end - i, j - i, dcid, scid)
            _body(packet, data, b0, j, end, plaintext)
            packets.append(packet)
            i = end
        else:
            j = i + 1 + dcid_len
            if j > len(data):
                raise ValueError("short header cut short")
            packet = QuicPacket("1-RTT", len(data) - i, j - i, bytes(data[i + 1:j]))
            _body(packet, data, b0, j, len(data), plaintext)
            packets.append(packet)
            break
    return packets


def _body(packet: QuicPacket, data: bytes, b0: int, j: int, end: int, plaintext: bool) -> None:
    if not plaintext:
        packet.protected = end - j
        return
    pn_len = (b0 & 0x03) + 1
    packet.number = int.from_bytes(data[j:j + pn_len], "big")
    packet.header += pn_len
    packet.frames = parse_quic_frames(bytes(data[j + pn_len:end]))


class QuicFlows:
    """What a run's QUIC datagrams tell about connections: each endpoint's
    connection-id length (from the SCID of its long headers), so a short
    header can be cut at its DCID; and the STREAM and CRYPTO bytes already
    sent on each flow, so that data sent again is seen (in clear only)."""

    def __init__(self) -> None:
        self.cid_len: dict[tuple[str, int], int] = {}
        self.sent: dict[tuple[Any, ...], list[tuple[int, int]]] = defaultdict(list)

    def learn(self, src: str, sport: int, data: bytes) -> None:
        """Note the SCID length of a long-header packet ``src:sport`` sent."""
        if len(data) > 6 and data[0] & 0x80:
            dl = data[5]
            if 6 + dl < len(data):
                self.cid_len[(src, sport)] = data[6 + dl]

    def dcid_len(self, dst: str, dport: int) -> int:
        return self.cid_len.get((dst, dport), 8)

    def again(self, flow: tuple[Any, ...], offset: int, length: int) -> int:
        """How many of the bytes ``offset`` .. ``offset + length`` of a
        stream were sent before on ``flow``; notes them as sent."""
        ranges = self.sent[flow]
        seen = sum(max(0, min(offset + length, b) - max(offset, a)) for a, b in ranges)
        ranges.append((offset, offset + length))
        return seen


#: Zenoh's transport message ids (the low 5 bits of a message's header).
ZENOH_TRANSPORT = {0x00: "OAM", 0x01: "INIT", 0x02: "OPEN", 0x03: "CLOSE", 0x04: "KEEP_ALIVE", 0x05: "FRAME",
                   0x06: "FRAGMENT", 0x07: "JOIN"}


def zenoh_batches(chunk: bytes) -> list[str] | None:
    """The first message of each Zenoh batch in ``chunk`` (a streamed
    link's batches: a 2-byte little-endian length, then the batch), if the
    chunk is whole batches; else None."""
    out = []
    i = 0
    while i < len(chunk):
        if i + 2 > len(chunk):
            return None
        n = int.from_bytes(chunk[i:i + 2], "little")
        if n == 0 or i + 2 + n > len(chunk):
            return None
        out.append(ZENOH_TRANSPORT.get(chunk[i + 2] & 0x1F, "?"))
        i += 2 + n
    return out


def classify_quic(datagrams: Sequence[Any], plaintext: bool) -> None:
    """Give each QUIC datagram its packets (``d.quic``), kind, detail, copy
    and parts.  ``plaintext``: Zenoh's reliable UDP (frames in clear)."""
    flows = QuicFlows()
    ordered = sorted(datagrams, key=lambda d: d.t)
    for d in ordered:
        flows.learn(d.src, d.sport, d.data)
    for d in ordered:
        parts = dict.fromkeys(PEER_PARTS, 0)
        parts["headers"] = link_headers(d)
        try:
            packets = _parse_guessing(d.data, flows.dcid_len(d.dst, d.dport), plaintext)
        except ValueError as exc:
            d.quic = []
            d.kind, d.detail, d.parts = "other", f"not QUIC: {exc}", parts | {"payload": len(d.data)}
            continue
        d.quic = packets
        again = fresh = 0
        names: list[str] = []
        for p in packets:
            parts["transport"] += p.header
            if p.frames is None:
                tag = QUIC_TAG if p.type != "Version negotiation" else 0
                tag = min(tag, p.protected)
                parts["crypto"] += tag
                parts["encrypted"] += p.protected - tag
                continue
            for f in p.frames:
                names.append(f.name)
                if f.name == "STREAM":
                    parts["transport"] += f.size - f.data
                    parts["payload"] += f.data
                    seen = flows.again((d.src, d.sport, d.dst, d.dport, f.stream), f.offset, f.data)
                    again += seen
                    fresh += f.data - seen
                elif f.name == "CRYPTO":
                    parts["crypto"] += f.size
                    seen = flows.again((d.src, d.sport, d.dst, d.dport, "crypto", p.type), f.offset, f.data)
                    again += seen
                    fresh += f.data - seen
                elif f.name == "ACK":
                    parts["acks"] += f.size
                else:
                    parts["control"] += f.size
        d.parts = parts
        d.kind, d.detail = quic_kind(packets, len(d.data))
        d.copy = "retransmission" if again and not fresh else "first"
        d.quic_again = again


def _parse_guessing(data: bytes, dcid_len: int, plaintext: bool) -> list[QuicPacket]:
    """:func:`parse_quic_datagram`; in clear, a short header whose receiver's
    connection-id length is not known (none of its long headers seen) is
    cut at the length whose frames parse."""
    try:
        return parse_quic_datagram(data, dcid_len, plaintext)
    except ValueError:
        if not plaintext or not data or data[0] & 0x80:
            raise
    for n in range(21):
        try:
            return parse_quic_datagram(data, n, plaintext)
        except ValueError:
            continue
    raise ValueError("no connection-id length makes its frames parse")


def quic_kind(packets: Sequence[QuicPacket], size: int) -> tuple[str, str]:
    """A QUIC datagram's kind and detail: by its first packet's type (a
    coalesced datagram's others in the detail); a 1-RTT packet in clear by
    its frames, a protected one by size."""
    first = packets[0]
    detail = "+".join(p.type for p in packets) if len(packets) > 1 else ""
    if first.long:
        return f"QUIC {first.type}", detail
    if first.frames is None:
        return ("QUIC 1-RTT small" if size <= QUIC_SMALL else "QUIC 1-RTT large"), detail
    names = {f.name for f in first.frames}
    streams = [f for f in first.frames if f.name == "STREAM"]
    if "CONNECTION_CLOSE" in names:
        return "QUIC 1-RTT close", detail
    if streams:
        messages = [m for f in streams for m in (zenoh_batches(f.chunk) or ["data"])]
        if messages and all(m == "KEEP_ALIVE" for m in messages):
            return "QUIC 1-RTT Zenoh keep-alive", "+".join(sorted(names - {"STREAM"}))
        if any(m in ("INIT", "OPEN") for m in messages):
            return "QUIC 1-RTT Zenoh session set-up", ""
        if any(m == "CLOSE" for m in messages):
            return "QUIC 1-RTT Zenoh close", ""
        return "QUIC 1-RTT stream data", "+".join(sorted(names - {"STREAM"}))
    if names <= {"ACK", "PADDING"}:
        return "QUIC 1-RTT ACK only", ""
    if "PING" in names and names <= {"PING", "ACK", "PADDING"}:
        return "QUIC 1-RTT PING", "+".join(sorted(names - {"PING"}))
    return "QUIC 1-RTT control", "+".join(sorted(names))


def quic_packet_table(datagrams: Iterable[Any], tasks: int) -> list[dict[str, Any]]:
    """QUIC packets (not datagrams) by type: packets and bytes per task,
    header, tag and frames; how many travelled coalesced."""
    rows: dict[str, Counter[str]] = defaultdict(Counter)
    for d in datagrams:
        packets = getattr(d, "quic", None) or []
        for p in packets:
            c = rows[p.type]
            c["packets"] += 1
            c["bytes"] += p.size
            c["header"] += p.header
            c["coalesced"] += len(packets) > 1
            if p.frames is None:
                c["protected"] += p.protected
    order = ["Initial", "0-RTT", "Handshake", "Retry", "Version negotiation", "1-RTT"]
    return [{"type": t, **{k: v / tasks for k, v in rows[t].items()}} for t in order if t in rows]


def _flow(d: Any) -> tuple[Any, ...]:
    a, b = (d.src, d.sport), (d.dst, d.dport)
    return (a, b) if a <= b else (b, a)


def quic_connections(datagrams: Sequence[Any]) -> dict[str, float]:
    """Connections (UDP flows) that carried long-header packets, and per
    such connection: long-header packets and bytes, datagrams until the
    first 1-RTT packet each way.  Over a whole capture: the handshakes
    happen mostly while the team comes up, before the budget's window."""
    by_flow: dict[tuple[Any, ...], list[Any]] = defaultdict(list)
    for d in sorted(datagrams, key=lambda d: d.t):
        if getattr(d, "quic", None):
            by_flow[_flow(d)].append(d)
    handshakes = [ds for ds in by_flow.values() if any(p.long for d in ds for p in d.quic)]
    if not handshakes:
        return {"connections": 0}
    longs = [sum(1 for d in ds for p in d.quic if p.long) for ds in handshakes]
    long_bytes = [sum(d.frame for d in ds if any(p.long for p in d.quic)) for ds in handshakes]
    coalesced = sum(1 for ds in handshakes for d in ds if len(d.quic) > 1)
    return {"connections": len(handshakes), "long_packets_per_connection": statistics.fmean(longs),
            "long_datagram_bytes_per_connection": statistics.fmean(long_bytes),
            "coalesced_datagrams": coalesced,
            "datagrams": sum(len(ds) for ds in handshakes)}


def size_bins(datagrams: Iterable[Any], bins: Sequence[int] = (48, 64, 96, 160, 320, 640, 1500)) -> Counter[str]:
    """1-RTT datagrams by UDP payload size: ``<= N`` bins."""
    out: Counter[str] = Counter()
    for d in datagrams:
        packets = getattr(d, "quic", None)
        if not packets or packets[0].long:
            continue
        n = len(d.data)
        label = next((f"<= {b}" for b in bins if n <= b), f"> {bins[-1]}")
        out[label] += 1
    return out


def idle_gaps(datagrams: Sequence[Any], gap: float = IDLE_GAP_S) -> dict[str, Any]:
    """Traffic on quiet flows: per directional flow, the gaps between
    consecutive datagrams; a datagram after at least ``gap`` seconds of
    silence on its flow (both ways) opens an idle exchange (a keep-alive,
    a liveliness message, a late ACK).  Returns the count of such
    datagrams, their bytes, and the gaps (seconds): their median, spread and list."""
    by_flow: dict[tuple[Any, ...], list[Any]] = defaultdict(list)
    for d in sorted(datagrams, key=lambda d: d.t):
        by_flow[_flow(d)].append(d)
    opened = []
    gaps: list[float] = []
    one_way: dict[tuple[Any, ...], float] = {}
    for ds in by_flow.values():
        for a, b in zip(ds, ds[1:]):
            if b.t - a.t >= gap:
                opened.append(b)
        for d in ds:
            key = (d.src, d.sport, d.dst, d.dport)
            if key in one_way and d.t - one_way[key] >= gap:
                gaps.append(d.t - one_way[key])
            one_way[key] = d.t
    return {"idle_datagrams": len(opened), "idle_bytes": sum(d.frame for d in opened),
            "gap_median_s": statistics.median(gaps) if gaps else None,
            "gap_p10_s": _quantile(gaps, 0.1), "gap_p90_s": _quantile(gaps, 0.9), "gap_list": gaps}


def _quantile(values: Sequence[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


# =========================================================================== TLS over TCP

#: TLS 1.3 record: a 5-byte header; an encrypted record's content ends with
#: its inner content type (1 byte) and the AEAD tag (16).
TLS_HEADER, TLS_SEALED_TAIL = 5, 1 + 16


def split_tls(segments: Sequence[Any]) -> None:
    """Split the payload of TCP segments that carry TLS (Zenoh over TCP with
    the team's keys) by the records they hold: each record's 5-byte header
    is ``transport``; an application-data record's inner type and tag
    ``crypto`` and the rest ``payload`` (the handshake's last flights are
    application-data records too in TLS 1.3, and count as payload here); a
    handshake, change-cipher-spec or alert record's content ``crypto``.
    The records are dpkt's; the sender's stream they are read from is put
    together here, in sequence-number order (the capture holds
    what each host sent, before any loss, so it has no holes); a segment
    sent again gets the split of the bytes it repeats.  A flow whose stream
    does not start with a TLS handshake record is left alone."""
    flows: dict[tuple[Any, ...], dict[str, Any]] = {}
    for d in sorted(segments, key=lambda d: d.t):
        if d.tcp is None:
            continue
        flags, seq = d.tcp
        f = flows.setdefault((d.src, d.sport, d.dst, d.dport), {"base": None, "buf": bytearray(), "segments": []})
        if flags & 0x02:
            f["base"] = (seq + 1) & 0xFFFFFFFF
            continue
        if not d.data:
            continue
        if f["base"] is None:
            f["base"] = seq
        offset = (seq - f["base"]) & 0xFFFFFFFF
        f["segments"].append((d, offset))
        buf = f["buf"]
        if offset <= len(buf) < offset + len(d.data):
            buf += d.data[len(buf) - offset:]
    for f in flows.values():
        buf = f["buf"]
        if len(buf) < 3 or buf[0] != 0x16 or buf[1] != 0x03:
            continue
        labels = _tls_labels(bytes(buf))
        for d, offset in f["segments"]:
            parts = dict.fromkeys(PEER_PARTS, 0)
            parts["headers"] = d.frame - len(d.data)
            for start, end, part in labels:
                parts[part] += max(0, min(end, offset + len(d.data)) - max(start, offset))
            parts["payload"] += len(d.data) - sum(parts[p] for p in PEER_PARTS if p != "headers")
            d.parts = parts
            d.detail = "TLS"


def _tls_labels(stream: bytes) -> list[tuple[int, int, str]]:
    """A sender's TLS stream by part: its records as dpkt reads them, up to
    the first that is not TLS or that the capture holds only part of."""
    labels: list[tuple[int, int, str]] = []
    pos = 0
    while pos + TLS_HEADER <= len(stream):
        try:
            record = dpkt.ssl.TLSRecord(stream[pos:])
        except dpkt.NeedData:
            break  # cut short: the rest stays payload
        if record.type not in (20, 21, 22, 23) or record.version >> 8 != 3:
            break  # not TLS from here on: the rest stays payload
        labels.append((pos, pos + TLS_HEADER, "transport"))
        body, end = pos + TLS_HEADER, pos + TLS_HEADER + record.length
        if record.type == 23 and record.length >= TLS_SEALED_TAIL:
            labels += [(body, end - TLS_SEALED_TAIL, "payload"), (end - TLS_SEALED_TAIL, end, "crypto")]
        else:
            labels.append((body, end, "crypto"))
        pos = end
    return labels


# =========================================================================== RTPS

#: The budget's name of each submessage id (the ids as Wireshark reads them).
RTPS_SUBMESSAGES = {0x01: "PAD", 0x06: "ACKNACK", 0x07: "HEARTBEAT", 0x08: "GAP", 0x09: "INFO_TS",
                    0x0C: "INFO_SRC", 0x0D: "INFO_REPLY_IP4", 0x0E: "INFO_DST", 0x0F: "INFO_REPLY",
                    0x12: "NACK_FRAG", 0x13: "HEARTBEAT_FRAG", 0x15: "DATA", 0x16: "DATA_FRAG",
                    0x30: "SEC_BODY", 0x31: "SEC_PREFIX", 0x32: "SEC_POSTFIX", 0x33: "SRTPS_PREFIX",
                    0x34: "SRTPS_POSTFIX", 0x81: "vendor MSG_LEN", 0x82: "vendor ENTITY_ID"}
_ENTITY_SUBMESSAGES = ("DATA", "DATA_FRAG", "HEARTBEAT", "HEARTBEAT_FRAG", "GAP", "ACKNACK", "NACK_FRAG")
_ACK_SUBMESSAGES = ("HEARTBEAT", "HEARTBEAT_FRAG", "GAP", "ACKNACK", "NACK_FRAG")

#: The builtin endpoints, by entity id (writer; its reader is the same with 0xc7/0xc4).
BUILTIN_ENTITIES = {
    0x000100C2: "SPDP", 0x000100C7: "SPDP",
    0x000003C2: "SEDP publications", 0x000003C7: "SEDP publications",
    0x000004C2: "SEDP subscriptions", 0x000004C7: "SEDP subscriptions",
    0x000002C2: "SEDP topics", 0x000002C7: "SEDP topics",
    0x000200C2: "participant message", 0x000200C7: "participant message",
    0x000300C3: "type lookup", 0x000300C4: "type lookup", 0x000301C3: "type lookup", 0x000301C4: "type lookup",
}
DISCOVERY = ("SPDP", "SEDP publications", "SEDP subscriptions", "SEDP topics", "participant message", "type lookup",
             "other builtin")


@dataclass
class Submessage:
    """One RTPS submessage: its id, name, flags, size (its 4-byte header
    included) and, for entity submessages, the reader and writer ids, the
    sequence number and the serialized payload's size."""

    id: int
    name: str
    flags: int
    size: int
    reader: int = 0
    writer: int = 0
    sn: int = 0
    fragment: int = 0
    inline_qos: int = 0
    payload: bytes = b""
    #: A DATA without a sample (no D flag): an unregister or a dispose.
    key_only: bool = False
    #: The GUID prefix of the participant that sent it (the header's, or an INFO_SRC's).
    source: bytes = b""
    #: The GUID prefix of the participant it is for (an INFO_DST's), if named.
    dest: bytes = b""
    #: A discovery sample's topic name and endpoint GUID (its parameters PID_TOPIC_NAME, PID_ENDPOINT_GUID).
    topic: str | None = None
    endpoint: bytes = b""


@dataclass
class RtpsMessage:
    version: tuple[int, int]
    vendor: int
    guid_prefix: bytes
    submessages: list[Submessage] = field(default_factory=list)


RTPS_HEADER = 20

#: tshark's arguments: RTPS's heuristic tried before any dissector of the ports, the tree as PDML (the
#: positions and sizes of the fields), only RTPS's part of it.
TSHARK_RTPS = ("-n", "-o", "udp.try_heuristic_first:TRUE", "--enable-heuristic", "rtps_udp", "-T", "pdml",
               "-J", "rtps")


def rtps_messages(payloads: Sequence[bytes], ports: Sequence[tuple[int, int]] = ()) -> list[RtpsMessage | None]:
    """The RTPS message of each UDP payload, dissected by Wireshark's RTPS
    dissector (one tshark run over a pcap of them, ``ports`` their UDP
    ports); None for one that is not RTPS, or that Wireshark finds malformed."""
    if not payloads:
        return []
    tshark = shutil.which("tshark")
    if tshark is None:
        raise RuntimeError("RTPS is dissected by Wireshark's: install tshark (Debian: apt-get install tshark)")
    with tempfile.TemporaryDirectory() as tmp:
        pcap, errors = Path(tmp) / "rtps.pcap", Path(tmp) / "stderr"
        with pcap.open("wb") as f:
            w = dpkt.pcap.Writer(f)
            for i, payload in enumerate(payloads):
                sport, dport = ports[i] if ports else (7400, 7400)
                udp = dpkt.udp.UDP(sport=sport, dport=dport, data=payload)
                udp.ulen = len(udp)
                ip = dpkt.ip.IP(src=b"\n\0\0\1", dst=b"\n\0\0\2", p=dpkt.ip.IP_PROTO_UDP, data=udp)
                w.writepkt(dpkt.ethernet.Ethernet(data=ip), ts=i)
        out: list[RtpsMessage | None] = []
        env = {**os.environ, "WIRESHARK_CONFIG_DIR": tmp}  # Wireshark's defaults, not a user's preferences
        with errors.open("wb") as err, subprocess.Popen([tshark, *TSHARK_RTPS, "-r", str(pcap)],
                                                        stdout=subprocess.PIPE, stderr=err, env=env) as proc:
            assert proc.stdout is not None
            try:
                for _event, elem in ET.iterparse(proc.stdout):  # the packets' trees, one at a time
                    if elem.tag == "packet":
                        out.append(_message(elem, payloads[len(out)]))
                        elem.clear()
            except ET.ParseError:
                if not proc.wait():
                    raise
        if proc.returncode:
            raise RuntimeError(f"tshark failed: {errors.read_text(errors='replace').strip()}")
    if len(out) != len(payloads):
        raise RuntimeError(f"tshark dissected {len(out)} of {len(payloads)} datagrams")
    return out


def _child(e: ET.Element, name: str) -> ET.Element | None:
    return next((c for c in e if c.get("name") == name), None)


def _int(e: ET.Element | None, base: int = 10) -> int:
    return 0 if e is None else int(e.get("show", "0"), base)


def _message(packet: ET.Element, data: bytes) -> RtpsMessage | None:
    """A packet of tshark's PDML as an RTPS message (``data``: its UDP payload)."""
    rtps = next((p for p in packet if p.get("name") == "rtps"), None)
    if rtps is None or any(p.get("name") == "_ws.malformed" for p in packet) or any(
            e.get("name", "").endswith(".error") for e in rtps.iter("field")):
        return None  # malformed: an error Wireshark reports (such as a submessage length it rejects)
    version = _child(rtps, "rtps.version")
    prefix = _child(rtps, "rtps.guidPrefix.src")
    if version is None or prefix is None:
        return None
    msg = RtpsMessage((_int(_child(version, "rtps.version.major")), _int(_child(version, "rtps.version.minor"))),
                      _int(_child(rtps, "rtps.vendorId"), 16), bytes.fromhex(prefix.get("value", "")))
    base = int(rtps.get("pos", "0"))
    source, dest = msg.guid_prefix, b""
    for sm in rtps:
        if sm.get("name") != "rtps.sm.id":
            continue
        sid = _int(sm, 16)
        name = RTPS_SUBMESSAGES.get(sid, f"vendor {sid:#04x}" if sid >= 0x80 else f"unknown {sid:#04x}")
        start = int(sm.get("pos", "0")) - base
        length = _int(_child(sm, "rtps.sm.octetsToNextHeader"))
        if length and int(sm.get("size", "0")) != 4 + length:
            return None  # past the end of the message (Wireshark cuts it at the end)
        sub = Submessage(sid, name, _int(_child(sm, "rtps.sm.flags"), 16), int(sm.get("size", "0")),
                         source=source, dest=dest)
        if name == "INFO_SRC":
            found = _child(sm, "rtps.guidPrefix.src")
            source = source if found is None else bytes.fromhex(found.get("value", ""))
        elif name == "INFO_DST":
            found = _child(sm, "rtps.guidPrefix.dst")
            dest = b"" if found is None else bytes.fromhex(found.get("value", ""))
            dest = b"" if dest == bytes(12) else dest
        elif name in _ENTITY_SUBMESSAGES:
            _entity_fields(sub, sm, data[start:start + sub.size])
        msg.submessages.append(sub)
    return msg


def _entity_fields(sub: Submessage, sm: ET.Element, raw: bytes) -> None:
    """An entity submessage's fields from its PDML element ``sm`` (``raw``: its bytes)."""
    sub.reader, sub.writer = _int(_child(sm, "rtps.sm.rdEntityId"), 16), _int(_child(sm, "rtps.sm.wrEntityId"), 16)
    if sub.name in ("DATA", "DATA_FRAG", "HEARTBEAT", "GAP", "HEARTBEAT_FRAG", "NACK_FRAG"):
        sub.sn = _int(_child(sm, "rtps.sm.seqNumber"))
    if sub.name not in ("DATA", "DATA_FRAG"):
        return
    # The payload (or the inline QoS) starts octetsToInlineQos after that field.
    start = 4 + 4 + _int(_child(sm, "rtps.octets_to_inline_qos"))
    sub.fragment = _int(_child(sm, "rtps.data_frag.number"))
    qos = next((c for c in sm if c.get("show", "").startswith("inlineQos")), None)
    if qos is not None and sub.flags & 0x02:
        sub.inline_qos = int(qos.get("size", "0"))
        start += sub.inline_qos
    if sub.name == "DATA":
        sub.key_only = not sub.flags & 0x04  # no sample: an unregister or dispose (a key, or inline QoS only)
        if not sub.flags & 0x0C:
            return
    sub.payload = raw[start:]
    if sub.writer != 0x000003C2:  # the SEDP publications' writer
        return
    for e in sm.iter("field"):  # a writer's topic and GUID (not Wireshark's own note of the topic)
        if e.get("name") == "rtps.param.topicName" and e.get("size") != "0" and sub.topic is None:
            sub.topic = e.get("show", "")
        elif e.get("name") == "rtps.param.endpoint_guid" and not sub.endpoint:
            sub.endpoint = bytes.fromhex(e.get("value", ""))


def entity_category(entity: int) -> str:
    """``SPDP``, ``SEDP publications``, ... for a builtin entity id,
    ``user`` for an application's, ``vendor`` for a vendor-specific one."""
    if entity in BUILTIN_ENTITIES:
        return BUILTIN_ENTITIES[entity]
    kind = entity & 0xFF
    if kind & 0xC0 == 0xC0:
        return "other builtin"
    if kind & 0xC0 == 0x40:
        return "vendor"
    return "user"


def submessage_category(sub: Submessage) -> str:
    """Which endpoint a submessage concerns: its writer's category (an
    ACKNACK names the writer it acknowledges), else its reader's."""
    if sub.writer:
        return entity_category(sub.writer)
    if sub.reader:
        return entity_category(sub.reader)
    return "user"


def user_sample_body(payload: bytes) -> int | None:
    """The length of coapkb's ``body`` in a serialized Request or Reply
    sample (``@key string client; @key uint64 token; sequence<octet> body``),
    in XCDR1 or XCDR2, with or without a DHEADER; None if it does not fit."""
    if len(payload) < 4:
        return None
    little = payload[1] & 0x01 == 1
    order = "little" if little else "big"
    pad = payload[3] & 0x03
    data = payload[4:len(payload) - pad] if pad else payload[4:]
    for dheader in (False, True):
        for align8 in (True, False):
            try:
                i = 4 if dheader else 0
                n = int.from_bytes(data[i:i + 4], order)
                i += 4 + n
                i = (i + (7 if align8 else 3)) & ~(7 if align8 else 3)
                i += 8
                i = (i + 3) & ~3
                body = int.from_bytes(data[i:i + 4], order)
                i += 4
                if i + body == len(data) and i <= len(data):
                    return body
            except (IndexError, ValueError):
                continue
    return None


class RtpsTopics:
    """Which topic each writer writes, from the SEDP publications seen
    (endpoint GUID and topic name): coapkb's ``.../request`` and ``.../reply``."""

    def __init__(self) -> None:
        self.topic: dict[bytes, str] = {}

    def learn(self, msg: RtpsMessage) -> None:
        for sub in msg.submessages:
            if sub.name == "DATA" and sub.writer == 0x000003C2 and sub.topic is not None and len(sub.endpoint) == 16:
                self.topic[sub.endpoint] = sub.topic

    def role(self, prefix: bytes, writer: int) -> str:
        """``request``, ``reply`` or ``data`` for the user writer ``prefix:writer``
        (without a known prefix: by entity id, if every writer of that id
        writes the same kind of topic)."""
        name = self.topic.get(prefix + writer.to_bytes(4, "big"))
        if name is not None:
            return _role(name)
        roles = {_role(n) for g, n in self.topic.items() if g[12:] == writer.to_bytes(4, "big")}
        return roles.pop() if len(roles) == 1 else "data"

    def role_of(self, sub: Submessage) -> str:
        """The role of the user writer a submessage concerns: its sender's
        (DATA, HEARTBEAT, GAP), or the one it acknowledges (ACKNACK, NACK_FRAG:
        the writer is at the INFO_DST's participant)."""
        prefix = sub.dest if sub.name in ("ACKNACK", "NACK_FRAG") else sub.source
        return self.role(prefix, sub.writer)


def _role(topic: str) -> str:
    if topic.endswith("request"):
        return "request"
    if topic.endswith("reply"):
        return "reply"
    return "data"


_MAIN_ORDER = ("DATA_FRAG", "DATA", "GAP", "HEARTBEAT_FRAG", "HEARTBEAT", "NACK_FRAG", "ACKNACK")


def classify_rtps(datagrams: Sequence[Any]) -> None:
    """Give each RTPS datagram its message (``d.rtps``), kind, detail, copy and parts.

    Kind: ``RTPS <what> <submessage>``, what being the category of the
    endpoints its entity submessages concern (a discovery endpoint, user
    ``request`` or ``reply``, ``mixed`` when several), and the submessage
    the main one (data before gaps before heartbeats before ACKNACKs; an
    unregister or dispose, a DATA without a sample, is ``DATA (unregister)``); every submessage's name
    in the detail.  A DATA (or fragment) the same writer sent to the same
    host before is a retransmission; a datagram of only such is one."""
    topics = RtpsTopics()
    ordered = sorted(datagrams, key=lambda d: d.t)
    for d, msg in zip(ordered, rtps_messages([d.data for d in ordered], [(d.sport, d.dport) for d in ordered])):
        d.rtps = msg
        if msg is None:
            d.detail = "not RTPS (or malformed, to Wireshark)"
            continue
        topics.learn(msg)
    sent: set[tuple[Any, ...]] = set()
    for d in ordered:
        parts = dict.fromkeys(PEER_PARTS, 0)
        parts["headers"] = link_headers(d)
        msg = d.rtps
        if msg is None:
            d.kind, d.parts = "other", parts | {"payload": len(d.data)}
            continue
        parts["transport"] += RTPS_HEADER
        whats: list[str] = []
        mains: list[str] = []
        new = repeats = 0
        for sub in msg.submessages:
            if sub.name in _ENTITY_SUBMESSAGES:
                what = submessage_category(sub)
                if what == "user":
                    what = topics.role_of(sub)
                whats.append(what)
                main = "DATA (unregister)" if sub.key_only else sub.name
                mains.append(main)
                if sub.name in _ACK_SUBMESSAGES:
                    parts["acks"] += sub.size
                else:
                    body = user_sample_body(sub.payload) if what in ("request", "reply", "data") else None
                    payload = len(sub.payload) if body is None else body
                    parts["payload"] += payload
                    parts["transport"] += sub.size - payload
                    key = (sub.source, sub.writer, sub.sn, sub.fragment, d.dst)
                    if key in sent:
                        repeats += 1
                    else:
                        new += 1
                        sent.add(key)
            elif sub.name.startswith("INFO_"):
                parts["transport"] += sub.size
            else:
                parts["control"] += sub.size
        d.parts = parts
        d.copy = "retransmission" if repeats and not new else "first"
        kinds = [w for w in dict.fromkeys(whats)]
        what = kinds[0] if len(kinds) == 1 else ("mixed" if kinds else "no entity")
        if len(kinds) > 1 and all(k in DISCOVERY for k in kinds):
            what = "discovery (several)"
        main = min(mains, key=lambda m: _MAIN_ORDER.index(m.split(" ")[0])) if mains else (
            msg.submessages[0].name if msg.submessages else "header only")
        d.kind = f"RTPS {what} {main}"
        d.detail = "+".join(s.name for s in msg.submessages)


def submessage_rows(datagrams: Iterable[Any], tasks: int) -> list[dict[str, Any]]:
    """RTPS bytes by (category, submessage), per task: how many, their bytes
    (the 4-byte submessage header included) and the serialized payload's
    share; the RTPS headers on a line of their own."""
    rows: dict[tuple[str, str], Counter[str]] = defaultdict(Counter)
    for d in datagrams:
        msg = getattr(d, "rtps", None)
        if msg is None:
            continue
        rows[("(all)", "RTPS header")].update({"count": 1, "bytes": RTPS_HEADER})
        for sub in msg.submessages:
            what = submessage_category(sub) if sub.name in _ENTITY_SUBMESSAGES else "(interpreter)"
            what = "user" if what in ("request", "reply", "data") else what
            name = "DATA (unregister)" if sub.key_only else sub.name
            rows[(what, name)].update({"count": 1, "bytes": sub.size, "payload": len(sub.payload)})
    order = [*DISCOVERY, "user", "vendor", "(interpreter)", "(all)"]
    out = []
    for (what, name), c in sorted(rows.items(), key=lambda kv: (order.index(kv[0][0]) if kv[0][0] in order
                                                                else len(order), kv[0][1])):
        out.append({"endpoint": what, "submessage": name, **{k: v / tasks for k, v in c.items()}})
    return out


# =========================================================================== a setting's budget

#: The comparison's groups of kinds, whole frames: what sets up (handshakes,
#: discovery), the messages themselves (requests, answers, notifications,
#: samples, stream data), what only acknowledges or keeps alive, the rest.
COMPARE_GROUPS = ("set-up and discovery", "messages", "acknowledgements and keep-alives", "other")

_COAP_SETUP = ("EDHOC",)
_COAP_ACKS = ("empty ACK", "reset", "liveness", "liveness answer")


def compare_group(kind: str) -> str:
    """The comparison group (:data:`COMPARE_GROUPS`) of a datagram's kind, any protocol."""
    if kind.startswith("RTPS "):
        if kind.startswith("RTPS participant message "):
            return COMPARE_GROUPS[2]
        if any(kind.startswith(f"RTPS {what} ") for what in DISCOVERY):
            return COMPARE_GROUPS[0]
        if any(kind.endswith(" " + s) for s in _ACK_SUBMESSAGES):
            return COMPARE_GROUPS[2]
        return COMPARE_GROUPS[1] if " DATA" in kind else COMPARE_GROUPS[3]
    if kind.startswith("QUIC "):
        if kind.split(" ")[1] in (*QUIC_LONG_TYPES, "Version") or kind.endswith("set-up"):
            return COMPARE_GROUPS[0]
        if kind.endswith(("ACK only", "PING", "keep-alive", "small")):
            return COMPARE_GROUPS[2]
        if kind.endswith(("stream data", "large")):
            return COMPARE_GROUPS[1]
        return COMPARE_GROUPS[3]
    if kind.startswith("TCP "):
        return {"TCP handshake": COMPARE_GROUPS[0], "TCP ACK": COMPARE_GROUPS[2],
                "TCP data": COMPARE_GROUPS[1]}.get(kind, COMPARE_GROUPS[3])
    if kind.startswith(_COAP_SETUP):
        return COMPARE_GROUPS[0]
    if kind in _COAP_ACKS:
        return COMPARE_GROUPS[2]
    if kind in ("other", "ICMP error", "IP fragment"):
        return COMPARE_GROUPS[3]
    return COMPARE_GROUPS[1]


def peer_parts(d: Any) -> dict[str, int]:
    """``d``'s bytes in :data:`PEER_PARTS`: a peer's as classified; a CoAP
    datagram's mapped (header, token, options and OSCORE's inner code and
    options are ``transport``, an empty ACK's or Reset's CoAP bytes
    ``acks``, OSCORE's option, markers and tag ``crypto``); a TCP segment's
    headers and payload."""
    p = d.parts or {}
    if d.proto in ("quic", "rtps") or d.kind == "IP fragment" or "crypto" in p:
        return {k: int(p.get(k, 0)) for k in PEER_PARTS}
    out = dict.fromkeys(PEER_PARTS, 0)
    out["headers"], out["payload"] = int(p.get("headers", 0)), int(p.get("payload", 0))
    framing = int(p.get("coap", 0)) + int(p.get("options", 0)) + int(p.get("inner_options", 0))
    out["crypto"] = int(p.get("oscore", 0)) - int(p.get("inner_options", 0))
    out["acks" if d.kind in ("empty ACK", "reset") else "transport"] = framing
    return out


ROW_FIELDS = ("setting", "system", "loss_pct", "security", "runs", "ok", "tasks", "table", "name", "packets", "lost",
              "bytes", *PEER_PARTS, "value")
SUBSETS = ("of which retransmissions", "of which retries (new message, same request)", "of which hedged copies",
           "of which lost on the link")


def setting_rows(name: str, runs: Sequence[Any], label: Any = None) -> list[dict[str, Any]]:
    """A setting's budget as rows (totals over its runs; the tables divide
    by its tasks): ``kind`` and ``group`` lines of packets, lost packets,
    bytes and parts; ``subset`` (copies, losses) and ``total``; ``setup``
    (what the hosts sent before the bench's first reading); ``idle``
    (traffic on quiet flows); QUIC's ``quic-packet`` (packets by header
    type; ``value`` how many were coalesced), ``quic-size`` (1-RTT
    datagrams by size) and ``quic-connection`` (over the whole capture);
    RTPS's ``rtps-submessage`` (``packets`` the count, ``payload`` the
    serialized payload).  ``label``: a datagram's kind label (the kind)."""
    label = label or (lambda d: d.kind)
    first = runs[0]
    common = {"setting": name, "system": first.system, "loss_pct": first.loss,
              "security": str(first.row.get("security") or ("oscore" if first.security else "none")),
              "runs": len(runs), "ok": sum(1 for r in runs if str(r.row.get("ok")) in ("True", "1", "true")),
              "tasks": sum(r.tasks for r in runs)}
    lines: dict[tuple[str, str], Counter[str]] = defaultdict(Counter)

    def add(table: str, key: str, d: Any) -> None:
        c = lines[(table, key)]
        c["packets"] += 1
        c["lost"] += int(d.lost)
        c["bytes"] += d.frame
        c.update(peer_parts(d))

    datagrams = [d for r in runs for d in r.datagrams]
    for d in datagrams:
        add("kind", label(d), d)
        add("group", compare_group(d.kind), d)
        add("total", "total", d)
        if d.copy == "retransmission":
            add("subset", SUBSETS[0], d)
        elif d.copy == "retry":
            add("subset", SUBSETS[1], d)
        elif d.copy == "hedge":
            add("subset", SUBSETS[2], d)
        if d.lost:
            add("subset", SUBSETS[3], d)
    for r in runs:
        for d in r.setup:
            add("setup", compare_group(d.kind), d)
            add("setup", "total", d)
    rows = [{**common, "table": t, "name": k, **c} for (t, k), c in lines.items()]
    idle: Counter[str] = Counter()
    gaps: list[float] = []
    for r in runs:
        g = idle_gaps(r.datagrams)
        idle.update({"idle_datagrams": g["idle_datagrams"], "idle_bytes": g["idle_bytes"]})
        gaps += g["gap_list"]
    rows += [{**common, "table": "idle", "name": k, "value": v} for k, v in idle.items()]
    if gaps:
        rows += [{**common, "table": "idle", "name": f"gap_{q}_s", "value": round(_quantile(gaps, x) or 0, 3)}
                 for q, x in (("p10", 0.1), ("median", 0.5), ("p90", 0.9))]
    if any(getattr(d, "quic", None) for d in datagrams):
        rows += _quic_rows(common, runs)
    if any(getattr(d, "rtps", None) for d in datagrams):
        for row in submessage_rows(datagrams, 1):
            rows.append({**common, "table": "rtps-submessage", "name": f"{row['endpoint']} / {row['submessage']}",
                         "packets": row.get("count", 0), "bytes": row.get("bytes", 0),
                         "payload": row.get("payload", 0)})
    return rows


def _quic_rows(common: Mapping[str, Any], runs: Sequence[Any]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    datagrams = [d for r in runs for d in r.datagrams]
    for row in quic_packet_table(datagrams, 1):
        rows.append({**common, "table": "quic-packet", "name": row["type"], "packets": row.get("packets", 0),
                     "bytes": row.get("bytes", 0), "transport": row.get("header", 0),
                     "encrypted": row.get("protected", 0), "value": row.get("coalesced", 0)})
    for label, n in size_bins(datagrams).items():
        rows.append({**common, "table": "quic-size", "name": label, "packets": n})
    total: Counter[str] = Counter()
    for r in runs:
        c = quic_connections([*r.setup, *r.datagrams])
        n = c.get("connections", 0)
        total["connections"] += n
        total["long packets"] += round(c.get("long_packets_per_connection", 0) * n)
        total["long-header datagram bytes"] += round(c.get("long_datagram_bytes_per_connection", 0) * n)
        total["coalesced datagrams"] += c.get("coalesced_datagrams", 0)
        total["connections in the window"] += quic_connections(r.datagrams).get("connections", 0)
    rows += [{**common, "table": "quic-connection", "name": k, "value": v} for k, v in total.items()]
    clear = [p for d in datagrams for p in (d.quic or [])]
    rows.append({**common, "table": "quic-connection", "name": "packets with frames in clear",
                 "value": sum(1 for p in clear if p.frames is not None)})
    rows.append({**common, "table": "quic-connection", "name": "packets", "value": len(clear)})
    rows.append({**common, "table": "quic-connection", "name": "stream bytes sent again",
                 "value": sum(getattr(d, "quic_again", 0) for d in datagrams)})
    return rows


def write_rows(rows: Iterable[Mapping[str, Any]], path: Any) -> None:
    import csv

    with open(path, "w", newline="", encoding="utf-8") as out:
        w = csv.DictWriter(out, ROW_FIELDS, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: row.get(k, 0 if k in PEER_PARTS or k in ("packets", "lost", "bytes") else "")
                        for k in ROW_FIELDS})


def read_rows(path: Any) -> list[dict[str, Any]]:
    import csv

    out = []
    with open(path, newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            r: dict[str, Any] = dict(row)
            for k in ("runs", "ok", "tasks"):
                r[k] = int(r[k])
            r["loss_pct"] = float(r["loss_pct"])
            for k in ("packets", "lost", "bytes", *PEER_PARTS, "value"):
                r[k] = float(r[k]) if r.get(k) not in (None, "") else 0.0
            out.append(r)
    return out


# =========================================================================== tables


def _per(value: float, n: int) -> str:
    v = value / n if n else 0.0
    if abs(v) >= 10:
        return f"{v:,.0f}"
    return f"{v:.2f}" if 0 < abs(v) < 0.1 else f"{v:.1f}"


def _by_setting(rows: Iterable[Mapping[str, Any]]) -> dict[str, list[Mapping[str, Any]]]:
    out: dict[str, list[Mapping[str, Any]]] = {}
    for r in rows:
        out.setdefault(r["setting"], []).append(r)
    return out


_KIND_ORDER = ("EDHOC", "query", "answer", "registration", "notification", "task post", "task answer",
               "decision post", "decision answer", "liveness", "hearsay", "lease", "empty ACK", "reset", "error", "TCP handshake", "TCP data", "TCP ACK", "TCP close",
               "QUIC Initial", "QUIC 0-RTT", "QUIC Handshake", "QUIC Retry", "QUIC Version",
               "QUIC 1-RTT Zenoh session set-up", "QUIC 1-RTT stream data", "QUIC 1-RTT large",
               "QUIC 1-RTT Zenoh keep-alive", "QUIC 1-RTT PING", "QUIC 1-RTT ACK only", "QUIC 1-RTT small",
               "QUIC 1-RTT control", "QUIC 1-RTT Zenoh close", "QUIC 1-RTT close", *(f"RTPS {w}" for w in DISCOVERY),
               "RTPS request", "RTPS reply", "RTPS data", "RTPS mixed", "RTPS discovery", "RTPS vendor")


def _kind_key(name: str) -> tuple[int, str]:
    for i, prefix in enumerate(_KIND_ORDER):
        if name == prefix or name.startswith(prefix + " "):
            return i, name
    return len(_KIND_ORDER), name


def kind_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """One setting's datagrams by kind, per task: packets, bytes, parts, lost."""
    tasks = rows[0]["tasks"]
    tcp = any(r["name"].startswith("TCP ") for r in rows if r["table"] == "kind")
    head = (f"| kind | packets | bytes | Eth+IP+{'TCP' if tcp else 'UDP'} | protocol headers | acks | crypto | control "
            "| encrypted | payload | lost packets |\n|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|\n")

    def line(r: Mapping[str, Any], bold: bool = False) -> str:
        cells = [_per(r["packets"], tasks), _per(r["bytes"], tasks), *(_per(r[p], tasks) for p in PEER_PARTS),
                 _per(r["lost"], tasks)]
        name = r["name"]
        if bold:
            cells, name = [f"**{c}**" for c in cells], f"**{name}**"
        return f"| {name} | " + " | ".join(cells) + " |\n"

    kinds = sorted((r for r in rows if r["table"] == "kind"), key=lambda r: _kind_key(r["name"]))
    body = "".join(line(r) for r in kinds)
    body += "".join(line(r, True) for r in rows if r["table"] == "total")
    body += "".join(line(r) for r in sorted((r for r in rows if r["table"] == "subset"),
                                             key=lambda r: SUBSETS.index(r["name"]) if r["name"] in SUBSETS else 9))
    return head + body


def _reference(rows: Mapping[str, Sequence[Mapping[str, Any]]], row: Mapping[str, Any]) -> Mapping[str, Any] | None:
    """The CoAP setting a peer's compares with: same loss, security on or off alike."""
    secure = row["security"] != "none"
    for rs in rows.values():
        r = rs[0]
        if r["system"] == "coap-distributed" and r["loss_pct"] == row["loss_pct"] and (r["security"] != "none") == secure:
            return next((x for x in rs if x["table"] == "total"), None)
    return None


def compare_table(rows: Iterable[Mapping[str, Any]], run_rows: Iterable[Mapping[str, Any]] = ()) -> str:
    """Every setting on one line, per task: bytes (the runs' own in
    brackets, from ``run_rows``; and against CoAP at the same loss, with or
    without security as the peer), packets, the comparison groups, the
    parts, the traffic on quiet flows, and the team's set-up before the
    window (per run)."""
    settings = _by_setting(rows)
    spread: dict[str, list[float]] = defaultdict(list)
    for r in run_rows:
        if int(float(r.get("tasks") or 0)):
            spread[str(r["setting"])].append(float(r["all_budget_bytes"]) / int(float(r["tasks"])))
    head = ("| setting | security | runs ok | bytes [runs] | ÷ CoAP | packets | set-up and discovery | messages "
            "| acks and keep-alives | other | Eth+IP+UDP/TCP | protocol headers, acks, control | crypto "
            "| encrypted, not split | payload | after 1 s of silence: packets, bytes "
            "| before the first reading (B per run) |\n"
            "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|--:|\n")
    body = ""
    for name, rs in settings.items():
        total = next((r for r in rs if r["table"] == "total"), None)
        if total is None:
            continue
        n = total["tasks"]
        ref = _reference(settings, total)
        ratio = f"{total['bytes'] / ref['bytes'] * ref['tasks'] / n:.2f}" if ref and ref["bytes"] else ""
        groups = {r["name"]: r["bytes"] for r in rs if r["table"] == "group"}
        setup = next((r["bytes"] for r in rs if r["table"] == "setup" and r["name"] == "total"), 0.0)
        framing = total["transport"] + total["acks"] + total["control"]
        idle = {r["name"]: r["value"] for r in rs if r["table"] == "idle"}
        each = sorted(spread.get(name, []))
        runs = f" [{each[0]:,.0f}-{each[-1]:,.0f}]" if len(each) > 1 else ""
        body += (f"| {name} | {total['security']} | {total['ok']}/{total['runs']} | {_per(total['bytes'], n)}{runs} "
                 f"| {ratio} "
                 f"| {_per(total['packets'], n)} | "
                 + " | ".join(_per(groups.get(g, 0.0), n) for g in COMPARE_GROUPS)
                 + f" | {_per(total['headers'], n)} | {_per(framing, n)} | {_per(total['crypto'], n)} "
                 f"| {_per(total['encrypted'], n)} | {_per(total['payload'], n)} "
                 f"| {_per(idle.get('idle_datagrams', 0), n)}, {_per(idle.get('idle_bytes', 0), n)} "
                 f"| {setup / max(1, total['runs']):,.0f} |\n")
    return head + body


def quic_tables(rows: Sequence[Mapping[str, Any]]) -> str:
    """One QUIC setting: its packets by header type, its 1-RTT datagrams by
    size, its connections' handshakes and its quiet-flow traffic."""
    tasks = rows[0]["tasks"]
    runs = max(1, rows[0]["runs"])
    out = ("| QUIC packet type | packets | bytes | header | protected (number, frames, tag) | of them coalesced |\n"
           "|---|--:|--:|--:|--:|--:|\n")
    for r in (r for r in rows if r["table"] == "quic-packet"):
        out += (f"| {r['name']} | {_per(r['packets'], tasks)} | {_per(r['bytes'], tasks)} "
                f"| {_per(r['transport'], tasks)} | {_per(r['encrypted'], tasks)} | {_per(r['value'], tasks)} |\n")
    sizes = {r["name"]: r["packets"] for r in rows if r["table"] == "quic-size"}

    def size_key(label: str) -> int:
        return int(label.split(" ")[1]) + (1 if label.startswith(">") else 0)

    if sizes:
        labels = sorted(sizes, key=size_key)
        out += ("\n| 1-RTT datagrams by UDP payload (B) | " + " | ".join(labels) + " |\n|---|"
                + "--:|" * len(labels) + "\n| per task | " + " | ".join(_per(sizes[x], tasks) for x in labels)
                + " |\n")
    c = {r["name"]: r["value"] for r in rows if r["table"] == "quic-connection"}
    idle = {r["name"]: r["value"] for r in rows if r["table"] == "idle"}
    conns = c.get("connections", 0)
    if conns:
        out += ("\n| connections per run (whole capture) | long-header packets per connection "
                "| bytes of their datagrams per connection | coalesced datagrams per run "
                "| connections opened in the window (per run) | packets with frames in clear "
                "| stream bytes sent again per task |\n|--:|--:|--:|--:|--:|--:|--:|\n")
        out += (f"| {conns / runs:.1f} | {c.get('long packets', 0) / conns:.1f} "
                f"| {c.get('long-header datagram bytes', 0) / conns:,.0f} | {c.get('coalesced datagrams', 0) / runs:.1f} "
                f"| {c.get('connections in the window', 0) / runs:.1f} "
                f"| {c.get('packets with frames in clear', 0):,.0f} of {c.get('packets', 0):,.0f} "
                f"| {_per(c.get('stream bytes sent again', 0), tasks)} |\n")
    if idle:
        out += idle_line(idle, tasks)
    return out


def idle_line(idle: Mapping[str, float], tasks: int) -> str:
    return (f"\nQuiet flows: {_per(idle.get('idle_datagrams', 0), tasks)} datagrams per task "
            f"({_per(idle.get('idle_bytes', 0), tasks)} B) came after at least {IDLE_GAP_S:g} s of silence on "
            f"their flow; the gaps of a quiet flow, one way, were {idle.get('gap_p10_s', 0):.2f} s (p10), "
            f"{idle.get('gap_median_s', 0):.2f} s (median), {idle.get('gap_p90_s', 0):.2f} s (p90).\n")


def rtps_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """One RTPS setting's bytes by endpoint and submessage, per task."""
    tasks = rows[0]["tasks"]
    out = ("| endpoint | submessage | count | bytes (submessage header included) | serialized payload |\n"
           "|---|---|--:|--:|--:|\n")
    for r in (r for r in rows if r["table"] == "rtps-submessage"):
        endpoint, _, sub = r["name"].partition(" / ")
        out += (f"| {endpoint} | {sub} | {_per(r['packets'], tasks)} | {_per(r['bytes'], tasks)} "
                f"| {_per(r['payload'], tasks)} |\n")
    idle = {r["name"]: r["value"] for r in rows if r["table"] == "idle"}
    if idle:
        out += idle_line(idle, tasks)
    return out
