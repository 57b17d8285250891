"""The byte budget: every datagram of one benchmark run, by kind and by part.

    sudo .venv/bin/python -m experiments.byte_budget [--loss 2] [--tasks 10] [--reps 1] [--insecure] [--keep DIR]
    sudo .venv/bin/python -m experiments.byte_budget --doc     # the runs of docs/byte-budget.md: CSVs and its tables
    .venv/bin/python -m experiments.byte_budget --read DIR ... # a kept run again (no root)
    .venv/bin/python -m experiments.byte_budget --from-csv [--doc]   # the tables from the committed CSVs
    sudo .venv/bin/python -m experiments.byte_budget --peers --doc [--reps 3]   # CoAP against its peers, by packets

One run is ``coapkb bench``'s own run (:func:`coapkb.bench.run.run_once`,
``coap-distributed``, by default 3 robots, 10 tasks, 35 kbit/s, 2 % loss,
security on), watched through the bench's own hooks (``run_once``'s
``testbed_class``, a testbed that also captures, and its ``observer``,
:class:`coapkb.bench.run.RunObserver`, which keeps the team's record):

* a packet capture in the testbed's bridge namespace
  (:class:`coapkb.bench.linkemu.capture.PacketCapture`): every frame each
  host put on its link, and whether the link delivered it;
* each process's wire trace (``COAPKB_WIRE_TRACE``,
  :mod:`coapkb.transport.coap.wire_trace`): what every datagram it sent
  carried in plaintext, OSCORE's inside included.

The budget is what each host sent between the bench's two counter readings
(team up; every robot idle), exactly: see :func:`load_run`.  Each datagram
is joined with its sender's trace line (source port, destination, Message
ID, token and length), put in one kind (:func:`classify`) and split into
parts (:func:`parts`); the sum over the robots' frames is compared with the
bench's own counters.  Then the workflow's minimum (:func:`minimum`): the
facts, states and task posts every robot needs, one packet each with the
least CoAP and OSCORE framing, and the ratio of what was sent to it.

The peers (``--peers``: Zenoh over TCP, QUIC and reliable UDP, DDS) keep
no trace: their datagrams are told apart from the packets alone, by
:mod:`byte_budget_peers` (QUIC headers and, in clear, frames; RTPS
submessages; TCP's roles), on the same capture and the same window, and
written to ``byte_budget_peers.csv`` (per setting: kinds, groups, parts,
QUIC packet types and connections, RTPS submessages) and
``byte_budget_peers_runs.csv`` (per run, against the bench's counters).

Writes ``experiments/results/byte_budget.csv`` (per run and kind),
``byte_budget_packets.csv`` (per datagram), ``byte_budget_runs.csv`` (per
run: the bench's counters and how much of them the budget explains) and
``byte_budget_minimum.csv``; with ``--doc``, the tables between the
``<!-- budget:NAME -->`` markers of ``docs/byte-budget.md``.  A run's raw
files (capture, traces, counter readings) stay in ``--keep DIR`` if given.
Only one benchmark may run on a machine at a time: start this under the
same lock as the others.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import json
import math
import os
import socket
import statistics
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import dpkt

from coapkb.agent.fact_push import FACTS_PATH
from coapkb.transport.coap.wire_trace import ENV, OSCORE_OPTION, CoapSplit, describe, split_coap
from experiments import byte_budget_peers as peers  # the peers' protocols (QUIC, RTPS): packets alone, no traces

if TYPE_CHECKING:
    from coapkb.bench.linkemu import Testbed
    from coapkb.bench.row import BenchRow
    from coapkb.harness.record import TeamRecord

ROOT = Path(__file__).resolve().parent.parent


RESULTS = ROOT / "experiments" / "results"
CSV_RUNS = RESULTS / "byte_budget.csv"
CSV_PACKETS = RESULTS / "byte_budget_packets.csv"
CSV_MINIMUM = RESULTS / "byte_budget_minimum.csv"
CSV_META = RESULTS / "byte_budget_runs.csv"
DOC = ROOT / "docs" / "byte-budget.md"

ETH_HEADER = 14
UDP_HEADER = 8
#: AES-CCM-16-64-128 (EDHOC cipher suite 2): OSCORE's tag.
AEAD_TAG = 8
#: The reliability layer spaces the copies of one try by 10 ms plus a small
#: datagram's airtime (25 ms at 35 kbit/s); a retry waits at least its
#: timeout (50 ms plus the exchange's airtime).  A repeat sooner than this is a copy.
HEDGE_GAP_S = 0.06
#: The least framing of one protected datagram: CoAP header 4, a 1-byte
#: token, an OSCORE option of flags, a 1-byte Partial IV and a 1-byte kid (1+3),
#: the payload marker, the inner code and the tag.
MIN_FRAMING_SECURE = 4 + 1 + 4 + 1 + 1 + AEAD_TAG
#: ... and of a plain one: header, token, marker.
MIN_FRAMING_PLAIN = 4 + 1 + 1
#: IPv4 (20) and UDP (8) under an Ethernet MTU of 1500.
MTU_PAYLOAD = 1500 - 20 - UDP_HEADER

#: The doc's runs: (setting, system, loss %, security).  ZeroMQ's is for
#: comparison: its messages are encrypted and not traced, so only TCP's roles.
DOC_RUNS = (("loss2", "coap-distributed", 2.0, True), ("loss20", "coap-distributed", 20.0, True),
            ("loss2-insecure", "coap-distributed", 2.0, False), ("zmq-distributed-loss2", "zmq-distributed", 2.0, True))
DOC_REPS = 3

#: The peers' comparison (``--peers``): (system, loss %, security), each
#: peer with CoAP's security where it has its own (OSCORE against Zenoh's
#: mutual TLS over TCP and QUIC), and without where it has none (Zenoh's
#: reliable UDP and DDS against CoAP without OSCORE).  A system the bench
#: does not have yet is left out.
PEER_RUNS = tuple((system, loss, security) for loss in (2.0, 20.0) for system, security in (
    ("coap-distributed", True), ("coap-distributed", False), ("zenoh-distributed", True),
    ("zenoh-quic-distributed", True), ("zenoh-udp-distributed", False), ("dds-distributed", False)))
CSV_PEERS = RESULTS / "byte_budget_peers.csv"
CSV_PEERS_RUNS = RESULTS / "byte_budget_peers_runs.csv"

PART_COLUMNS = ("headers", "coap", "options", "oscore", "inner_options", "payload")


# --------------------------------------------------------------------------- frames


@dataclass
class Datagram:
    """One UDP datagram a host put on its link (one captured ``in`` frame)."""

    t: float
    src: str
    dst: str
    sport: int
    dport: int
    frame: int
    headers: int
    data: bytes
    coap: CoapSplit | None = None
    lost: bool = True
    delivered_t: float | None = None
    record: dict[str, Any] | None = None
    #: What it carries, in plaintext: as traced, or decoded from the wire.
    plain: dict[str, Any] | None = None
    kind: str = "other"
    detail: str = ""
    copy: str = "first"
    block: bool = False
    parts: dict[str, int] = field(default_factory=dict)
    #: A TCP segment's flags and sequence number (ZeroMQ's systems), else None.
    tcp: tuple[int, int] | None = None
    #: What the UDP payload is: ``coap``, ``quic`` (Zenoh's QUIC and reliable
    #: UDP links) or ``rtps`` (DDS); ``tcp`` for a TCP segment.
    proto: str = "coap"
    #: A QUIC datagram's packets, an RTPS datagram's message (see byte_budget_peers).
    quic: list[Any] | None = None
    rtps: Any = None
    #: QUIC stream bytes it sent again (in clear only).
    quic_again: int = 0
    #: An IPv4 fragment after the first: the datagram whose first fragment
    #: carries the UDP header (that one's ``data`` is the whole datagram).
    fragment_of: Datagram | None = None
    #: The IPv4 fragments after the first, of a fragmented datagram.
    fragments: int = 0
    #: False for a fragmented datagram some fragment of which was not seen.
    whole: bool = True

    @property
    def oscore(self) -> bool:
        return self.coap is not None and any(n == OSCORE_OPTION for n, _ in self.coap.options)

    @property
    def client(self) -> tuple[str, int]:
        return (self.src, self.sport) if self.is_request else (self.dst, self.dport)

    @property
    def is_request(self) -> bool:
        return self.coap is not None and 1 <= self.coap.code < 32

    @property
    def is_response(self) -> bool:
        return self.coap is not None and self.coap.code >= 64


def ipv4(frame: bytes) -> dpkt.ip.IP | None:
    """The IPv4 packet of an Ethernet frame, dissected by dpkt (its UDP or
    TCP segment too, unless it is a fragment after the first), else None."""
    try:
        ip = dpkt.ethernet.Ethernet(frame).data
    except dpkt.Error:
        return None
    return ip if isinstance(ip, dpkt.ip.IP) else None


def _udp(ip: dpkt.ip.IP) -> tuple[str, str, int, int, int, bytes] | None:
    udp = ip.data
    if not isinstance(udp, dpkt.udp.UDP):
        return None
    return (socket.inet_ntoa(ip.src), socket.inet_ntoa(ip.dst), udp.sport, udp.dport,
            ETH_HEADER + ip.hl * 4 + UDP_HEADER, bytes(udp.data))


def parse_frame(frame: bytes) -> tuple[str, str, int, int, int, bytes] | None:
    """(source IP, destination IP, source port, destination port, header
    bytes, UDP payload) of an Ethernet/IPv4/UDP frame, else None."""
    ip = ipv4(frame)
    return None if ip is None else _udp(ip)


@dataclass(frozen=True)
class OtherFrame:
    """A frame that is not UDP over IPv4 (an ICMP error, say): who sent it, when, how long."""

    t: float
    src: str
    dst: str
    frame: int
    icmp: bool


_SYN, _FIN, _RST = 0x02, 0x01, 0x04

#: What a run's UDP datagrams carry, by the bench's transport scheme (CoAP's otherwise).
UDP_PROTOCOL = {"zenoh+quic": "quic", "zenoh+udp": "quic-plain", "dds": "rtps"}


def datagrams_from_capture(frames: Iterable[Any], hosts: Mapping[str, str],
                           udp: str = "coap") -> tuple[list[Datagram], list[OtherFrame]]:
    """The datagrams the hosts sent (``in`` frames), each marked delivered if
    its ``out`` copy was seen; and the other frames they sent (not UDP/IPv4).
    ``hosts``: IP address -> host name.  ``udp``: what the UDP datagrams
    carry (``coap``, ``quic``, ``quic-plain``, ``rtps``; see
    :data:`UDP_PROTOCOL`).  An IPv4 fragment after a datagram's first is a
    datagram of its own (``fragment_of`` the first), and the first's
    ``data`` the whole datagram once every fragment was seen.  Ethernet,
    IPv4, UDP and TCP are dissected by dpkt."""
    sent: list[Datagram] = []
    waiting: dict[bytes, list[Datagram]] = defaultdict(list)
    other: list[OtherFrame] = []
    pieces: dict[tuple[Any, ...], dict[str, Any]] = {}
    proto = udp.split("-")[0]
    for f in sorted(frames, key=lambda f: f.t):
        if f.direction == "in":
            ip = ipv4(f.frame)
            parsed = None if ip is None or ip.offset else _udp(ip)
            if ip is not None and ip.offset:  # an IPv4 fragment after the first
                d = _continuation(f, ip, hosts, pieces, proto)
                if d is None:
                    other.append(_other_frame(f, ip, hosts))
                    continue
            elif ip is not None and isinstance(ip.data, dpkt.tcp.TCP):
                tcp = ip.data
                src, dst = socket.inet_ntoa(ip.src), socket.inet_ntoa(ip.dst)
                d = Datagram(f.t, hosts.get(src, src), hosts.get(dst, dst), tcp.sport, tcp.dport, len(f.frame),
                             ETH_HEADER + ip.hl * 4 + tcp.off * 4, bytes(tcp.data), tcp=(tcp.flags, tcp.seq),
                             proto="tcp")
            elif ip is None or parsed is None:
                other.append(_other_frame(f, ip, hosts))
                continue
            else:
                src, dst, sport, dport, headers, data = parsed
                d = Datagram(f.t, hosts.get(src, src), hosts.get(dst, dst), sport, dport, len(f.frame), headers,
                             data, proto=proto)
                if ip.mf:  # the first fragment: its UDP header and the start
                    d.whole = False
                    p = pieces.setdefault((src, dst, ip.id), {"head": None, "parts": {}, "end": None})
                    p["head"] = d
                    p["parts"][0] = ip.data.pack_hdr() + data
                elif proto == "coap":
                    try:
                        d.coap = split_coap(data)
                    except ValueError:
                        d.coap = None
            sent.append(d)
            waiting[f.frame].append(d)
        else:
            copies = waiting.get(f.frame)
            if copies:
                d = copies.pop(0)
                d.lost, d.delivered_t = False, f.t
    for p in pieces.values():  # the whole datagram, where every fragment was seen
        head, parts = p["head"], p["parts"]
        if head is None or p["end"] is None:
            continue
        whole, at = b"", 0
        for offset in sorted(parts):
            if offset != at:
                break
            whole += parts[offset]
            at += len(parts[offset])
        else:
            if at == p["end"]:
                head.data, head.whole = whole[UDP_HEADER:], True
    return sent, other


def _continuation(f: Any, ip: dpkt.ip.IP, hosts: Mapping[str, str],
                  pieces: dict[tuple[Any, ...], dict[str, Any]], proto: str) -> Datagram | None:
    """An IPv4 fragment after the first, as a datagram of its own (no UDP header)."""
    if ip.p != dpkt.ip.IP_PROTO_UDP:
        return None
    src, dst = socket.inet_ntoa(ip.src), socket.inet_ntoa(ip.dst)
    offset = ip.offset * 8
    p = pieces.setdefault((src, dst, ip.id), {"head": None, "parts": {}, "end": None})
    piece = bytes(ip.data)
    p["parts"][offset] = piece
    if not ip.mf:
        p["end"] = offset + len(piece)
    head = p["head"]
    d = Datagram(f.t, hosts.get(src, src), hosts.get(dst, dst), 0 if head is None else head.sport,
                 0 if head is None else head.dport, len(f.frame), ETH_HEADER + ip.hl * 4, b"", proto=proto,
                 fragment_of=head)
    if head is not None:
        head.fragments += 1
    else:
        d.whole = False
    return d


def _other_frame(f: Any, ip: dpkt.ip.IP | None, hosts: Mapping[str, str]) -> OtherFrame:
    if ip is None:
        return OtherFrame(f.t, "?", "?", len(f.frame), False)
    return OtherFrame(f.t, hosts.get(socket.inet_ntoa(ip.src), "?"), hosts.get(socket.inet_ntoa(ip.dst), "?"),
                      len(f.frame), ip.p == dpkt.ip.IP_PROTO_ICMP)


# --------------------------------------------------------------------------- traces


def read_traces(directory: Path) -> list[dict[str, Any]]:
    records = []
    for path in sorted(directory.glob("wire-*.jsonl")):
        with path.open(encoding="utf-8") as lines:
            records += [json.loads(line) for line in lines if line.strip()]
    return sorted(records, key=lambda r: r["t"])


def _record_key(r: Mapping[str, Any]) -> tuple[Any, ...]:
    host, _, port = str(r["dst"]).rpartition(":")
    return (int(r["port"]), host.strip("[]"), int(port), int(r["mid"]), str(r["token"]), int(r["len"]))


def join_traces(datagrams: Sequence[Datagram], records: Sequence[Mapping[str, Any]],
                hosts: Mapping[str, str]) -> list[Mapping[str, Any]]:
    """Give each datagram its sender's trace line (same source port,
    destination, Message ID, token and length; repeats in order); returns
    the lines no datagram took."""
    address = {name: ip for ip, name in hosts.items()}
    by_key: dict[tuple[Any, ...], list[Mapping[str, Any]]] = defaultdict(list)
    for r in records:
        by_key[_record_key(r)].append(r)
    for d in datagrams:
        if d.coap is None:
            continue
        key = (d.sport, address.get(d.dst, d.dst), d.dport, d.coap.mid, d.coap.token.hex(), len(d.data))
        candidates = by_key.get(key)
        if candidates:
            # The line written before the frame reached the bridge, latest first
            # (a datagram may wait in its host's shaper for a while).
            before = [r for r in candidates if r["t"] <= d.t + 0.05]
            chosen = before[0] if before else candidates[0]
            candidates.remove(chosen)
            d.record = dict(chosen)
    return [r for rs in by_key.values() for r in rs]


_METHODS = {"0.01": "GET", "0.02": "POST", "0.03": "PUT", "0.04": "DELETE", "0.05": "FETCH", "0.06": "PATCH",
            "0.07": "iPATCH"}


def plaintext(d: Datagram) -> dict[str, Any] | None:
    """What ``d`` carries in plaintext: its trace line's account, or (plain
    CoAP only) its own options decoded."""
    if d.record is not None:
        r = d.record
        out = {k: v for k, v in r.items() if k in ("path", "query", "observe", "block2", "payload", "edhoc", "req")}
        code = str(r.get("inner_code") or r.get("code"))
        out["code"] = _METHODS.get(code, code)  # an unprotected request's line names its method by number
        return out
    if d.coap is None or d.oscore:
        return None
    import aiocoap

    try:
        message = aiocoap.Message.decode(d.data)
    except Exception:  # noqa: BLE001 -- not CoAP after all
        return None
    return describe(message)


# --------------------------------------------------------------------------- parts


def parts(d: Datagram) -> dict[str, int]:
    """``d``'s bytes by part: ``headers`` (Ethernet, IPv4, UDP), ``coap``
    (header and token), ``options`` (the outer options but OSCORE's; for a
    plain message with its payload marker), ``oscore`` (the OSCORE option,
    the ciphertext's marker, the tag, and the inner code, options and marker
    that OSCORE moves inside), ``inner_options`` (of ``oscore``: the inner
    code, options and marker), ``payload`` (the application's payload, inside
    OSCORE when protected).  They add up to the frame."""
    out = dict.fromkeys(PART_COLUMNS, 0)
    out["headers"] = d.headers
    c = d.coap
    if c is None:
        out["payload"] = len(d.data) if d.tcp is not None else d.frame - d.headers
        out["headers"] = d.frame - out["payload"]
        return out
    out["coap"] = c.header + len(c.token)
    if not d.oscore:
        out["options"] = c.option_bytes + c.marker
        out["payload"] = c.payload
    else:
        out["options"] = c.option_bytes - c.option_size(OSCORE_OPTION)
        inner_total = c.payload - AEAD_TAG
        inner_payload = (d.plain or {}).get("payload")
        if inner_payload is None:  # not traced: the smallest inner framing (the code)
            inner_payload = max(0, inner_total - 1)
        out["inner_options"] = inner_total - inner_payload
        out["oscore"] = c.option_size(OSCORE_OPTION) + c.marker + AEAD_TAG + out["inner_options"]
        out["payload"] = inner_payload
    out["headers"] += d.frame - d.headers - len(d.data)  # link padding, if any
    return out


# --------------------------------------------------------------------------- kinds

#: Kinds in the order of the tables, by group.
GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("EDHOC", ("EDHOC message_1", "EDHOC message_2", "EDHOC message_3", "EDHOC message_4")),
    ("named queries", ("query", "answer")),
    ("observation", ("registration", "registration answer", "notification")),
    ("task feed", ("task post", "task answer")),
    ("decisions", ("decision post", "decision answer")),
    ("knowledge writes", ("write", "write answer", "replication", "replication answer")),
    ("liveness and membership", ("liveness", "liveness answer", "hearsay", "hearsay answer", "lease", "lease answer")),
    ("acknowledgements", ("empty ACK", "reset")),
    ("errors", ("error answer",)),
    ("TCP (ZeroMQ)", ("TCP handshake", "TCP data", "TCP ACK", "TCP close")),
    ("other", ("stats", "stats answer", "other request", "other answer", "ICMP error", "other")),
)
_ANSWER_OF = {"EDHOC message_1": "EDHOC message_2", "EDHOC message_3": "EDHOC message_4", "query": "answer",
              "registration": "registration answer", "task post": "task answer", "decision post": "decision answer",
              "liveness": "liveness answer", "hearsay": "hearsay answer", "lease": "lease answer",
              "stats": "stats answer", "other request": "other answer", "write": "write answer",
              "replication": "replication answer"}


def request_kind(plain: Mapping[str, Any]) -> tuple[str, str]:
    """(kind, detail) of a request from its plaintext (code, path, query, observe, edhoc)."""
    path = plain.get("path") or ""
    query = plain.get("query") or ""
    code = plain.get("code")
    if path == "/.well-known/edhoc":
        return ("EDHOC message_1" if plain.get("edhoc") == 1 else "EDHOC message_3"), ""
    if path.startswith("/kb/q/"):
        return "query", path[len("/kb/q/"):]
    if path == "/kb/sparql":
        return "query", "sparql"
    if path.startswith(FACTS_PATH) and plain.get("observe") == 0:
        return "registration", FACTS_PATH
    if path in ("/robot/plan", "/robot/state", "/robot/outcome"):
        if plain.get("observe") == 0:
            return "registration", path
        if "of=" in query:
            return "hearsay", path
        return "liveness", path
    if path == "/robot/lease":
        return "lease", path
    if path == "/tasks":
        return ("task post", "") if code == "POST" else ("other request", "GET /tasks")
    if path == "/decisions":
        return "decision post", ""
    if path == "/robot/stats":
        return "stats", ""
    if path == "/kb" and code in ("PATCH", "iPATCH"):
        return "write", ""
    if path == "/kb/sync":
        return "replication", ""
    return "other request", f"{code} {path}"


def classify(datagrams: Sequence[Datagram], others: Sequence[OtherFrame] = (), udp: str = "coap") -> None:
    """Give every datagram its kind, detail, copy (``first``,
    ``retransmission``: the same Message ID again; ``retry``: the same
    request again as a new message after its try went unanswered; ``hedge``:
    a copy of a try sent before any answer could come, or the same query to
    another holder) and parts.  Answers take their request's kind and copy.
    ``others``: the frames that are not datagrams; an ICMP error between two
    copies makes the second a retry (the layer sends again at once).
    ``udp``: what the UDP datagrams carry (:data:`UDP_PROTOCOL`): QUIC's and
    RTPS's are classified by :mod:`byte_budget_peers`, from their packets."""
    heads = [d for d in datagrams if d.fragment_of is None and d.proto in ("quic", "rtps")]
    if udp.startswith("quic"):
        peers.classify_quic([d for d in heads if d.proto == "quic"], plaintext=udp == "quic-plain")
    elif udp == "rtps":
        peers.classify_rtps([d for d in heads if d.proto == "rtps"])
    for d in datagrams:
        if d.fragment_of is not None or (d.proto in ("quic", "rtps") and not d.whole):
            _classify_fragment(d)
    ordered = sorted((d for d in datagrams if d.proto in ("coap", "tcp") and d.fragment_of is None
                      and not d.fragments), key=lambda d: d.t)
    errors = [(o.t, o.src, o.dst) for o in others if o.icmp]
    for d in ordered:
        d.plain = plaintext(d)
    # The earliest answer each request token got delivered to its client.
    answered: dict[tuple[Any, ...], float] = {}
    for d in ordered:
        if d.is_response and d.delivered_t is not None and d.coap is not None:
            key = (d.dst, d.dport, d.src, d.sport, d.coap.token)
            answered[key] = min(answered.get(key, math.inf), d.delivered_t)
    seen_mids: set[tuple[Any, ...]] = set()
    confirmable: dict[tuple[Any, ...], Datagram] = {}  # (sender, receiver, MID) of each CON
    requests: dict[tuple[Any, ...], Datagram] = {}  # (client, server, token) -> request
    last_same: dict[tuple[Any, ...], Datagram] = {}  # (client, signature) -> latest request
    answer_mids: dict[tuple[Any, ...], list[int]] = defaultdict(list)
    for d in ordered:
        c = d.coap
        d.parts = parts(d)
        if c is None:
            if d.tcp is not None:
                _classify_tcp(d, seen_mids)
            else:
                d.kind, d.detail = "other", "not CoAP"
            continue
        sender = (d.src, d.sport, d.dst, d.dport, c.mtype, c.mid)
        again = sender in seen_mids
        seen_mids.add(sender)
        plain = d.plain or {}
        if c.code == 0:
            d.kind = "empty ACK" if c.mtype == 2 else "reset" if c.mtype == 3 else "other"
            d.copy = "retransmission" if again else "first"
            answered_con = confirmable.get((d.dst, d.dport, d.src, d.sport, c.mid))
            if answered_con is not None:  # what it acknowledges (or resets)
                d.detail = _kind_label(answered_con)
            continue
        if c.mtype == 0:
            confirmable[sender[:4] + (c.mid,)] = d
        if d.is_request:
            if not plain:
                d.kind, d.detail = "other request", "protected, not traced"
            else:
                d.kind, d.detail = request_kind(plain)
                block = plain.get("block2")
                d.block = bool(block and block[0] > 0)
            if again:
                d.copy = "retransmission"
            else:
                d.copy = _copy_of(d, plain, last_same, answered, errors)
            requests.setdefault((d.src, d.sport, d.dst, d.dport, c.token), d)
            continue
        # A response: its request's kind, from the server's account or the request itself.
        request = requests.get((d.dst, d.dport, d.src, d.sport, c.token))
        asked = plain.get("req")
        if asked:
            kind, detail = request_kind(asked)
        elif request is not None:
            kind, detail = request.kind, request.detail
        else:
            kind, detail = "other request", "unknown request"
        mids = answer_mids[(d.src, d.sport, d.dst, d.dport, c.token)]
        if c.mid not in mids:
            mids.append(c.mid)
        if c.code >= 128:  # 4.xx, 5.xx
            d.kind, d.detail = "error answer", f"{c.code >> 5}.{c.code & 0x1F:02d} to {kind} {detail}".strip()
        elif kind == "registration" and mids.index(c.mid) > 0:
            d.kind, d.detail = "notification", detail
        else:
            d.kind, d.detail = _ANSWER_OF.get(kind, "other answer"), detail
        if request is not None:
            d.block = request.block
        if again:
            d.copy = "retransmission"
        elif request is not None and d.kind != "notification":
            d.copy = request.copy
    peers.split_tls([d for d in ordered if d.tcp is not None])  # Zenoh over TCP with TLS: its records


