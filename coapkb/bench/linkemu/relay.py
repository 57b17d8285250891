"""Fallback without root: a user-space UDP relay (labelled, CoAP only)."""

from __future__ import annotations

import asyncio
import random
from collections import deque
from collections.abc import Callable
from types import TracebackType
from typing import Any, cast

from .spec import LinkCounters, LinkEmulationError, LinkSpec

__all__ = ["UDP_IPV4_OVERHEAD", "UdpRelay"]


# --------------------------------------------------------------------------
# Fallback without root: a user-space UDP relay (labelled, CoAP only)
# --------------------------------------------------------------------------

#: Bytes a UDP/IPv4 datagram occupies on an Ethernet link beyond its payload
#: (14 Ethernet + 20 IPv4 + 8 UDP).  The relay charges it so its rates mean
#: the same as the kernel testbed's.
UDP_IPV4_OVERHEAD = 42


class _Direction:
    """One direction of a relayed path: FIFO, token bucket, then loss, then delay.

    Same order as the kernel testbed: a datagram waits for tokens, "uses the
    link" (counted in ``tx``), and only then may be lost.  Timing comes from
    the event loop's timers, so it is only as precise as the loop is idle.
    """

    def __init__(self, spec: LinkSpec, rng: random.Random, loop: asyncio.AbstractEventLoop, overhead: int) -> None:
        self.spec = spec
        self._rng = rng
        self._loop = loop
        self._overhead = overhead
        self._queue: deque[tuple[bytes, Callable[[bytes], None]]] = deque()
        self._queued_bytes = 0
        self._tokens = float(spec.burst_bytes)
        self._stamp = loop.time()
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False
        self.tx_bytes = self.tx_packets = self.rx_bytes = self.rx_packets = 0
        self.dropped = self.dropped_bytes = self.queue_drops = 0

    def counters(self) -> LinkCounters:
        return LinkCounters(
            self.tx_bytes, self.tx_packets, self.rx_bytes, self.rx_packets,
            self.dropped, self.dropped_bytes, self.queue_drops,
        )

    def push(self, data: bytes, deliver: Callable[[bytes], None]) -> None:
        if self._closed:
            return
        frame = len(data) + self._overhead
        if self.spec.rate_bit_s is not None and self._queued_bytes + frame > self.spec.limit_bytes:
            self.queue_drops += 1
            return
        self._queue.append((data, deliver))
        self._queued_bytes += frame
        if self._timer is None:
            self._pump()

    def _pump(self) -> None:
        self._timer = None
        rate = self.spec.rate_bit_s
        burst = self.spec.burst_bytes
        while self._queue and not self._closed:
            data, deliver = self._queue[0]
            frame = len(data) + self._overhead
            if rate is not None:
                now = self._loop.time()
                self._tokens = min(float(burst), self._tokens + (now - self._stamp) * rate / 8)
                self._stamp = now
                # A datagram larger than the bucket goes once the bucket is
                # full and leaves a debt, so the long-run rate stays exact.
                need = min(frame, burst)
                if self._tokens < need:
                    self._timer = self._loop.call_later((need - self._tokens) * 8 / rate, self._pump)
                    return
                self._tokens -= frame
            self._queue.popleft()
            self._queued_bytes -= frame
            self._transmit(data, frame, deliver)

    def _transmit(self, data: bytes, frame: int, deliver: Callable[[bytes], None]) -> None:
        self.tx_bytes += frame
        self.tx_packets += 1
        if self.spec.loss_pct and self._rng.random() * 100 < self.spec.loss_pct:
            self.dropped += 1
            self.dropped_bytes += frame
            return
        self.rx_bytes += frame
        self.rx_packets += 1
        if self.spec.delay_ms:
            self._loop.call_later(self.spec.delay_ms / 1000, self._deliver, data, deliver)
        else:
            deliver(data)

    def _deliver(self, data: bytes, deliver: Callable[[bytes], None]) -> None:
        if not self._closed:
            deliver(data)

    def close(self) -> None:
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._queue.clear()


