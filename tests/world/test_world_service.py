"""The world's truth (coapkb.world.truth) and its Unix-socket service
(coapkb.world.service): one shared shelf that two robots race for, a
misplaced object, malformed requests, and a world that is gone.  Real
sockets in a temporary folder; no processes."""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import cbor2
import pytest

from coapkb.world.service import MAX_FRAME, WorldClient, WorldServer, WorldUnavailable
from coapkb.world.truth import KBWorld, Taken, WorldTruth

MISPLACED = "not where the KB says it is (misplaced)"


def frame(body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + body


async def exchange(path: Path, raw: bytes) -> tuple[object, bytes]:
    """Send ``raw`` on a new connection; the answer's one frame, decoded, and
    what came after it before the server hung up (b"" if it did)."""
    reader, writer = await asyncio.open_unix_connection(str(path))
    try:
        writer.write(raw)
        await writer.drain()
        async with asyncio.timeout(5):
            size = struct.unpack(">I", await reader.readexactly(4))[0]
            answer = cbor2.loads(await reader.readexactly(size))
            rest = await reader.read()
        return answer, rest
    finally:
        writer.close()


@pytest.fixture
async def world(tmp_path: Path) -> AsyncIterator[WorldServer]:
    async with WorldServer(WorldTruth.with_misplaced(["Barilla_pasta_1"]), tmp_path / "world.sock") as server:
        yield server


# ------------------------------------------------------------------ the truth


def test_the_first_take_wins_and_later_ones_name_who_took_it() -> None:
    truth = WorldTruth()
    assert truth.take_now("Gucci_bag_14", "Robot2", 1) is None
    assert truth.taken == {"Gucci_bag_14": Taken("Robot2", 1)}
    assert truth.take_now("Gucci_bag_14", "Robot1", 3) == "gone: picked by Robot2 at task 1"
    assert truth.take_now("Gucci_bag_14", "Robot2", 4) == "gone: picked by Robot2 at task 1"  # even its taker
    assert truth.taken == {"Gucci_bag_14": Taken("Robot2", 1)}  # a refused take changes nothing


def test_a_misplaced_object_is_never_taken() -> None:
    truth = WorldTruth.with_misplaced(["Barilla_pasta_1"])
    for seq in (1, 2):
        assert truth.take_now("Barilla_pasta_1", "Robot1", seq) == MISPLACED
    assert truth.taken == {}
    assert truth.take_now("Canon_tv_538", "Robot1", 3) is None


def test_the_truth_forgets_the_oldest_taken_beyond_its_bound() -> None:
    truth = WorldTruth(taken_kept=2)
    for seq, obj in enumerate(("A_1", "B_2", "C_3"), start=1):
        assert truth.take_now(obj, "Robot1", seq) is None
    assert list(truth.taken) == ["B_2", "C_3"]
    assert truth.take_now("A_1", "Robot2", 4) is None  # delivered long ago: nobody remembers it


def test_a_delivery_puts_a_taken_or_misplaced_object_back_on_its_shelf() -> None:
    truth = WorldTruth.with_misplaced(["Barilla_pasta_1"])
    assert truth.take_now("Gucci_bag_14", "Robot2", 1) is None
    truth.restock("Gucci_bag_14")
    truth.restock("Barilla_pasta_1")
    truth.restock("Canon_tv_538")  # on its shelf already: nothing changes
    assert truth.taken == {} and truth.misplaced == frozenset()
    assert truth.take_now("Gucci_bag_14", "Robot1", 5) is None
    assert truth.take_now("Barilla_pasta_1", "Robot1", 6) is None
    assert truth.take_now("Gucci_bag_14", "Robot3", 7) == "gone: picked by Robot1 at task 5"


async def test_without_a_simulated_world_every_object_is_where_the_kb_says() -> None:
    world = KBWorld()
    assert [await world.take("Gucci_bag_14", r, 1) for r in ("Robot1", "Robot2")] == [None, None]
    assert await WorldTruth().take("Gucci_bag_14", "Robot1", 1) is None


# ---------------------------------------------------------------- the service


async def test_two_robots_race_for_one_object_and_exactly_one_gets_it(world: WorldServer) -> None:
    clients = [WorldClient(world.path) for _ in range(2)]
    try:
        answers = await asyncio.gather(clients[0].take("Gucci_bag_14", "Robot1", 1),
                                       clients[1].take("Gucci_bag_14", "Robot4", 1))
        assert answers.count(None) == 1, answers
        winner = ("Robot1", "Robot4")[answers.index(None)]
        [refused] = [a for a in answers if a is not None]
        assert refused == f"gone: picked by {winner} at task 1"
        assert world.truth.taken == {"Gucci_bag_14": Taken(winner, 1)}
        # One connection serves a robot's every question, in turn.
        assert await clients[0].take("Canon_tv_538", "Robot1", 2) is None
        assert await clients[0].take("Canon_tv_538", "Robot1", 3) == "gone: picked by Robot1 at task 2"
    finally:
        for client in clients:
            await client.aclose()


async def test_many_robots_at_once_one_winner_per_object(world: WorldServer) -> None:
    clients = [WorldClient(world.path) for _ in range(8)]
    objects = ["Gucci_bag_14", "Canon_tv_538", "Levis_jeans_234"]
    try:
        answers = await asyncio.gather(*(c.take(obj, f"Robot{i}", i) for i, c in enumerate(clients, 1)
                                         for obj in objects))
    finally:
        for client in clients:
            await client.aclose()
    assert answers.count(None) == len(objects)
    assert set(world.truth.taken) == set(objects)
    assert all(a is None or a.startswith("gone: picked by Robot") for a in answers)


async def test_a_delivery_over_the_socket_puts_objects_back(world: WorldServer) -> None:
    robot, feeder = WorldClient(world.path), WorldClient(world.path)
    try:
        assert await robot.take("Gucci_bag_14", "Robot1", 1) is None
        assert await robot.take("Barilla_pasta_1", "Robot1", 2) == MISPLACED
        await feeder.restock("Gucci_bag_14")
        await feeder.restock("Barilla_pasta_1")
        assert await robot.take("Gucci_bag_14", "Robot2", 3) is None  # the robot's connection goes on
        assert await robot.take("Barilla_pasta_1", "Robot2", 4) is None
        assert world.truth.taken == {"Gucci_bag_14": Taken("Robot2", 3), "Barilla_pasta_1": Taken("Robot2", 4)}
    finally:
        await robot.aclose()
        await feeder.aclose()
    assert world.malformed == 0


async def test_a_misplaced_object_is_answered_why(world: WorldServer) -> None:
    client = WorldClient(world.path)
    try:
        assert await client.take("Barilla_pasta_1", "Robot1", 4) == MISPLACED
        assert world.truth.taken == {}
    finally:
        await client.aclose()
    assert world.malformed == 0


@pytest.mark.parametrize(
    ("raw", "says"),
    [
        (struct.pack(">I", MAX_FRAME + 1) + b"\x80", f"at most {MAX_FRAME}"),
        (struct.pack(">I", 2**32 - 1), f"at most {MAX_FRAME}"),
        (frame(b"\xff\xff"), "error: "),
        (frame(b"\x83\x61a"), "error: "),  # an array of 3 cut short
        (frame(b""), "error: "),
        (frame(cbor2.dumps({"object": "Gucci_bag_14"})), "error: a request is [object, robot, seq]"),
        (frame(cbor2.dumps(["Gucci_bag_14", "Robot1"])), "error: a request is [object, robot, seq]"),
        (frame(cbor2.dumps(["Gucci_bag_14", "Robot1", "1"])), "error: a request is [object, robot, seq]"),
        (frame(cbor2.dumps(["Gucci_bag_14", "Robot1", True])), "error: a request is [object, robot, seq]"),
        (frame(cbor2.dumps([b"Gucci_bag_14", "Robot1", 1])), "error: a request is [object, robot, seq]"),
        (frame(cbor2.dumps(["Gucci_bag_14", None, 1])), "error: a request is [object, robot, seq]"),
        (frame(cbor2.dumps(["Gucci_bag_14", "Robot1", 1.0])), "error: a request is [object, robot, seq]"),
        (frame(b"\x81" * 600 + b"\x00"), "error: "),  # nested too deep to decode
    ],
    ids=["too-long", "far-too-long", "not-cbor", "cut-short", "empty", "a-map", "two-items", "text-seq",
         "bool-seq", "bytes-object", "null-robot", "float-seq", "deep-nesting"],
)
async def test_a_malformed_request_is_answered_an_error_and_the_server_goes_on(
    world: WorldServer, raw: bytes, says: str
) -> None:
    loyal = WorldClient(world.path)  # a robot connected before the garbage arrives
    try:
        assert await loyal.take("Gucci_bag_14", "Robot1", 1) is None
        answer, rest = await exchange(world.path, raw)
        assert isinstance(answer, str) and answer.startswith("error: ") and says in answer, answer
        assert rest == b""  # and the connection closed
        assert world.malformed == 1
        assert world.truth.taken == {"Gucci_bag_14": Taken("Robot1", 1)}  # nothing taken by the garbage
        # The robot already connected, and a new one, are served as before.
        assert await loyal.take("Canon_tv_538", "Robot1", 2) is None
        newcomer = WorldClient(world.path)
        try:
            assert await newcomer.take("Canon_tv_538", "Robot2", 3) == "gone: picked by Robot1 at task 2"
        finally:
            await newcomer.aclose()
    finally:
        await loyal.aclose()


async def test_a_request_after_a_malformed_one_on_its_connection_is_not_served(world: WorldServer) -> None:
    """The connection is closed after the error: what the sender queued behind it takes nothing."""
    good = frame(cbor2.dumps(["Gucci_bag_14", "Robot1", 1]))
    answer, rest = await exchange(world.path, frame(b"\xff") + good)
    assert isinstance(answer, str) and answer.startswith("error: ")
    assert rest == b"" and world.truth.taken == {} and world.malformed == 1


async def test_a_request_sent_in_pieces_is_served(world: WorldServer) -> None:
    raw = frame(cbor2.dumps(["Gucci_bag_14", "Robot3", 7]))
    reader, writer = await asyncio.open_unix_connection(str(world.path))
    try:
        for i in range(len(raw)):
            writer.write(raw[i:i + 1])
            await writer.drain()
        async with asyncio.timeout(5):
            size = struct.unpack(">I", await reader.readexactly(4))[0]
            assert cbor2.loads(await reader.readexactly(size)) is None
    finally:
        writer.close()
    assert world.truth.taken == {"Gucci_bag_14": Taken("Robot3", 7)} and world.malformed == 0


async def test_a_client_with_no_world_at_its_path_raises_at_once(tmp_path: Path) -> None:
    client = WorldClient(tmp_path / "nobody.sock", timeout_s=5.0)
    async with asyncio.timeout(1):  # well within its timeout: nobody listens
        with pytest.raises(WorldUnavailable, match="does not answer"):
            await client.take("Gucci_bag_14", "Robot1", 1)


async def test_a_closed_server_leaves_no_socket_and_new_clients_fail(tmp_path: Path) -> None:
    path = tmp_path / "world.sock"
    server = WorldServer(WorldTruth(), path)
    await server.start()
    assert path.is_socket()
    client = WorldClient(path, timeout_s=1.0)
    assert await client.take("Gucci_bag_14", "Robot1", 1) is None
    await client.aclose()
    async with asyncio.timeout(5):
        await server.aclose()
    assert not path.exists()
    with pytest.raises(WorldUnavailable):
        await WorldClient(path, timeout_s=1.0).take("Canon_tv_538", "Robot1", 2)


async def test_closing_the_server_ends_the_connections_of_robots_still_connected(tmp_path: Path) -> None:
    """A robot keeps its connection between questions: the server's close
    (``coapkb world`` on SIGTERM) neither waits for it nor serves it after."""
    server = WorldServer(WorldTruth(), tmp_path / "world.sock")
    await server.start()
    client = WorldClient(server.path, timeout_s=1.0)
    try:
        assert await client.take("Gucci_bag_14", "Robot1", 1) is None
        async with asyncio.timeout(5):
            await server.aclose()
        with pytest.raises(WorldUnavailable):
            await client.take("Canon_tv_538", "Robot1", 2)
    finally:
        await client.aclose()


async def test_a_world_that_does_not_answer_raises_within_the_timeout(tmp_path: Path) -> None:
    path = tmp_path / "mute.sock"
    connections: list[asyncio.StreamWriter] = []

    async def mute(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        connections.append(writer)  # reads nothing, answers nothing, keeps the line open

    server = await asyncio.start_unix_server(mute, path=str(path))
    client = WorldClient(path, timeout_s=0.2)
    try:
        loop = asyncio.get_running_loop()
        started = loop.time()
        with pytest.raises(WorldUnavailable, match="does not answer"):
            await client.take("Gucci_bag_14", "Robot1", 1)
        assert loop.time() - started < 2.0
    finally:
        await client.aclose()
        for writer in connections:
            writer.close()
        server.close()


async def test_a_world_that_hangs_up_raises_and_the_client_reconnects_to_a_new_one(tmp_path: Path) -> None:
    path = tmp_path / "world.sock"

    async def hang_up(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.close()

    rude = await asyncio.start_unix_server(hang_up, path=str(path))
    client = WorldClient(path, timeout_s=2.0)
    try:
        async with asyncio.timeout(2.5):
            with pytest.raises(WorldUnavailable):
                await client.take("Gucci_bag_14", "Robot1", 1)
        rude.close()
        await rude.wait_closed()
        # The world comes back at the same path: the next question reaches it.
        async with WorldServer(WorldTruth(), path) as server:
            assert await client.take("Gucci_bag_14", "Robot1", 2) is None
            assert server.truth.taken == {"Gucci_bag_14": Taken("Robot1", 2)}
    finally:
        await client.aclose()


async def test_an_answer_of_the_wrong_type_is_no_answer(tmp_path: Path) -> None:
    path = tmp_path / "odd.sock"

    async def odd(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readexactly(struct.unpack(">I", await reader.readexactly(4))[0])
        writer.write(frame(cbor2.dumps(42)))
        await writer.drain()

    server = await asyncio.start_unix_server(odd, path=str(path))
    client = WorldClient(path, timeout_s=2.0)
    try:
        with pytest.raises(WorldUnavailable, match="answered 42"):
            await client.take("Gucci_bag_14", "Robot1", 1)
    finally:
        await client.aclose()
        server.close()