def _classify_fragment(d: Datagram) -> None:
    """An IPv4 fragment after a datagram's first: its first's kind; its own
    parts only Ethernet and IPv4 (its bytes beyond are in its first's parts,
    split with the whole datagram).  One whose first was not seen (or the
    first of one not whole) is ``IP fragment``."""
    head = d.fragment_of if d.fragment_of is not None else d
    if not head.whole:
        d.kind, d.detail = "IP fragment", "its datagram not whole in the capture"
        d.parts = dict.fromkeys(peers.PEER_PARTS, 0) | {"headers": d.headers, "payload": d.frame - d.headers}
        return
    # Its payload bytes are in its first's parts, split with the whole datagram.
    d.kind, d.detail, d.copy = head.kind, f"{head.detail} (IP fragment)".strip(), head.copy
    d.parts = dict.fromkeys(peers.PEER_PARTS, 0) | {"headers": d.headers}


def _classify_tcp(d: Datagram, seen: set[tuple[Any, ...]]) -> None:
    """A TCP segment's kind (ZeroMQ's systems: CurveZMQ hides the messages,
    so only TCP's own roles): handshake, data, pure ACK, close; a data
    segment with the same sequence number and length again is a retransmission."""
    assert d.tcp is not None
    flags, seq = d.tcp
    if flags & _SYN:
        d.kind = "TCP handshake"
    elif flags & (_FIN | _RST):
        d.kind = "TCP close"
    elif d.data:
        d.kind = "TCP data"
        key = ("tcp", d.src, d.sport, d.dst, d.dport, seq, len(d.data))
        d.copy = "retransmission" if key in seen else "first"
        seen.add(key)
    else:
        d.kind = "TCP ACK"