class _Listener(asyncio.DatagramProtocol):
    def __init__(self, relay: UdpRelay) -> None:
        self._relay = relay

    def datagram_received(self, data: bytes, addr: tuple[Any, ...]) -> None:
        self._relay._from_client(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP errors: the path is lossy anyway
        pass


class _Upstream(asyncio.DatagramProtocol):
    """The relay's socket towards the target for one client (NAT-style)."""

    def __init__(self, relay: UdpRelay, client: tuple[Any, ...]) -> None:
        self._relay = relay
        self._client = client
        self.transport: asyncio.DatagramTransport | None = None
        self.pending: list[bytes] = []

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = dgram = cast(asyncio.DatagramTransport, transport)
        for data in self.pending:
            dgram.sendto(data)
        self.pending.clear()

    def send(self, data: bytes) -> None:
        if self.transport is None:
            self.pending.append(data)
        elif not self.transport.is_closing():
            self.transport.sendto(data)

    def datagram_received(self, data: bytes, addr: tuple[Any, ...]) -> None:
        self._relay._from_target(data, self._client)

    def error_received(self, exc: Exception) -> None:
        pass


class UdpRelay:
    """**Fallback, user space, UDP only**: one lossy, slow path without root.

    Where :class:`Testbed` cannot run (no root, no namespaces), a CoAP-only
    benchmark can put one relay in front of each server: clients send to
    :attr:`address`, the relay forwards to ``target`` through ``up`` (client
    -> server) and sends the replies back through ``down``.  Each direction
    has a FIFO of ``limit_bytes``, a token bucket at ``rate_kbit`` (charging
    :data:`UDP_IPV4_OVERHEAD` per datagram like the kernel shaper), then loss,
    then ``delay_ms`` -- which, unlike the kernel path, works here, since
    holding a datagram in user space *is* a real delay.

    Results from the relay must be labelled as such: it emulates a path, not
    a host's link (two clients of one server do not share a downlink), its
    timing is only as good as the event loop's timers, it cannot carry TCP
    (ZeroMQ), and the client's and server's own kernels see a loopback link.

    ``counters()`` gives one :class:`LinkCounters` per direction: ``tx`` what
    entered the path (after the bucket, lost datagrams included), ``rx`` what
    was delivered, ``dropped`` the losses, ``queue_drops`` FIFO overflows.
    """

    def __init__(
        self,
        target: tuple[str, int],
        up: LinkSpec,
        down: LinkSpec | None = None,
        *,
        listen: tuple[str, int] = ("127.0.0.1", 0),
        seed: int | None = None,
        overhead_bytes: int = UDP_IPV4_OVERHEAD,
    ) -> None:
        if not isinstance(up, LinkSpec) or not isinstance(down, (LinkSpec, type(None))):
            raise ValueError("up and down must be LinkSpec (down=None: same as up)")
        for spec in (up, down):
            if spec is not None and (spec.jitter_ms or spec.loss_model != "random"):
                raise ValueError("UdpRelay emulates rate, random loss and fixed delay only (no jitter, no burst loss)")
        self.target = target
        self.up_spec = up
        self.down_spec = up if down is None else down
        self._listen = listen
        self._rng = random.Random(seed)
        self._overhead = overhead_bytes
        self._transport: asyncio.DatagramTransport | None = None
        self._sessions: dict[tuple[Any, ...], _Upstream] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._up: _Direction | None = None
        self._down: _Direction | None = None

    @property
    def address(self) -> tuple[str, int]:
        """Where clients send to (host, port), once started."""
        if self._transport is None:
            raise LinkEmulationError("relay not started")
        host, port = self._transport.get_extra_info("sockname")[:2]
        return host, port

    async def start(self) -> tuple[str, int]:
        loop = asyncio.get_running_loop()
        self._up = _Direction(self.up_spec, self._rng, loop, self._overhead)
        self._down = _Direction(self.down_spec, self._rng, loop, self._overhead)
        transport, _ = await loop.create_datagram_endpoint(lambda: _Listener(self), local_addr=self._listen)
        self._transport = transport
        return self.address

    async def __aenter__(self) -> UdpRelay:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        for d in (self._up, self._down):
            if d is not None:
                d.close()
        for task in self._tasks:
            task.cancel()
        for s in self._sessions.values():
            if s.transport is not None:
                s.transport.close()
        self._sessions.clear()
        if self._transport is not None:
            self._transport.close()

    def counters(self) -> dict[str, LinkCounters]:
        """``{"up": ..., "down": ...}`` since start."""
        if self._up is None or self._down is None:
            raise LinkEmulationError("relay not started")
        return {"up": self._up.counters(), "down": self._down.counters()}

    def _from_client(self, data: bytes, client: tuple[Any, ...]) -> None:
        assert self._up is not None
        session = self._sessions.get(client)
        if session is None:
            session = self._sessions[client] = _Upstream(self, client)
            loop = asyncio.get_running_loop()
            upstream = session
            task = loop.create_task(loop.create_datagram_endpoint(lambda: upstream, remote_addr=self.target))
            self._tasks.add(task)
            task.add_done_callback(lambda t: self._session_done(t, client))
        self._up.push(data, session.send)

    def _session_done(self, task: asyncio.Task[Any], client: tuple[Any, ...]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            # Could not open a socket towards the target: forget the session
            # (its datagrams are lost, as on a broken path); the next datagram retries.
            self._sessions.pop(client, None)

    def _from_target(self, data: bytes, client: tuple[Any, ...]) -> None:
        assert self._down is not None
        transport = self._transport
        if transport is None:
            return

        def deliver(d: bytes) -> None:
            if not transport.is_closing():
                transport.sendto(d, client)

        self._down.push(data, deliver)
