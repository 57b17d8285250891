"""The world's truth shared by the robot processes of a run, over a Unix socket.

``coapkb team`` and ``coapkb bench`` serve one :class:`~.truth.WorldTruth`
for their robots; a robot started by hand reaches one with ``world =
"PATH"`` in its TOML (``coapkb world PATH`` serves it).  A Unix socket
keeps these sensor readings out of the emulated radio links and their byte
counts: they stand for what a robot sees, not for what it sends.

Each request and answer is one CBOR item behind a 4-byte length: the
request ``[object, robot, seq]``, the answer null (taken) or a text (why
not); a delivery (the feeder's) ``["restock", object]``, answered null.  A malformed request is answered with an error text and the
connection closed; the server goes on.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from pathlib import Path

import cbor2

from ..errors import CoapkbError
from .truth import WorldTruth

log = logging.getLogger(__name__)

#: The largest request or answer: an object's name, a robot's id, a number.
MAX_FRAME = 1024
#: How long a robot waits for the world before it trusts the KB's word.
ANSWER_TIMEOUT_S = 2.0
#: The first item of a delivery's request.
RESTOCK = "restock"


class WorldUnavailable(CoapkbError):
    """The world's socket does not answer."""


async def _read_frame(reader: asyncio.StreamReader) -> object:
    size = struct.unpack(">I", await reader.readexactly(4))[0]
    if size > MAX_FRAME:
        raise ValueError(f"a frame of {size} bytes; at most {MAX_FRAME}")
    return cbor2.loads(await reader.readexactly(size))


def _frame(item: object) -> bytes:
    body = cbor2.dumps(item)
    return struct.pack(">I", len(body)) + body


class WorldServer:
    """Serves ``truth`` on the Unix socket ``path`` until closed."""

    def __init__(self, truth: WorldTruth, path: Path) -> None:
        self.truth = truth
        self.path = path
        self._server: asyncio.AbstractServer | None = None
        #: The robots connected now: closed with the server.
        self._connections: set[asyncio.StreamWriter] = set()
        #: Requests refused as malformed (they closed their connection).
        self.malformed = 0

    async def start(self) -> None:
        self.path.unlink(missing_ok=True)
        self._server = await asyncio.start_unix_server(self._serve, path=str(self.path))

    async def aclose(self) -> None:
        """Stop listening and hang up on every connected robot (from Python
        3.12 on, ``wait_closed`` waits for them)."""
        if self._server is not None:
            self._server.close()
            for writer in list(self._connections):
                writer.close()
            await self._server.wait_closed()
        self.path.unlink(missing_ok=True)

    async def __aenter__(self) -> WorldServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._connections.add(writer)
        try:
            while True:
                try:
                    request = await _read_frame(reader)
                except asyncio.IncompleteReadError:
                    return  # the robot hung up
                except (ValueError, cbor2.CBORDecodeError) as exc:
                    self.malformed += 1
                    writer.write(_frame(f"error: {exc}"[:200]))
                    return
                if (isinstance(request, list) and len(request) == 2 and request[0] == RESTOCK
                        and isinstance(request[1], str)):
                    self.truth.restock(request[1])
                    writer.write(_frame(None))
                    await writer.drain()
                    continue
                if not (isinstance(request, list) and len(request) == 3 and isinstance(request[0], str)
                        and isinstance(request[1], str) and type(request[2]) is int):
                    self.malformed += 1
                    writer.write(_frame('error: a request is [object, robot, seq] or ["restock", object]'))
                    return
                writer.write(_frame(self.truth.take_now(*request)))
                await writer.drain()
        except (ConnectionError, OSError, asyncio.CancelledError):
            return  # the robot went, or the server is closing: nothing to answer
        finally:
            self._connections.discard(writer)
            writer.close()


class WorldClient:
    """A robot's sensors at the shelf: asks the world served at ``path``."""

    def __init__(self, path: Path, timeout_s: float = ANSWER_TIMEOUT_S) -> None:
        self.path = path
        self.timeout_s = timeout_s
        self._streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._lock = asyncio.Lock()

    async def take(self, obj: str, robot: str, seq: int) -> str | None:
        """:meth:`~.truth.World.take`; raises :class:`WorldUnavailable`."""
        return await self._ask([obj, robot, seq])

    async def restock(self, obj: str) -> None:
        """:meth:`~.truth.WorldTruth.restock`; raises :class:`WorldUnavailable`."""
        answer = await self._ask([RESTOCK, obj])
        if answer is not None:
            raise WorldUnavailable(f"the world at {self.path} refused a delivery: {answer}")

    async def _ask(self, request: list[object]) -> str | None:
        async with self._lock:  # one question at a time on the one connection
            try:
                async with asyncio.timeout(self.timeout_s):
                    if self._streams is None:
                        self._streams = await asyncio.open_unix_connection(str(self.path))
                    reader, writer = self._streams
                    writer.write(_frame(request))
                    await writer.drain()
                    answer = await _read_frame(reader)
            except (OSError, TimeoutError, asyncio.IncompleteReadError, ValueError, cbor2.CBORDecodeError) as exc:
                await self.aclose()
                raise WorldUnavailable(f"the world at {self.path} does not answer: {exc or type(exc).__name__}") from None
        if answer is not None and not isinstance(answer, str):
            raise WorldUnavailable(f"the world at {self.path} answered {answer!r}")
        return answer

    async def aclose(self) -> None:
        if self._streams is not None:
            self._streams[1].close()
            self._streams = None