def _signature(d: Datagram, plain: Mapping[str, Any]) -> tuple[Any, ...]:
    block = plain.get("block2")
    return (plain.get("code"), plain.get("path"), plain.get("query"), plain.get("observe"),
            None if block is None else block[0], plain.get("payload"))


def _copy_of(d: Datagram, plain: Mapping[str, Any], last_same: dict[tuple[Any, ...], Datagram],
             answered: Mapping[tuple[Any, ...], float], errors: Sequence[tuple[float, str, str]] = ()) -> str:
    """``first``, ``retry`` or ``hedge`` for a new request message ``d``: a
    repeat of the client's latest request of the same signature (to the same
    server; for a named query, to any holder) that had no answer yet."""
    assert d.coap is not None
    query = d.kind == "query"
    key = (d.src, d.sport, None if query else (d.dst, d.dport), _signature(d, plain))
    previous = last_same.get(key)
    last_same[key] = d
    if previous is None or previous.coap is None:
        return "first"
    sent = _sent_at(d)
    got = answered.get((previous.src, previous.sport, previous.dst, previous.dport, previous.coap.token), math.inf)
    if got <= sent:
        return "first"  # the same request again, after an answer: a new exchange
    if previous.dst != d.dst:
        return "hedge"  # the same query to another holder
    if any(previous.t <= t <= d.t and src == previous.dst and dst == d.src for t, src, dst in errors):
        return "retry"  # sent again at once after an ICMP error
    return "hedge" if sent - _sent_at(previous) < HEDGE_GAP_S else "retry"


