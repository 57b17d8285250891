"""A trace of every CoAP datagram a process sends: off unless asked for.

The byte budget (``experiments/byte_budget.py``, ``docs/byte-budget.md``)
puts every datagram of a benchmark run in a kind (a named query, its answer,
a state notification, an EDHOC message, an empty ACK, ...).  A packet
capture shows OSCORE-protected messages as ciphertext, so the processes say
what they sent: with ``COAPKB_WIRE_TRACE=DIR`` in its environment, each
process writes one JSON line per datagram its CoAP contexts send to
``DIR/wire-PID.jsonl``.  A line holds the time, the context's role and
port, the destination, the type, Message ID, token and code as on the wire,
the datagram's length, and the plaintext the datagram carries:

* for a request, its method, Uri-Path, Uri-Query, Observe, Block2 and
  payload length (inside OSCORE when protected: ``inner_code``, ``path``, ...);
* for a response or notification, its code and payload length, and the
  request it answers (``req``: method, path, query, observe), as the server
  unprotected it;
* ``edhoc``: 1 or 3 for an EDHOC message_1 or message_3 (their answers are
  message_2 and message_4).

Where it hooks: :class:`~.aiocoap_adapter.ContextHooks` hands every datagram
its context sends to :meth:`WireTrace.sent` (one ``is None`` test when the
trace is off).  OSCORE builds the outer message afresh, so while the trace
is on, aiocoap's ``CanProtect.protect`` and ``CanUnprotect.unprotect`` are
wrapped (process-wide, installed on first use) to note the plaintext on the
outer message they make or read; nothing changes when the variable is unset.

:func:`split_coap` (the parts of a CoAP datagram) is pure and shared with
the byte budget's analysis.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

__all__ = ["ENV", "OSCORE_OPTION", "CoapSplit", "WireTrace", "describe", "split_coap", "tracer"]

#: The environment variable naming the trace directory.
ENV = "COAPKB_WIRE_TRACE"
#: RFC 8613's option number.
OSCORE_OPTION = 9
_TYPES = ("CON", "NON", "ACK", "RST")
#: The attribute the OSCORE wrappers set on an outer message: its plaintext.
_PLAIN = "_coapkb_plain"


@dataclass(frozen=True)
class CoapSplit:
    """A CoAP datagram's parts (RFC 7252 section 3), in bytes."""

    mtype: int
    code: int
    mid: int
    token: bytes
    #: (number, encoded bytes with its delta/length header) of each option, in order.
    options: tuple[tuple[int, int], ...]
    #: The payload marker (0xFF): 1 if there is a payload.
    marker: int
    payload: int
    header: int = 4

    @property
    def option_bytes(self) -> int:
        return sum(size for _, size in self.options)

    def option_size(self, number: int) -> int:
        return sum(size for n, size in self.options if n == number)

    @property
    def total(self) -> int:
        return self.header + len(self.token) + self.option_bytes + self.marker + self.payload


def _extended(nibble: int, data: bytes, at: int) -> tuple[int, int]:
    """An option delta or length nibble with its extension bytes: (value, next offset)."""
    if nibble < 13:
        return nibble, at
    if nibble == 13:
        if at + 1 > len(data):
            raise ValueError("option extension runs past the datagram")
        return data[at] + 13, at + 1
    if nibble == 14:
        if at + 2 > len(data):
            raise ValueError("option extension runs past the datagram")
        return int.from_bytes(data[at:at + 2], "big") + 269, at + 2
    raise ValueError("reserved option nibble 15")


def split_coap(data: bytes) -> CoapSplit:
    """The parts of the CoAP datagram ``data``; ValueError if it is not one."""
    if len(data) < 4 or data[0] >> 6 != 1:
        raise ValueError("not a CoAP version 1 datagram")
    tkl = data[0] & 0x0F
    if tkl > 8 or len(data) < 4 + tkl:
        raise ValueError("bad token length")
    at = 4 + tkl
    number = 0
    options: list[tuple[int, int]] = []
    marker = 0
    while at < len(data):
        first = data[at]
        if first == 0xFF:
            marker = 1
            at += 1
            if at == len(data):
                raise ValueError("payload marker without a payload")
            break
        start = at
        delta, at = _extended(first >> 4, data, at + 1)
        length, at = _extended(first & 0x0F, data, at)
        if at + length > len(data):
            raise ValueError("option value runs past the datagram")
        at += length
        number += delta
        options.append((number, at - start))
    return CoapSplit(mtype=(data[0] >> 4) & 0x03, code=data[1], mid=int.from_bytes(data[2:4], "big"),
                     token=bytes(data[4:4 + tkl]), options=tuple(options), marker=marker,
                     payload=len(data) - at if marker else 0)


