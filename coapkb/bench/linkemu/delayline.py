"""User-space delay line: propagation delay, jitter and burst loss per link.

The kernel here has no ``sch_netem``, so the bridge namespace sends the
packets of every host whose :class:`~.spec.LinkSpec` needs it to a netfilter
queue (iptables ``NFQUEUE``; queue number = host index), after the host's
uplink shaper and the random-loss rule, and this process gives each packet
its verdict: accepted after ``delay +- jitter`` with each link kept FIFO, or
dropped by a Gilbert two-state burst model.  Verdicts go over an
``AF_NETLINK`` socket spoken with the standard library, all packets due at
once in one batch.  One process per testbed, started by :class:`DelayLine`
with ``ip netns exec`` in the bridge namespace; it exits when its control
pipe (stdin) closes, and dies with the namespaces.

Control protocol (one JSON object per line on stdin, one reply line on
stdout): ``{"op": "set", "queue": N, "delay_ms": .., "jitter_ms": ..,
"p": .., "r": ..}`` and ``{"op": "stats"}``.

docs/link-emulation.md ("Delay, jitter and burst loss: the delay line")
specifies the release rule, the Gilbert mapping from a loss rate and a mean
burst, why netlink by hand and why ``select()``, and the lifecycle.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import random
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from .spec import LinkEmulationError, LinkSpec

__all__ = ["DelayLine", "QueueStats"]

# ---- nfnetlink_queue, from <linux/netlink.h>, <linux/netfilter/nfnetlink*.h>

NETLINK_NETFILTER = 12
SOL_NETLINK = 270
NETLINK_NO_ENOBUFS = 5
SO_RCVBUFFORCE = 33
NLM_F_REQUEST = 0x1
NLM_F_ACK = 0x4
NLMSG_ERROR = 2
NFNL_SUBSYS_QUEUE = 3
NFQNL_MSG_PACKET = 0
NFQNL_MSG_VERDICT = 1
NFQNL_MSG_CONFIG = 2
NFQNL_MSG_VERDICT_BATCH = 3
NFQA_PACKET_HDR = 1
NFQA_VERDICT_HDR = 2
NFQA_PAYLOAD = 10
NFQA_CAP_LEN = 13
NFQA_CFG_CMD = 1
NFQA_CFG_PARAMS = 2
NFQA_CFG_QUEUE_MAXLEN = 3
NFQNL_CFG_CMD_BIND = 1
NFQNL_COPY_PACKET = 2
NF_DROP = 0
NF_ACCEPT = 1

_NLMSG = struct.Struct("=IHHII")  # len, type, flags, seq, portid
_NFGEN = struct.Struct("!BBH")  # family, version, res_id (the queue number, big-endian)
_NLA = struct.Struct("=HH")  # len, type

#: Bytes of each packet copied to user space: the IPv4 header's total length
#: is all the delay line reads (``NFQA_CAP_LEN`` carries the full length too).
COPY_RANGE = 64

#: Kernel-side queue limit per link.  Packets held for ``delay`` accumulate:
#: 10,000 packets/s for 600 ms is 6000; beyond the limit the kernel drops
#: (counted as the link's ``queue_drops``).
QUEUE_MAXLEN = 65_536

#: Ethernet header: the queue sees IP packets, counters count frames.
_ETH_HEADER = 14

_PR_SET_TIMERSLACK = 29


def _attrs(buf: memoryview, start: int, end: int) -> dict[int, memoryview]:
    """Netlink attributes in ``buf[start:end]`` by type (flags masked off)."""
    out: dict[int, memoryview] = {}
    while start + 4 <= end:
        length, kind = _NLA.unpack_from(buf, start)
        if length < 4:
            break
        out[kind & 0x3FFF] = buf[start + 4 : start + length]
        start += (length + 3) & ~3
    return out


def _attr(kind: int, payload: bytes) -> bytes:
    raw = _NLA.pack(4 + len(payload), kind) + payload
    return raw + b"\0" * (-len(raw) % 4)


class NfQueue:
    """One ``NETLINK_NETFILTER`` socket bound to several queue numbers."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, NETLINK_NETFILTER)
        # Packets arrive in bursts (a TCP window, nine robots at once); a full
        # socket buffer would make the kernel drop them.  As root the buffer
        # can exceed rmem_max; NO_ENOBUFS keeps recv() from failing then.
        with contextlib.suppress(OSError):
            self.sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 16 << 20)
        self.sock.setsockopt(SOL_NETLINK, NETLINK_NO_ENOBUFS, 1)
        self.sock.bind((0, 0))
        self._seq = 0
        self._buf = bytearray(1 << 20)

    def fileno(self) -> int:
        return self.sock.fileno()

    def _send(self, msg_type: int, queue: int, body: bytes, flags: int = NLM_F_REQUEST) -> int:
        self._seq += 1
        payload = _NFGEN.pack(socket.AF_UNSPEC, 0, queue) + body
        header = _NLMSG.pack(_NLMSG.size + len(payload), (NFNL_SUBSYS_QUEUE << 8) | msg_type, flags, self._seq, 0)
        self.sock.send(header + payload)
        return self._seq

    def _config(self, queue: int, body: bytes) -> None:
        """Send a config message and wait for its ack (errors raise OSError)."""
        seq = self._send(NFQNL_MSG_CONFIG, queue, body, NLM_F_REQUEST | NLM_F_ACK)
        while True:
            n = self.sock.recv_into(self._buf)
            view = memoryview(self._buf)[:n]
            pos = 0
            while pos + _NLMSG.size <= n:
                length, kind, _flags, mseq, _pid = _NLMSG.unpack_from(view, pos)
                if kind == NLMSG_ERROR and mseq == seq:
                    (err,) = struct.unpack_from("=i", view, pos + _NLMSG.size)
                    if err:
                        raise OSError(-err, f"nfqueue config of queue {queue}: {os.strerror(-err)}")
                    return
                pos += (length + 3) & ~3

    def bind(self, queue: int, maxlen: int = QUEUE_MAXLEN) -> None:
        """Take queue ``queue``: copy the first :data:`COPY_RANGE` bytes of each packet."""
        self._config(queue, _attr(NFQA_CFG_CMD, struct.pack("!BxH", NFQNL_CFG_CMD_BIND, socket.AF_UNSPEC)))
        params = struct.pack("!IB", COPY_RANGE, NFQNL_COPY_PACKET)
        self._config(queue, _attr(NFQA_CFG_PARAMS, params) + _attr(NFQA_CFG_QUEUE_MAXLEN, struct.pack("!I", maxlen)))

    def receive(self) -> list[tuple[float, int, int, int]]:
        """Every packet waiting on the socket as ``(time read, queue, packet id,
        IP length)``; [] if none.  The time is taken after the read, so it is
        never before the packet reached the queue: a delay counted from it is
        never short."""
        packets: list[tuple[float, int, int, int]] = []
        while True:
            try:
                n = self.sock.recv_into(self._buf, 0, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return packets
            now = time.monotonic()
            view = memoryview(self._buf)[:n]
            pos = 0
            while pos + _NLMSG.size <= n:
                length, kind, _flags, _seq, _pid = _NLMSG.unpack_from(view, pos)
                if length < _NLMSG.size:
                    break
                if kind == (NFNL_SUBSYS_QUEUE << 8) | NFQNL_MSG_PACKET:
                    _fam, _ver, queue = _NFGEN.unpack_from(view, pos + _NLMSG.size)
                    attrs = _attrs(view, pos + _NLMSG.size + _NFGEN.size, pos + length)
                    (packet_id,) = struct.unpack_from("!I", attrs[NFQA_PACKET_HDR])
                    if NFQA_CAP_LEN in attrs:
                        (size,) = struct.unpack_from("!I", attrs[NFQA_CAP_LEN])
                    else:
                        size = len(attrs.get(NFQA_PAYLOAD, b""))
                    packets.append((now, queue, packet_id, size))
                pos += (length + 3) & ~3

    def verdict(self, queue: int, packet_id: int, verdict: int, *, batch: bool = False) -> None:
        """``verdict`` for one packet, or with ``batch`` for every held packet with id <= ``packet_id``."""
        kind = NFQNL_MSG_VERDICT_BATCH if batch else NFQNL_MSG_VERDICT
        self._send(kind, queue, _attr(NFQA_VERDICT_HDR, struct.pack("!II", verdict, packet_id)))

    def close(self) -> None:
        self.sock.close()


@dataclass
class _Link:
    """One sending host's link in the delay line."""

    delay_s: float = 0.0
    jitter_s: float = 0.0
    p: float = 0.0  # Gilbert: Good -> Bad per packet
    r: float = 1.0  # Gilbert: Bad -> Good per packet
    bad: bool = False
    last_release: float = 0.0
    held: deque[tuple[float, int]] = field(default_factory=deque)  # (release time, packet id), FIFO
    packets: int = 0
    dropped: int = 0
    dropped_bytes: int = 0


@dataclass(frozen=True)
class QueueStats:
    """What the delay line did with one link's packets since it started."""

    packets: int = 0  # packets that entered the delay line
    dropped: int = 0  # burst-loss drops
    dropped_bytes: int = 0  # their frame bytes (Ethernet header included)
    held: int = 0  # packets waiting for their release time right now
    kernel_drops: int = 0  # the kernel's queue overflowed or could not reach the delay line


def _kernel_queue_drops() -> dict[int, int]:
    """``queue_dropped + user_dropped`` per queue, from this namespace's
    ``/proc/net/netfilter/nfnetlink_queue``."""
    out: dict[int, int] = {}
    with contextlib.suppress(OSError), open("/proc/net/netfilter/nfnetlink_queue") as f:
        for line in f:
            cols = line.split()
            if len(cols) >= 7:
                out[int(cols[0])] = int(cols[5]) + int(cols[6])
    return out


class _Engine:
    """The delay line's state and loop (runs in the child process)."""

    def __init__(self, queues: Sequence[int], seed: int | None) -> None:
        self.nfq = NfQueue()
        self.links = {q: _Link() for q in queues}
        for q in queues:
            self.nfq.bind(q)
        self.rng = random.Random(seed)

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        op = request.get("op")
        if op == "set":
            link = self.links[int(request["queue"])]
            link.delay_s = float(request["delay_ms"]) / 1000
            link.jitter_s = float(request["jitter_ms"]) / 1000
            link.p, link.r = float(request["p"]), float(request["r"])
            if link.p == 0:
                link.bad = False
            return {"ok": True}
        if op == "stats":
            kernel = _kernel_queue_drops()
            return {
                "ok": True,
                "queues": {
                    str(q): [link.packets, link.dropped, link.dropped_bytes, len(link.held), kernel.get(q, 0)]
                    for q, link in self.links.items()
                },
            }
        return {"ok": False, "error": f"unknown op {op!r}"}

    def arrive(self) -> None:
        for now, queue, packet_id, size in self.nfq.receive():
            link = self.links.get(queue)
            if link is None:  # not ours (cannot happen: only bound queues deliver)
                self.nfq.verdict(queue, packet_id, NF_ACCEPT)
                continue
            link.packets += 1
            if link.p > 0:
                # Gilbert: the state moves once per packet, then Bad loses it.
                link.bad = (self.rng.random() >= link.r) if link.bad else (self.rng.random() < link.p)
                if link.bad:
                    link.dropped += 1
                    link.dropped_bytes += size + _ETH_HEADER
                    self.nfq.verdict(queue, packet_id, NF_DROP)
                    continue
            due = now + link.delay_s
            if link.jitter_s:
                due += self.rng.uniform(-link.jitter_s, link.jitter_s)
            due = max(due, link.last_release)  # FIFO: never before the previous packet
            link.last_release = due
            link.held.append((due, packet_id))

    def release(self, now: float) -> float | None:
        """Accept every due packet (one batch verdict per link); the next due time."""
        following: float | None = None
        for queue, link in self.links.items():
            last = -1
            while link.held and link.held[0][0] <= now:
                last = link.held.popleft()[1]
            if last >= 0:
                self.nfq.verdict(queue, last, NF_ACCEPT, batch=True)
            if link.held and (following is None or link.held[0][0] < following):
                following = link.held[0][0]
        return following

    def run(self, control_in: Any, control_out: Any) -> None:
        control = control_in.fileno()
        os.set_blocking(control, False)
        pending = b""
        following: float | None = None
        while True:
            timeout = None if following is None else max(0.0, following - time.monotonic())
            readable, _, _ = select.select([self.nfq, control], [], [], timeout)
            if self.nfq in readable:
                self.arrive()
            if control in readable:
                try:
                    chunk = os.read(control, 65536)
                except BlockingIOError:  # select said readable, but nothing came: look again
                    chunk = None
                if chunk == b"":
                    return  # the owner closed the pipe (or died): stop, the kernel drops what is held
                pending += chunk or b""
                while b"\n" in pending:
                    line, pending = pending.split(b"\n", 1)
                    if line.strip():
                        control_out.write(json.dumps(self.handle(json.loads(line))) + "\n")
                        control_out.flush()
            following = self.release(time.monotonic())


def _serve(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m coapkb.bench.linkemu.delayline")
    parser.add_argument("--queues", required=True, help="comma-separated queue numbers to bind")
    parser.add_argument("--seed", type=int, default=None)
    args = parser.parse_args(argv)
    # Timer slack 1 us instead of 50 us: select() wake-ups are the delay's precision.
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0)
    # Real-time priority where allowed (root): on a saturated machine a
    # descheduled delay line delays packets past their time and, once its
    # socket buffer is full, the kernel drops packets the link model never
    # drew (seen in the suite beside two busy processes: 25 % lost at a set
    # 10 %).  It sleeps in select() between packets, and the kernel's
    # real-time throttling keeps 5 % of each core for everything else.
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
    queues = [int(q) for q in args.queues.split(",") if q]
    try:
        engine = _Engine(queues, args.seed)
    except OSError as exc:
        print(json.dumps({"ok": False, "error": f"cannot bind the netfilter queues: {exc}"}), flush=True)
        return 1
    print(json.dumps({"ok": True, "ready": queues}), flush=True)
    try:
        engine.run(sys.stdin.buffer, sys.stdout)
    except KeyboardInterrupt:
        pass
    finally:
        engine.nfq.close()
    return 0


# --------------------------------------------------------------------------
# The owner's side: start, configure, query, stop
# --------------------------------------------------------------------------


class DelayLine:
    """The delay-line process of one testbed, seen from the testbed.

    ``start`` launches it in ``netns`` (the bridge namespace) bound to
    ``queues`` and waits until it is ready; ``configure`` sets one link;
    ``stats`` reads every link's :class:`QueueStats`.  Requests are
    serialised with a lock (``Testbed.acounters`` reads from a worker thread).
    """

    def __init__(self, netns: str, queues: Iterable[int], *, seed: int | None = None) -> None:
        self.netns = netns
        self.queues = sorted(set(queues))
        self._seed = seed
        self._proc: subprocess.Popen[str] | None = None
        self._lock = threading.Lock()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def start(self, timeout: float = 15.0) -> None:
        argv = ["ip", "netns", "exec", self.netns, sys.executable, "-m", "coapkb.bench.linkemu.delayline",
                "--queues", ",".join(map(str, self.queues))]
        if self._seed is not None:
            argv += ["--seed", str(self._seed)]
        self._proc = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1
        )
        reply = self._read_reply(timeout)
        if not reply.get("ok"):
            raise LinkEmulationError(f"delay line did not start: {reply.get('error')}")

    def _read_reply(self, timeout: float) -> dict[str, Any]:
        proc = self._proc
        if proc is None or proc.stdout is None:
            raise LinkEmulationError("delay line not started")
        ready, _, _ = select.select([proc.stdout], [], [], timeout)
        line = proc.stdout.readline() if ready else ""
        if not line:
            code = proc.poll()
            err = ""
            if code is not None and proc.stderr is not None:
                err = proc.stderr.read().strip()[-500:]
            state = f"exited with {code}" if code is not None else f"silent for {timeout:g} s"
            raise LinkEmulationError(f"delay line {state}: {err or 'no output'}")
        result: dict[str, Any] = json.loads(line)
        return result

    def _request(self, request: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
        with self._lock:
            proc = self._proc
            if proc is None or proc.stdin is None:
                raise LinkEmulationError("delay line not started")
            try:
                proc.stdin.write(json.dumps(request) + "\n")
                proc.stdin.flush()
            except (BrokenPipeError, OSError) as exc:
                raise LinkEmulationError(f"delay line is gone (exit {proc.poll()}): {exc}") from None
            reply = self._read_reply(timeout)
        if not reply.get("ok"):
            raise LinkEmulationError(f"delay line refused {request}: {reply.get('error')}")
        return reply

    def configure(self, queue: int, spec: LinkSpec) -> None:
        """Apply ``spec``'s delay, jitter and (burst model only) loss to ``queue``."""
        burst = spec.loss_model == "burst" and spec.loss_pct > 0
        self._request({
            "op": "set", "queue": queue, "delay_ms": spec.delay_ms, "jitter_ms": spec.jitter_ms,
            "p": spec.gilbert_p if burst else 0.0, "r": spec.gilbert_r if burst else 1.0,
        })

    def stats(self) -> dict[int, QueueStats]:
        """Every bound queue's counters."""
        reply = self._request({"op": "stats"})
        return {int(q): QueueStats(*v) for q, v in reply["queues"].items()}

    def close(self, timeout: float = 2.0) -> None:
        """Close the control pipe (the process exits by itself), then make sure. Idempotent."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


if __name__ == "__main__":
    sys.exit(_serve())