def _sent_at(d: Datagram) -> float:
    return float(d.record["t"]) if d.record is not None else d.t


# --------------------------------------------------------------------------- runs


@dataclass
class Run:
    """One traced bench run, read back."""

    name: str
    loss: float
    security: bool
    tasks: int
    robots: list[str]
    row: dict[str, Any]
    window: tuple[float, float]
    #: Per host: (tx bytes, tx packets) the bench's counters saw in the window.
    counted: dict[str, tuple[int, int]]
    datagrams: list[Datagram]
    unmatched_records: int = 0
    untraced_protected: int = 0
    outside: int = 0
    #: Per-peer reliability counters the robots reported (retries, hedge copies, ...).
    path_stats: dict[str, int] = field(default_factory=dict)
    #: The budget's frames are exactly those the counters counted (see :func:`load_run`).
    exact: bool = True
    #: Per host: bytes sent before the bench's first reading (the team starting up).
    before_window: dict[str, int] = field(default_factory=dict)
    #: The datagrams sent before the first reading (the team coming up: handshakes, discovery).
    setup: list[Datagram] = field(default_factory=list)
    #: What its UDP datagrams carried (:data:`UDP_PROTOCOL`).
    udp: str = "coap"

    @property
    def system(self) -> str:
        return str(self.row.get("system") or "coap-distributed")


def load_run(directory: Path, name: str | None = None) -> Run:
    """A run directory written by :func:`traced_run`, joined and classified.

    The budget is what each host sent between the bench's two counter
    readings.  The capture holds every frame since the links came up, so the
    frames a reading counted are exactly the first ``tx_packets`` a host
    sent (their bytes must add up to ``tx_bytes``: checked); where they do
    not, the frames between the readings' times are taken (``exact`` False)."""
    from coapkb.bench.linkemu.capture import read_frames

    meta = json.loads((directory / "run.json").read_text(encoding="utf-8"))
    hosts = {ip: host for host, ip in meta["hosts"].items()}
    before, end = meta["readings"][0], meta["readings"][1]
    udp = UDP_PROTOCOL.get(str(meta["row"].get("transport")), "coap")
    datagrams, others = datagrams_from_capture(read_frames(directory / "capture.jsonl"), hosts, udp)
    records = read_traces(directory / "wire") if (directory / "wire").is_dir() else []
    unmatched = join_traces(datagrams, records, hosts)
    classify(datagrams, others, udp)
    frames: list[Datagram] = list(datagrams)
    for o in others:  # not UDP: in the budget as what they are
        d = Datagram(o.t, o.src, o.dst, 0, 0, o.frame, o.frame, b"", lost=False)
        d.kind, d.detail = ("ICMP error" if o.icmp else "other"), ("" if o.icmp else "not UDP/IPv4")
        d.parts = dict.fromkeys(PART_COLUMNS, 0) | {"headers": o.frame}
        frames.append(d)
    counted: dict[str, tuple[int, int]] = {}
    before_window: dict[str, int] = {}
    inside: list[Datagram] = []
    setup: list[Datagram] = []
    exact = True
    window = (before["t1"], end["t0"])
    for host in meta["hosts"]:
        b0, p0 = before["counters"][host]["tx_bytes"], before["counters"][host]["tx_packets"]
        b1, p1 = end["counters"][host]["tx_bytes"], end["counters"][host]["tx_packets"]
        counted[host] = (b1 - b0, p1 - p0)
        sent = sorted((d for d in frames if d.src == host), key=lambda d: d.t)
        if len(sent) >= p1 and sum(d.frame for d in sent[:p0]) == b0 and sum(d.frame for d in sent[:p1]) == b1:
            early, mine = sent[:p0], sent[p0:p1]
        else:
            exact = False
            early = [d for d in sent if d.t < window[0]]
            mine = [d for d in sent if window[0] <= d.t <= window[1]]
        inside += mine
        setup += early
        before_window[host] = sum(d.frame for d in early)
    row = meta["row"]
    first = min((d.t for d in inside), default=window[0])
    last = max((d.t for d in inside), default=window[1])
    return Run(
        name=name or directory.name, loss=float(row["loss_pct"]), security=row["security"] != "none",
        tasks=int(row["tasks"]), robots=[h for h in meta["hosts"] if h.startswith("Robot")], row=row,
        window=(first, last), counted=counted, datagrams=sorted(inside, key=lambda d: d.t),
        unmatched_records=sum(1 for r in unmatched if first <= r["t"] <= last),
        untraced_protected=sum(1 for d in inside if d.oscore and d.record is None),
        outside=len(frames) - len(inside), path_stats=meta.get("path_stats", {}), exact=exact,
        before_window=before_window, setup=sorted(setup, key=lambda d: d.t), udp=udp,
    )