def _dotted(code: int) -> str:
    return f"{code >> 5}.{code & 0x1F:02d}"


def describe(message: Any) -> dict[str, Any]:
    """What a (plaintext) aiocoap message says: code or method, path, query,
    Observe, Block2/Block1, payload length."""
    code = message.code
    out: dict[str, Any] = {"code": code.name if code.is_request() else _dotted(int(code))}
    opt = message.opt
    if opt.uri_path:
        out["path"] = "/" + "/".join(opt.uri_path)
    if opt.uri_query:
        out["query"] = "&".join(opt.uri_query)
    if opt.observe is not None:
        out["observe"] = int(opt.observe)
    for name in ("block2", "block1"):
        block = getattr(opt, name)
        if block is not None:
            out[name] = [block.block_number, int(block.more), block.size_exponent]
    out["payload"] = len(message.payload)
    if code.is_request() and opt.uri_path == (".well-known", "edhoc") and message.payload:
        out["edhoc"] = 1 if message.payload[:1] == b"\xf5" else 3  # message_1 follows CBOR true
    return out


def _address(sockaddr: Any) -> str:
    host, port = sockaddr[0], sockaddr[1]
    if isinstance(host, str) and host.startswith("::ffff:") and "." in host:
        host = host[len("::ffff:"):]
    return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"


class WireTrace:
    """One process's trace file (``DIR/wire-PID.jsonl``), a line per datagram sent."""

    def __init__(self, directory: Path) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.path = directory / f"wire-{os.getpid()}.jsonl"
        # Line-buffered: a process stopped by a signal loses no record.
        self._out: TextIO = self.path.open("a", buffering=1, encoding="utf-8")
        self._lock = threading.Lock()

    def sent(self, role: str, port: int | None, message: Any, data: bytes) -> None:
        """Record datagram ``data``, the encoding of ``message``, sent by a
        ``role`` ("client" or "server") context bound to ``port``."""
        record: dict[str, Any] = {
            "t": round(time.time(), 6), "pid": os.getpid(), "role": role, "port": port,
            "dst": _address(message.remote.sockaddr), "type": _TYPES[int(message.mtype)], "mid": message.mid,
            "token": bytes(message.token).hex(), "code": _dotted(int(message.code)), "len": len(data),
        }
        try:
            record.update(self._plain(message))
        except Exception as exc:  # noqa: BLE001 -- a trace must never break a send
            record["error"] = repr(exc)
        line = json.dumps(record, separators=(",", ":"))
        with self._lock:
            self._out.write(line + "\n")

    @staticmethod
    def _plain(message: Any) -> dict[str, Any]:
        code = message.code
        if int(code) == 0:  # empty: an ACK or a Reset
            return {}
        plain = getattr(message, _PLAIN, None)
        out: dict[str, Any] = {}
        if plain is not None:
            out["oscore"] = True
            out.update({("inner_code" if k == "code" else k): v for k, v in plain.items()})
        elif message.opt.oscore is not None:
            out["oscore"] = True  # protected by something that did not note its plaintext
        else:
            out.update({k: v for k, v in describe(message).items() if k != "code"})
        if code.is_response():
            request = getattr(message, "request", None)
            if request is not None:
                asked = getattr(request, _PLAIN, None)
                if asked is None and request.opt.oscore is None:
                    asked = describe(request)
                if asked is not None:
                    out["req"] = {k: asked[k] for k in ("code", "path", "query", "observe", "edhoc") if k in asked}
        return out

    def close(self) -> None:
        self._out.close()


_TRACER: WireTrace | None = None
_TRACER_DIR: str | None = None
_TRACER_LOCK = threading.Lock()


def tracer(note_protection: Callable[[str, Callable[[Any], Any]], None]) -> WireTrace | None:
    """This process's trace, if ``COAPKB_WIRE_TRACE`` names a directory (read
    when a context is created), else None.  Before a trace starts,
    ``note_protection`` (the adapter's :func:`~.aiocoap_adapter.note_protection`)
    has OSCORE's protect and unprotect note each outer message's plaintext
    (see the module doc)."""
    global _TRACER, _TRACER_DIR
    directory = os.environ.get(ENV)
    if not directory:
        return None
    with _TRACER_LOCK:
        if _TRACER is None or _TRACER_DIR != directory:
            note_protection(_PLAIN, describe)
            _TRACER, _TRACER_DIR = WireTrace(Path(directory)), directory
        return _TRACER
