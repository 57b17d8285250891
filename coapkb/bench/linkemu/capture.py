"""A packet capture of a testbed's bridge, in pure Python (AF_PACKET).

Every frame a host puts on its link enters the bridge at the host's port
(``p-NAME``), before the loss rule; every frame the bridge delivers leaves
at the receiver's port.  One raw socket in the bridge namespace sees both:
``in`` frames are what the hosts sent (what their ``eth0`` counters count),
``out`` frames what reached a host; an ``in`` frame with no ``out`` copy was
dropped on the link.  Frames are kept whole, Ethernet header included, with
the kernel's receive timestamp.

    with PacketCapture(testbed.bridge_netns, path):
        ...   # run something on the testbed
    frames = list(read_frames(path))

Used by the byte budget (``experiments/byte_budget.py``); needs root, like
the testbed itself.
"""

from __future__ import annotations

import json
import socket
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

from .netns import enter_netns
from .spec import LinkEmulationError

__all__ = ["CapturedFrame", "PacketCapture", "read_frames"]

_ETH_P_ALL = 0x0003
_PACKET_OUTGOING = 4
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
#: Kernel receive buffer: a whole run's frames may wait while the thread is busy.
_BUFFER_BYTES = 16 * 1024 * 1024


@dataclass(frozen=True)
class CapturedFrame:
    """One frame seen at a bridge port: ``in`` from the host behind ``port``, or ``out`` to it."""

    t: float
    port: str
    direction: str
    frame: bytes


class PacketCapture:
    """Writes every frame crossing the bridge of namespace ``netns`` to
    ``path`` (JSON lines), from :meth:`start` (or ``with``) to :meth:`stop`."""

    def __init__(self, netns: str, path: Path) -> None:
        self.netns = netns
        self.path = Path(path)
        self.frames = 0
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None

    def __enter__(self) -> PacketCapture:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def start(self) -> None:
        try:
            with enter_netns(self.netns):  # the socket belongs to the namespace it was made in
                sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(_ETH_P_ALL))
        except OSError as exc:
            raise LinkEmulationError(f"cannot capture in {self.netns}: {exc.strerror}") from None
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, _BUFFER_BYTES)
        except OSError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _BUFFER_BYTES)
        sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        sock.settimeout(0.1)
        self._sock = sock
        self._thread = threading.Thread(target=self._run, name=f"capture {self.netns}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop after reading what the kernel still holds; re-raises a failure of the capture."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        if self._error is not None:
            raise LinkEmulationError(f"capture in {self.netns} failed: {self._error}")

    def _run(self) -> None:
        assert self._sock is not None
        sock = self._sock
        space = socket.CMSG_SPACE(16)
        try:
            with self.path.open("w", encoding="utf-8") as out:
                while True:
                    try:
                        data, ancdata, _flags, address = sock.recvmsg(65535, space)
                    except TimeoutError:
                        if self._stop.is_set():
                            return
                        continue
                    out.write(json.dumps(_record(data, ancdata, address)) + "\n")
                    self.frames += 1
        except BaseException as exc:  # noqa: BLE001 -- reported by stop()
            self._error = exc
        finally:
            sock.close()


def _record(data: bytes, ancdata: list[tuple[int, int, bytes]], address: Any) -> dict[str, Any]:
    t = None
    for level, kind, value in ancdata:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(value) >= 16:
            seconds, nanos = struct.unpack("qq", value[:16])
            t = seconds + nanos / 1e9
    if t is None:
        import time

        t = time.time()
    port, _proto, pkttype = address[0], address[1], address[2]
    return {"t": round(t, 9), "port": port, "dir": "out" if pkttype == _PACKET_OUTGOING else "in",
            "frame": data.hex()}


def read_frames(path: Path) -> Iterator[CapturedFrame]:
    """The frames a :class:`PacketCapture` wrote, in the order seen."""
    with Path(path).open(encoding="utf-8") as lines:
        for line in lines:
            if line.strip():
                r = json.loads(line)
                yield CapturedFrame(float(r["t"]), r["port"], r["dir"], bytes.fromhex(r["frame"]))