class _CaptureSetup:
    """What the traced run adds to a bench run: where its files go, the
    counter readings (with their times) the bench takes, and the team's
    record (a :class:`coapkb.bench.run.RunObserver`)."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.readings: list[dict[str, Any]] = []
        self.hosts: dict[str, str] = {}
        self.record: TeamRecord | None = None

    def team_recorded(self, row: BenchRow, record: TeamRecord) -> None:
        self.record = record

    def testbed_class(self) -> type[Testbed]:
        from coapkb.bench.linkemu import Testbed
        from coapkb.bench.linkemu.capture import PacketCapture

        setup = self

        class CapturingTestbed(Testbed):
            def setup(self) -> None:
                super().setup()
                setup.hosts = {name: h.address for name, h in self.hosts.items()}
                self._capture = PacketCapture(self.bridge_netns, setup.directory / "capture.jsonl")
                self._capture.start()

            async def acounters(self) -> Any:
                t0 = time.time()
                counters = await super().acounters()
                setup.readings.append({"t0": t0, "t1": time.time(),
                                       "counters": {h: vars(c) for h, c in counters.items()}})
                return counters

            def close(self) -> None:
                capture = getattr(self, "_capture", None)
                if capture is not None:
                    self._capture = None
                    capture.stop()
                super().close()

        return CapturingTestbed


async def traced_run(directory: Path, *, system: str = "coap-distributed", robots: int = 3, tasks: int = 10,
                     bandwidth: float = 35.0, loss: float = 2.0, rep: int = 0, security: bool = True,
                     writable: bool = False) -> dict[str, Any]:
    """One ``coapkb bench`` run with the capture and the wire traces on; its
    files in ``directory``; returns its row."""
    from coapkb.bench.run import run_once

    directory.mkdir(parents=True, exist_ok=True)
    setup = _CaptureSetup(directory)
    previous = os.environ.get(ENV)
    os.environ[ENV] = str(directory / "wire")
    try:
        row = await run_once(system, robots, tasks, bandwidth, loss, rep, security=security, kb_writable=writable,
                             observer=setup, testbed_class=setup.testbed_class())
    finally:
        if previous is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = previous
    stats: Counter[str] = Counter()
    if setup.record is not None:
        for robot in setup.record.robot_stats.values():
            for layer in (robot.retransmission, robot.server_retransmission):
                for peer in ((layer or {}).get("peers") or {}).values():
                    for key in ("attempts", "retries", "hedge_copies", "notifications", "notification_retransmissions"):
                        stats[key] += int(peer.get(key) or 0)
    meta = {"row": row.to_dict(), "hosts": setup.hosts, "readings": setup.readings, "path_stats": dict(stats)}
    (directory / "run.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return meta["row"]


# --------------------------------------------------------------------------- tables


@dataclass
class Line:
    """One line of a budget table: datagrams of a kind (or a subset)."""

    label: str
    packets: int = 0
    lost: int = 0
    bytes: int = 0
    parts: Counter[str] = field(default_factory=Counter)

    def add(self, d: Datagram) -> None:
        self.packets += 1
        self.lost += d.lost
        self.bytes += d.frame
        self.parts.update(d.parts)


def _kind_label(d: Datagram) -> str:
    if d.kind in ("query", "answer") or (d.kind in ("registration", "registration answer", "notification") and d.detail):
        return f"{d.kind} {d.detail}"
    return d.kind


def _kind_order(label: str) -> tuple[int, int, str]:
    for g, (_, kinds) in enumerate(GROUPS):
        for k, kind in enumerate(kinds):
            if label == kind or label.startswith(kind + " "):
                return g, k, label
    return len(GROUPS), 0, label


def budget_lines(datagrams: Iterable[Datagram]) -> tuple[list[Line], list[Line], Line]:
    """The kind lines (every datagram in one), the subset lines (copies,
    block-wise, lost) and the total."""
    datagrams = list(datagrams)
    again = ("of which retransmissions (same TCP sequence number)" if any(d.tcp is not None for d in datagrams)
             else "of which retransmissions (same Message ID)")
    kinds: dict[str, Line] = {}
    subsets = {name: Line(name) for name in (
        again, "of which retries (new message, same request)",
        "of which hedged copies", "of which block-wise continuations", "of which lost on the link")}
    total = Line("total")
    for d in datagrams:
        label = _kind_label(d)
        kinds.setdefault(label, Line(label)).add(d)
        total.add(d)
        if d.copy == "retransmission":
            subsets[again].add(d)
        elif d.copy == "retry":
            subsets["of which retries (new message, same request)"].add(d)
        elif d.copy == "hedge":
            subsets["of which hedged copies"].add(d)
        if d.block:
            subsets["of which block-wise continuations"].add(d)
        if d.lost:
            subsets["of which lost on the link"].add(d)
    return sorted(kinds.values(), key=lambda line: _kind_order(line.label)), list(subsets.values()), total


def _per(value: float, n: int) -> str:
    v = value / n
    if abs(v) >= 10:
        return f"{v:,.0f}"
    return f"{v:.2f}" if 0 < abs(v) < 0.1 else f"{v:.1f}"


def budget_table(runs: Sequence[Run]) -> str:
    """The markdown budget of ``runs`` (one setting; values per task, over every run)."""
    n = sum(r.tasks for r in runs)
    lines, subsets, total = budget_lines(d for r in runs for d in r.datagrams)
    transport = "TCP" if any(d.tcp is not None for r in runs for d in r.datagrams) else "UDP"
    head = (f"| kind | packets | bytes | Eth+IP+{transport} | CoAP hdr+token | outer options | OSCORE "
            "| (inner code+options) | payload | lost packets |\n|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|\n")

    def row(line: Line, bold: bool = False) -> str:
        cells = [_per(line.packets, n), _per(line.bytes, n)] + [_per(line.parts[p], n) for p in PART_COLUMNS]
        cells.append(_per(line.lost, n))
        label = f"**{line.label}**" if bold else line.label
        if bold:
            cells = [f"**{c}**" for c in cells]
        return f"| {label} | " + " | ".join(cells) + " |\n"

    body = "".join(row(line) for line in lines) + row(total, bold=True)
    body += "".join(row(s) for s in subsets if s.packets)
    return head + body


def _frame_bytes_by(runs: Sequence[Run], key: Callable[[Datagram], str]) -> Counter[str]:
    """The runs' frame bytes summed by ``key`` of each datagram."""
    sums: Counter[str] = Counter()
    for r in runs:
        for d in r.datagrams:
            sums[key(d)] += d.frame
    return sums


def group_table(settings: Mapping[str, Sequence[Run]]) -> str:
    """Bytes per task by group of kinds, one column per setting."""
    names = list(settings)
    head = "| group | " + " | ".join(names) + " |\n|---|" + "--:|" * len(names) + "\n"
    per_group: dict[str, dict[str, float]] = defaultdict(dict)
    for name, runs in settings.items():
        n = sum(r.tasks for r in runs)
        totals = _frame_bytes_by(runs, lambda d: _group_of(d.kind))
        for g, _ in GROUPS:
            per_group[g][name] = totals[g] / n
        per_group["total"][name] = sum(totals.values()) / n
    body = ""
    for g in [*(g for g, _ in GROUPS), "total"]:
        values = per_group[g]
        if g != "total" and not any(values.values()):
            continue
        label = f"**{g}**" if g == "total" else g
        body += f"| {label} | " + " | ".join(f"{values.get(nm, 0):,.0f}" for nm in names) + " |\n"
    return head + body


def _group_of(kind: str) -> str:
    for g, kinds in GROUPS:
        if kind in kinds:
            return g
    return "other"


def explained(run: Run) -> dict[str, Any]:
    """The budget against the bench's own counters: robots, feeder, all."""
    out: dict[str, Any] = {"run": run.name}
    groups = {"robots": run.robots, "feeder": ["feeder"], "all": list(run.counted)}
    for label, hosts in groups.items():
        budget = sum(d.frame for d in run.datagrams if d.src in hosts)
        classified = sum(d.frame for d in run.datagrams if d.src in hosts and d.kind != "other")
        counted = sum(run.counted[h][0] for h in hosts if h in run.counted)
        out[f"{label}_counted_bytes"] = counted
        out[f"{label}_budget_bytes"] = budget
        out[f"{label}_classified_bytes"] = classified
        out[f"{label}_packets_counted"] = sum(run.counted[h][1] for h in hosts if h in run.counted)
        out[f"{label}_packets_budget"] = sum(1 for d in run.datagrams if d.src in hosts)
        out[f"{label}_explained_pct"] = round(100.0 * classified / counted, 2) if counted else None
    out["robots_before_window_bytes"] = sum(run.before_window.get(h, 0) for h in run.robots)
    out["unmatched_trace_lines"] = run.unmatched_records
    out["untraced_protected"] = run.untraced_protected
    out["bench_wire_bytes"] = run.row.get("wire_bytes")
    return out


def explained_table(runs: Sequence[Run]) -> str:
    head = ("| run | robots: counted (B) | in the budget | classified | explained | feeder: counted | classified "
            "| packets counted / in the budget | untraced protected | trace lines without a frame "
            "| robots before the first reading |\n|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|\n")
    body = ""
    for r in runs:
        e = explained(r)
        body += (f"| {r.name} | {e['robots_counted_bytes']:,} | {e['robots_budget_bytes']:,} | "
                 f"{e['robots_classified_bytes']:,} | {e['robots_explained_pct']:.2f} % | "
                 f"{e['feeder_counted_bytes']:,} | {e['feeder_classified_bytes']:,} | "
                 f"{e['all_packets_counted']:,} / {e['all_packets_budget']:,} | {e['untraced_protected']} | "
                 f"{e['unmatched_trace_lines']} | {e['robots_before_window_bytes']:,} |\n")
    return head + body


def copies_table(runs: Sequence[Run]) -> str:
    """Redundant datagrams by the kind they repeat, per task."""
    n = sum(r.tasks for r in runs)
    lines: dict[tuple[str, str], Line] = {}
    for r in runs:
        for d in r.datagrams:
            if d.copy != "first":
                key = (d.copy, _kind_label(d))
                lines.setdefault(key, Line(f"{d.copy}: {key[1]}")).add(d)
    if not lines:
        return "(none)\n"
    head = "| copy of | packets | bytes | lost |\n|---|--:|--:|--:|\n"
    ordered = sorted(lines.values(), key=lambda line: -line.bytes)
    return head + "".join(f"| {line.label} | {_per(line.packets, n)} | {_per(line.bytes, n)} | "
                          f"{_per(line.lost, n)} |\n" for line in ordered)


# --------------------------------------------------------------------------- the minimum


@dataclass
class Need:
    """Something every robot must receive, and its payload."""

    what: str
    count: int
    payload: float

    def packets(self, secure: bool) -> int:
        framing = MIN_FRAMING_SECURE if secure else MIN_FRAMING_PLAIN
        return self.count * max(1, math.ceil(self.payload / (MTU_PAYLOAD - framing)))

    def bytes(self, secure: bool) -> float:
        framing = MIN_FRAMING_SECURE if secure else MIN_FRAMING_PLAIN
        return self.packets(secure) * (ETH_HEADER + 20 + UDP_HEADER + framing) + self.count * self.payload


def minimum(run: Run) -> list[Need]:
    """What must cross the link for every robot to compute the same
    assignment (compute-by-all), measured on ``run``:

    * the facts each robot lacks: every distinct named query it had answered
      remotely (2.05), once, with the answer's whole payload (block-wise
      answers summed), and every ``/kb/facts`` notification with answers a
      holder pushed to it (each carries the answers of one task);
    * every teammate's planned state after the previous task (the initial
      one for the first): tasks x robots x (robots - 1) states, each the
      median payload of the run's ``/robot/plan`` notifications;
    * the feeder's task post to each robot: one per robot and task, its payload.
    """
    answers: dict[tuple[str, str, str], dict[int, int]] = defaultdict(dict)
    posts: dict[tuple[str, str], int] = {}
    states: list[int] = []
    pushed: list[int] = []
    for d in run.datagrams:
        plain = d.plain or {}
        if d.lost or d.coap is None:
            continue
        if d.kind == "answer" and d.dst in run.robots and plain.get("code") == "2.05":
            block = plain.get("block2")
            number = 0 if block is None else block[0]
            answers[(d.dst, d.detail, _query_of(plain))].setdefault(number, int(plain.get("payload", 0)))
        elif d.kind == "task post" and d.copy == "first":
            posts.setdefault((d.dst, plain.get("query", "")), int(plain.get("payload", 0)))
        elif d.kind in ("notification", "registration answer") and d.detail == "/robot/plan":
            states.append(int(plain.get("payload", 0)))
        elif d.kind == "notification" and d.detail == FACTS_PATH and d.copy == "first" and d.dst in run.robots:
            pushed.append(int(plain.get("payload", 0)))
    needs: list[Need] = []
    by_query: dict[str, list[int]] = defaultdict(list)
    for (_robot, name, _query), blocks in answers.items():
        by_query[name].append(sum(blocks.values()))
    for name in sorted(by_query, key=lambda q: _kind_order(f"answer {q}")):
        sizes = by_query[name]
        needs.append(Need(f"fact: {name}", len(sizes), statistics.fmean(sizes)))
    if pushed:
        needs.append(Need("facts pushed by their holder", len(pushed), statistics.fmean(pushed)))
    n = len(run.robots)
    if states:
        needs.append(Need("teammate's planned state", run.tasks * n * (n - 1), statistics.median(states)))
    if posts:
        needs.append(Need("task post", run.tasks * n, statistics.fmean(posts.values())))
    return needs


def _query_of(plain: Mapping[str, Any]) -> str:
    """A request's Uri-Query, or an answer's request's."""
    return str(plain.get("query") or (plain.get("req") or {}).get("query") or "")


def minimum_table(settings: Mapping[str, Sequence[Run]]) -> str:
    head = ("| setting | needed | count per task | payload (B) | packets per task | bytes per task |\n"
            "|---|---|--:|--:|--:|--:|\n")
    body = ""
    for name, runs in settings.items():
        n = sum(r.tasks for r in runs)
        merged: dict[str, list[Need]] = defaultdict(list)
        for r in runs:
            for need in minimum(r):
                merged[need.what].append(need)
        secure = runs[0].security
        if not merged:
            continue
        total_p = total_b = 0.0
        for what, needs in merged.items():
            count = sum(x.count for x in needs)
            payload = sum(x.count * x.payload for x in needs) / count
            packets = sum(x.packets(secure) for x in needs)
            nbytes = sum(x.bytes(secure) for x in needs)
            total_p += packets
            total_b += nbytes
            body += f"| {name} | {what} | {_per(count, n)} | {payload:.0f} | {_per(packets, n)} | {_per(nbytes, n)} |\n"
        body += f"| {name} | **minimum** | | | **{_per(total_p, n)}** | **{_per(total_b, n)}** |\n"
    return head + body


#: Where the bytes above the minimum go: each first transmission by what it is for.
BREAKDOWN = (
    "needed items, as sent",
    "requests for the facts",
    "robots' registrations: plans, pushed facts",
    "acknowledgements of plan notifications",
    "the feeder's view: /robot/outcome (before: /robot/state) registrations, notifications and their acknowledgements",
    "task answers (2.04)",
    "key exchange (EDHOC)",
    "liveness, hearsay, lease",
    "resets, errors, other",
    "copies: retransmissions, retries, hedged copies",
)


#: What the feeder observes of each robot: /robot/outcome, or /robot/state
#: in runs of the code before it.
FEEDER_VIEW = ("/robot/outcome", "/robot/state")


def breakdown_of(d: Datagram) -> str:
    """Which line of :data:`BREAKDOWN` datagram ``d`` belongs to."""
    if d.copy != "first":
        return BREAKDOWN[9]
    kind, detail = d.kind, d.detail
    code = (d.plain or {}).get("code")
    if (kind == "answer" and code == "2.05") or kind == "task post" or (
            kind in ("notification", "registration answer") and detail == "/robot/plan") or (
            kind == "notification" and detail == FACTS_PATH):
        return BREAKDOWN[0]
    if kind == "query":
        return BREAKDOWN[1]
    if kind in ("registration", "registration answer") and detail in ("/robot/plan", FACTS_PATH):
        return BREAKDOWN[2]
    if kind == "empty ACK" and detail.endswith("/robot/plan"):
        return BREAKDOWN[3]
    if detail in FEEDER_VIEW or (kind == "empty ACK" and detail.endswith(FEEDER_VIEW)):
        return BREAKDOWN[4]
    if kind == "task answer":
        return BREAKDOWN[5]
    if kind.startswith("EDHOC"):
        return BREAKDOWN[6]
    if kind.split(" ")[0] in ("liveness", "hearsay", "lease"):
        return BREAKDOWN[7]
    return BREAKDOWN[8]


def breakdown_table(settings: Mapping[str, Sequence[Run]]) -> str:
    """Bytes per task by what they are for, against the minimum, per setting."""
    names = [name for name, runs in settings.items() if any(minimum(r) for r in runs)]
    head = "| bytes per task | " + " | ".join(names) + " |\n|---|" + "--:|" * len(names) + "\n"
    values: dict[str, dict[str, float]] = defaultdict(dict)
    for name, runs in settings.items():
        n = sum(r.tasks for r in runs)
        sums = _frame_bytes_by(runs, breakdown_of)
        sent = sum(sums.values())
        need = sum(x.bytes(r.security) for r in runs for x in minimum(r))
        if not need:
            continue
        for line in BREAKDOWN:
            values[line][name] = sums[line] / n
        values["**sent**"][name] = sent / n
        values["**minimum**"][name] = need / n
        values["sent above the minimum"][name] = (sent - need) / n
        values["of it, the needed items' framing above the minimum's"][name] = (sums[BREAKDOWN[0]] - need) / n
    body = ""
    for line, by_name in values.items():
        body += f"| {line} | " + " | ".join(f"{by_name.get(nm, 0):,.0f}" for nm in names) + " |\n"
    return head + body


def gap_table(settings: Mapping[str, Sequence[Run]]) -> str:
    """What was sent against the minimum, per setting (over its runs; the
    runs' own byte ratios in brackets)."""
    head = ("| setting | runs | sent per task (B) | minimum per task (B) | ratio | per run | packets sent per task "
            "| minimum packets per task | ratio |\n|---|--:|--:|--:|--:|---|--:|--:|--:|\n")
    body = ""
    for name, runs in settings.items():
        n = sum(r.tasks for r in runs)
        sent = sum(d.frame for r in runs for d in r.datagrams)
        packets = sum(len(r.datagrams) for r in runs)
        need_b = sum(x.bytes(r.security) for r in runs for x in minimum(r))
        need_p = sum(x.packets(r.security) for r in runs for x in minimum(r))
        if not need_b:
            continue  # nothing traced, so no minimum (ZeroMQ, Zenoh)
        each = sorted(sum(d.frame for d in r.datagrams) / sum(x.bytes(r.security) for x in minimum(r)) for r in runs)
        per_run = ", ".join(f"{x:.1f}" for x in each)
        body += (f"| {name} | {len(runs)} | {sent / n:,.0f} | {need_b / n:,.0f} | {sent / need_b:.1f}x | {per_run} "
                 f"| {packets / n:.1f} | {need_p / n:.1f} | {packets / need_p:.1f}x |\n")
    return head + body


# --------------------------------------------------------------------------- CSV


PACKET_FIELDS = ("run", "setting", "t", "src", "dst", "sport", "dport", "type", "code", "mid", "token", "kind", "detail",
                 "copy", "block", "lost", "traced", "protected", "frame", *PART_COLUMNS, "plain_code", "query",
                 "block_number")


def packet_rows(run: Run, setting: str) -> Iterator[dict[str, Any]]:
    """One CSV row per datagram: where and what, its parts, and the
    plaintext the minimum reads (code, query, block number; the payload is
    its part)."""
    start = run.window[0]
    for d in sorted(run.datagrams, key=lambda d: d.t):
        c = d.coap
        plain = d.plain or {}
        block = plain.get("block2")
        yield {
            "run": run.name, "setting": setting, "t": f"{d.t - start:.4f}", "src": d.src, "dst": d.dst,
            "sport": d.sport, "dport": d.dport, "type": "" if c is None else ("CON", "NON", "ACK", "RST")[c.mtype],
            "code": "" if c is None else c.code, "mid": "" if c is None else c.mid,
            "token": "" if c is None else c.token.hex(), "kind": d.kind, "detail": d.detail, "copy": d.copy,
            "block": int(d.block), "lost": int(d.lost), "traced": int(d.record is not None),
            "protected": int(d.oscore), "frame": d.frame, **{p: d.parts.get(p, 0) for p in PART_COLUMNS},
            "plain_code": plain.get("code", ""), "query": _query_of(plain),
            "block_number": "" if block is None else block[0],
        }


def write_packets(settings: Mapping[str, Sequence[Run]], path: Path) -> None:
    with path.open("w", newline="", encoding="utf-8") as out:
        w = csv.DictWriter(out, PACKET_FIELDS)
        w.writeheader()
        for setting, runs in settings.items():
            for r in runs:
                w.writerows(packet_rows(r, setting))


def write_summary(settings: Mapping[str, Sequence[Run]], path: Path) -> None:
    fields = ("setting", "run", "tasks", "loss_pct", "security", "kind", "packets", "lost", "bytes",
              *PART_COLUMNS, "bytes_per_task", "packets_per_task")
    with path.open("w", newline="", encoding="utf-8") as out:
        w = csv.DictWriter(out, fields)
        w.writeheader()
        for setting, runs in settings.items():
            for r in runs:
                lines, subsets, total = budget_lines(r.datagrams)
                for line in [*lines, total, *subsets]:
                    w.writerow({"setting": setting, "run": r.name, "tasks": r.tasks, "loss_pct": r.loss,
                                "security": "oscore" if r.security else "none", "kind": line.label,
                                "packets": line.packets, "lost": line.lost, "bytes": line.bytes,
                                **{p: line.parts.get(p, 0) for p in PART_COLUMNS},
                                "bytes_per_task": round(line.bytes / r.tasks, 1),
                                "packets_per_task": round(line.packets / r.tasks, 2)})


def write_minimum(settings: Mapping[str, Sequence[Run]], path: Path) -> None:
    fields = ("setting", "run", "tasks", "needed", "count", "payload", "packets", "bytes")
    with path.open("w", newline="", encoding="utf-8") as out:
        w = csv.DictWriter(out, fields)
        w.writeheader()
        for setting, runs in settings.items():
            for r in runs:
                for need in minimum(r):
                    w.writerow({"setting": setting, "run": r.name, "tasks": r.tasks, "needed": need.what,
                                "count": need.count, "payload": round(need.payload, 1),
                                "packets": need.packets(r.security), "bytes": round(need.bytes(r.security))})


RUN_FIELDS = ("setting", "run", "tasks", "loss_pct", "security", "ok", "wire_bytes", "wire_packets", "completion_s",
              "robots_counted_bytes", "robots_budget_bytes", "robots_classified_bytes", "robots_explained_pct",
              "feeder_counted_bytes", "feeder_classified_bytes", "all_packets_counted", "all_packets_budget",
              "untraced_protected", "unmatched_trace_lines", "frames_outside_window", "exact", "counted", "path_stats",
              "before_window")


PEER_RUN_FIELDS = ("setting", "run", "system", "tasks", "loss_pct", "security", "ok", "wire_bytes", "wire_packets",
                   "completion_s", "all_counted_bytes", "all_budget_bytes", "all_classified_bytes",
                   "all_packets_counted", "all_packets_budget", "robots_counted_bytes", "robots_budget_bytes",
                   "robots_explained_pct", "feeder_counted_bytes", "feeder_budget_bytes", "exact",
                   "frames_outside_window", "before_window_bytes", "before_window_packets")


def peer_run_row(setting: str, r: Run) -> dict[str, Any]:
    """One run of the peers' comparison: the bench's figures and counters
    against the budget (every host, the robots, the feeder)."""
    return {"setting": setting, "system": r.system, "tasks": r.tasks, "loss_pct": r.loss,
            "security": r.row.get("security") or ("oscore" if r.security else "none"),
            **{k: r.row.get(k) for k in ("ok", "wire_bytes", "wire_packets", "completion_s")},
            **explained(r), "exact": int(r.exact), "frames_outside_window": r.outside,
            "before_window_bytes": sum(d.frame for d in r.setup), "before_window_packets": len(r.setup)}


def write_peer_runs(settings: Mapping[str, Sequence[Run]], path: Path) -> None:
    with path.open("w", newline="", encoding="utf-8") as out:
        w = csv.DictWriter(out, PEER_RUN_FIELDS, extrasaction="ignore")
        w.writeheader()
        for setting, runs in settings.items():
            for r in runs:
                w.writerow(peer_run_row(setting, r))


def peer_explained_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The peers' budgets against the bench's own counters, per run."""
    head = ("| run | ok | counted (B, every host) | in the budget | classified | packets counted / in the budget "
            "| exact | the bench's wire_bytes |\n|---|---|--:|--:|--:|--:|---|--:|\n")
    body = ""
    for r in rows:
        body += (f"| {r['run']} | {r['ok']} | {int(r['all_counted_bytes']):,} | {int(r['all_budget_bytes']):,} "
                 f"| {int(r['all_classified_bytes']):,} | {int(r['all_packets_counted']):,} / "
                 f"{int(r['all_packets_budget']):,} | {'yes' if str(r['exact']) == '1' else 'no'} "
                 f"| {int(float(r['wire_bytes'] or 0)):,} |\n")
    return head + body


def peer_sections(rows: Sequence[Mapping[str, Any]], run_rows: Sequence[Mapping[str, Any]]) -> dict[str, str]:
    """The doc's tables of the peers' comparison, by marker name."""
    sections = {"peers-compare": peers.compare_table(rows, run_rows),
                "peers-explained": peer_explained_table(run_rows)}
    for name, rs in peers._by_setting(rows).items():
        sections[f"peers-kinds-{name}"] = peers.kind_table(rs)
        if any(r["table"] == "quic-packet" for r in rs):
            sections[f"peers-quic-{name}"] = peers.quic_tables(rs)
        if any(r["table"] == "rtps-submessage" for r in rs):
            sections[f"peers-rtps-{name}"] = peers.rtps_table(rs)
    return sections


def print_peer_report(rows: Sequence[Mapping[str, Any]], run_rows: Sequence[Mapping[str, Any]]) -> None:
    for name, content in peer_sections(rows, run_rows).items():
        print(f"\n## {name}\n\n{content}")


def write_runs(settings: Mapping[str, Sequence[Run]], path: Path) -> None:
    """One line per run: the bench's own figures, its counters per host and
    how much of them the budget explains."""
    with path.open("w", newline="", encoding="utf-8") as out:
        w = csv.DictWriter(out, RUN_FIELDS, extrasaction="ignore")
        w.writeheader()
        for setting, runs in settings.items():
            for r in runs:
                w.writerow({"setting": setting, "tasks": r.tasks, "loss_pct": r.loss,
                            "security": "oscore" if r.security else "none",
                            **{k: r.row.get(k) for k in ("ok", "wire_bytes", "wire_packets", "completion_s")},
                            **explained(r), "frames_outside_window": r.outside, "exact": int(r.exact),
                            "counted": json.dumps(r.counted, sort_keys=True),
                            "path_stats": json.dumps(r.path_stats, sort_keys=True),
                            "before_window": json.dumps(r.before_window, sort_keys=True)})


def read_packets(path: Path, runs_path: Path) -> dict[str, list[Run]]:
    """The runs of a per-datagram CSV and its per-run CSV (``--from-csv``)."""
    rows_by_run: dict[str, list[dict[str, str]]] = defaultdict(list)
    with path.open(newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            rows_by_run[row["run"]].append(row)
    settings: dict[str, list[Run]] = defaultdict(list)
    with runs_path.open(newline="", encoding="utf-8") as f:
        for meta in csv.DictReader(f):
            datagrams = [_datagram_of(row) for row in rows_by_run.get(meta["run"], [])]
            counted = {h: (int(v[0]), int(v[1])) for h, v in json.loads(meta["counted"]).items()}
            run = Run(name=meta["run"], loss=float(meta["loss_pct"]), security=meta["security"] == "oscore",
                      tasks=int(meta["tasks"]), robots=sorted(h for h in counted if h.startswith("Robot")),
                      row={k: meta[k] for k in ("ok", "wire_bytes", "wire_packets", "completion_s")},
                      window=(0.0, 0.0), counted=counted, datagrams=datagrams,
                      unmatched_records=int(meta["unmatched_trace_lines"]),
                      untraced_protected=int(meta["untraced_protected"]),
                      outside=int(meta["frames_outside_window"]), path_stats=json.loads(meta["path_stats"]),
                      exact=meta["exact"] == "1", before_window=json.loads(meta["before_window"]))
            settings[meta["setting"]].append(run)
    return dict(settings)


def _datagram_of(row: Mapping[str, str]) -> Datagram:
    d = Datagram(float(row["t"]), row["src"], row["dst"], int(row["sport"]), int(row["dport"]),
                 int(row["frame"]), int(row["headers"]), b"")
    d.kind, d.detail, d.copy = row["kind"], row["detail"], row["copy"]
    d.block, d.lost = row["block"] == "1", row["lost"] == "1"
    d.parts = {p: int(row[p]) for p in PART_COLUMNS}
    if d.kind.startswith("TCP "):
        d.tcp = (0, 0)  # a TCP segment (its flags are not kept)
    if row["plain_code"]:
        d.plain = {"code": row["plain_code"], "query": row["query"], "payload": d.parts["payload"]}
        if row["block_number"] != "":
            d.plain["block2"] = [int(row["block_number"]), 0, 0]
    if row["mid"] != "":
        options = ((OSCORE_OPTION, 1),) if row["protected"] == "1" else ()
        d.coap = CoapSplit(("CON", "NON", "ACK", "RST").index(row["type"]), int(row["code"]), int(row["mid"]),
                           bytes.fromhex(row["token"]), options, 0, 0)
    return d


# --------------------------------------------------------------------------- the doc


def replace_section(text: str, name: str, content: str) -> str:
    """``text`` with what lies between ``<!-- budget:NAME -->`` and
    ``<!-- /budget:NAME -->`` replaced by ``content``."""
    begin, end = f"<!-- budget:{name} -->", f"<!-- /budget:{name} -->"
    a, b = text.find(begin), text.find(end)
    if a < 0 or b < a:
        raise ValueError(f"no section {name!r} in the document")
    return text[:a + len(begin)] + "\n" + content.rstrip("\n") + "\n" + text[b:]


def doc_sections(settings: Mapping[str, Sequence[Run]]) -> dict[str, str]:
    sections = {}
    for name, runs in settings.items():
        sections[f"table-{name}"] = budget_table(runs)
        sections[f"copies-{name}"] = copies_table(runs)
    sections["groups"] = group_table(settings)
    sections["explained"] = explained_table([r for runs in settings.values() for r in runs])
    sections["minimum"] = minimum_table(settings)
    sections["gap"] = gap_table(settings)
    sections["breakdown"] = breakdown_table(settings)
    return sections


def update_doc(settings: Mapping[str, Sequence[Run]], doc: Path = DOC,
               sections: Mapping[str, str] | None = None) -> None:
    text = doc.read_text(encoding="utf-8")
    for name, content in (doc_sections(settings) if sections is None else sections).items():
        if f"<!-- budget:{name} -->" in text:
            text = replace_section(text, name, content)
    doc.write_text(text, encoding="utf-8")


def print_report(settings: Mapping[str, Sequence[Run]]) -> None:
    for name, runs in settings.items():
        r = runs[0]
        print(f"\n## {name}: {len(runs)} run(s), {r.tasks} tasks each, {r.loss:g} % loss, "
              f"security {'on' if r.security else 'off'} (per task)\n")
        print(budget_table(runs))
        print(copies_table(runs))
    print(explained_table([r for runs in settings.values() for r in runs]))
    print(minimum_table(settings))
    print(gap_table(settings))
    print(breakdown_table(settings))


# --------------------------------------------------------------------------- main


def setting_name(loss: float, security: bool, system: str = "coap-distributed", writable: bool = False) -> str:
    prefix = "" if system == "coap-distributed" else f"{system}-"
    return f"{prefix}loss{loss:g}" + ("" if security else "-insecure") + ("-writable" if writable else "")


async def run_settings(plan: Sequence[tuple[str, str, float, bool]], args: argparse.Namespace,
                       keep: Path) -> dict[str, list[Run]]:
    from coapkb.bench.linkemu import available, cleanup_stale

    ok, why = available()
    if not ok:
        raise SystemExit(f"byte_budget: no kernel link emulation here: {why}")
    cleanup_stale()
    settings: dict[str, list[Run]] = {}
    for name, system, loss, security in plan:
        for rep in range(args.reps):
            directory = keep / f"{name}-rep{rep}"
            row = await traced_run(directory, system=system, robots=args.robots, tasks=args.tasks,
                                   bandwidth=args.bandwidth, loss=loss, rep=rep, security=security,
                                   writable=name.endswith("-writable"))
            print(f"{name} rep {rep}: ok={row['ok']} wire_bytes={row['wire_bytes']} "
                  f"completion={row['completion_s']} s {row['error']}", flush=True)
            meta = json.loads((directory / "run.json").read_text(encoding="utf-8"))
            if len(meta["readings"]) < 2:
                print(f"  no budget: the run ended before the bench read its counters (files in {directory})",
                      flush=True)
                continue
            if not row["ok"]:
                print(f"  a failed run: its budget is still written (files in {directory})", flush=True)
            settings.setdefault(name, []).append(load_run(directory, f"{name}-rep{rep}"))
    return settings


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.byte_budget", description=__doc__.split("\n\n")[0])
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--tasks", type=int, default=10)
    p.add_argument("--bandwidth", type=float, default=35.0, metavar="KBPS")
    p.add_argument("--loss", type=float, default=2.0, metavar="PCT")
    p.add_argument("--reps", type=int, default=None,
                   help=f"runs per setting (repetitions 0..N-1, as the bench's; default 1, {DOC_REPS} with --doc)")
    p.add_argument("--insecure", action="store_true", help="security off (OSCORE and EDHOC)")
    p.add_argument("--writable", action="store_true",
                   help="the robots write their picks, positions, loads and charges into the KB (bench --writable)")
    p.add_argument("--systems", dest="system", default=None,
                   help="one system of coapkb bench; for ZeroMQ and Zenoh only TCP's roles are told apart "
                        "(handshake, data, ACK), their messages being encrypted and not traced")
    p.add_argument("--peers", action="store_true",
                   help="the peers' comparison: CoAP with and without security, Zenoh over TCP, QUIC and reliable "
                        "UDP, DDS, at --loss (or, with --doc, 2 %% and 20 %%); --systems a,b picks some (CoAP "
                        "among them if wanted); its CSVs byte_budget_peers*.csv; with --read, the runs kept earlier")
    p.add_argument("--doc", action="store_true",
                   help="the doc's runs (2 %% and 20 %% loss secure, 2 %% insecure, ZeroMQ at 2 %%), the CSVs and "
                        "the doc's tables")
    p.add_argument("--from-csv", action="store_true", help="no runs: the tables from the committed per-datagram CSV")
    p.add_argument("--read", type=Path, metavar="DIR", action="append", default=[],
                   help="no runs: a run directory kept earlier (repeatable)")
    p.add_argument("--keep", type=Path, metavar="DIR", help="keep each run's capture and traces here")
    p.add_argument("--no-csv", action="store_true", help="do not write the CSVs")
    args = p.parse_args(argv)
    if args.reps is None:
        args.reps = DOC_REPS if args.doc else 1
    if args.peers:
        return peers_main(args)
    if args.from_csv:
        settings = read_packets(CSV_PACKETS, CSV_META)
        print_report(settings)
        if args.doc:
            update_doc(settings)
        return 0
    if args.read:
        settings = {}
        for directory in args.read:
            run = load_run(directory)
            settings.setdefault(setting_name(run.loss, run.security, str(run.row.get("system"))), []).append(run)
    else:
        system = args.system or "coap-distributed"
        plan = list(DOC_RUNS) if args.doc else [(setting_name(args.loss, not args.insecure, system, args.writable),
                                                 system, args.loss, not args.insecure)]
        with contextlib.ExitStack() as stack:
            keep = args.keep or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="byte-budget-")))
            settings = asyncio.run(run_settings(plan, args, keep))
    print_report(settings)
    if not args.no_csv:
        RESULTS.mkdir(parents=True, exist_ok=True)
        write_packets(settings, CSV_PACKETS)
        write_summary(settings, CSV_RUNS)
        write_minimum(settings, CSV_MINIMUM)
        write_runs(settings, CSV_META)
    if args.doc:
        update_doc(settings)
    return 0


def peer_setting_name(system: str, loss: float, security: bool) -> str:
    """A setting of the peers' comparison: the system always named."""
    return f"{system}-loss{loss:g}" + ("" if security else "-insecure")


def peers_main(args: argparse.Namespace) -> int:
    """``--peers``: run (or read) the peers' settings, write their CSVs, print (and with --doc write) their tables."""
    if args.from_csv:
        rows = peers.read_rows(CSV_PEERS)
        with CSV_PEERS_RUNS.open(newline="", encoding="utf-8") as f:
            run_rows = list(csv.DictReader(f))
    else:
        if args.read:
            settings: dict[str, list[Run]] = {}
            for directory in args.read:
                run = load_run(directory)
                settings.setdefault(peer_setting_name(run.system, run.loss, run.security), []).append(run)
        else:
            from coapkb.bench.run import SYSTEMS

            wanted = set(args.system.split(",")) if args.system else None
            losses = (2.0, 20.0) if args.doc else (args.loss,)
            plan = [(peer_setting_name(system, loss, security), system, loss, security)
                    for system, loss, security in PEER_RUNS
                    if system in SYSTEMS and loss in losses and (wanted is None or system in wanted)]
            missing = sorted({s for s, _, _ in PEER_RUNS} - set(SYSTEMS))
            if missing:
                print(f"not in this bench (left out): {', '.join(missing)}", flush=True)
            with contextlib.ExitStack() as stack:
                keep = args.keep or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="byte-budget-")))
                settings = asyncio.run(run_settings(plan, args, keep))
        order = [(system, security) for system, _, security in PEER_RUNS]

        def place(item: tuple[str, list[Run]]) -> tuple[float, int, str]:
            r = item[1][0]
            key = (r.system, r.security)
            return r.loss, order.index(key) if key in order else len(order), item[0]

        settings = dict(sorted(settings.items(), key=place))
        rows = [row for name, runs in settings.items() for row in peers.setting_rows(name, runs, _kind_label)]
        run_rows = [peer_run_row(name, r) for name, runs in settings.items() for r in runs]
        if not args.no_csv:
            RESULTS.mkdir(parents=True, exist_ok=True)
            peers.write_rows(rows, CSV_PEERS)
            write_peer_runs(settings, CSV_PEERS_RUNS)
    print_peer_report(rows, run_rows)
    if args.doc:
        update_doc({}, sections=peer_sections(rows, run_rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
