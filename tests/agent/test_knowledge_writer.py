"""What a robot did, written into the team's knowledge (coapkb.agent.knowledge_writer):
each SPARQL Update applied to a writable LiveKB of the committed ontologies
and read back with the named queries (``pick-place`` as the controller reads
it, ``robot-positions``, ``robot-loads``), and the writer's queue: in order,
the waiting facts of one module as one update, retried, dropped after
WRITE_TRIES."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import AsyncIterator, Callable

import pytest
from agent_helpers import ONTOLOGIES, config, endpoint

from coapkb.agent.controller import Controller
from coapkb.agent.decisions import Task
from coapkb.agent.job import Job
from coapkb.agent.knowledge_writer import LAZY_S, WRITE_TRIES, KnowledgeWriter, _Later
from coapkb.agent.query_handler import QueryHandler
from coapkb.agent.robot import write_knowledge
from coapkb.agent.robot_state import LiveState, PlannedState, RobotState
from coapkb.agent.task_executor import TaskExecutor
from coapkb.agent.team_view import TeamView
from coapkb.kb.client import KBClient, QueryFailed
from coapkb.kb.errors import KBError
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.named_updates import (
    PROLOGUE,
    NamedUpdate,
    load_update,
    missing_update,
    named_updates_sparql,
    pick_update,
)
from coapkb.kb.named_updates import delivered_update as _delivered
from coapkb.kb.named_updates import robot_at_update as _robot_at
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.base import PeerUnreachable, ResourceInfo
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import Request, Response, Status
from coapkb.transport.router import Router

LOC = "http://www.tcs.org/2018/Location#"
BAG, TV, PASTA = "Gucci_bag_14", "Canon_tv_538", "Barilla_pasta_1"
ALL = ("Location", "Object", "Capability")
DEPOT = (1, 0)


def _job(seq: int, obj: str, aisle: int = 3, rack: int = 7) -> Job:
    return Job(seq, obj, aisle=aisle, rack=rack, to_object_m=10.0, to_depot_m=0.0, depot=DEPOT)


def _text(rows: list[dict]) -> list[dict[str, str]]:
    return [{k: str(v) for k, v in row.items()} for row in rows]


def _place(live: LiveKB, obj: str) -> list[dict[str, str]]:
    """``pick-place`` of ``obj``: its rows, each value as text."""
    return _text(live.query(NAMED_QUERIES["pick-place"].render({"name": obj})).as_dicts())  # type: ignore[union-attr]


def _position(live: LiveKB, robot: str) -> list[tuple[str, str, str | None]]:
    """``robot-positions`` of ``robot``: (aisle, rack, updated_ms) per row."""
    rows = _text(live.query(NAMED_QUERIES["robot-positions"].render({})).as_dicts())  # type: ignore[union-attr]
    return [(r["aisle_no"], r["rack_no"], r.get("updated_ms")) for r in rows if r["robo_id"] == robot]


def _load(live: LiveKB, robot: str) -> list[dict[str, str]]:
    rows = _text(live.query(NAMED_QUERIES["robot-loads"].render({})).as_dicts())  # type: ignore[union-attr]
    return [{k: v for k, v in r.items() if k != "robo_id"} for r in rows if r["robo_id"] == robot]


def _values(live: LiveKB, obj: str, prop: str) -> list[str]:
    rows = live.query(f"SELECT ?v WHERE {{ <{LOC}{obj}> <{LOC}{prop}> ?v }}").rows  # type: ignore[union-attr]
    return sorted(str(v) for (v,) in rows)


def _writable(*modules: str) -> LiveKB:
    return LiveKB(KnowledgeBase.load([ONTOLOGIES / f"{m}.owl" for m in modules]), "R.1", wall_ms=wall_ms)


@pytest.fixture
def live() -> LiveKB:
    """A writable Location KB, as its holder serves it on a writable team."""
    return _writable("Location")


def with_prologue(module: str, update: str) -> str:
    return PROLOGUE[module] + update


def _location(update: str) -> str:
    return with_prologue("Location", update)


def delivered_update(objects: list[tuple[str, int]]) -> str:
    return " ;\n".join(_delivered(obj, seq) for obj, seq in objects)


def robot_at_update(robot: str, at: tuple[int, int], at_ms: int) -> str:
    return _robot_at(robot, at[0], at[1], at_ms)


# ------------------------------------------------------------------ the updates


def test_a_pick_takes_the_object_off_its_shelf(live: LiveKB) -> None:
    assert _place(live, BAG) == [{"aisle_no": "3", "rack_no": "21", "bin_no": "3"}]
    written = live.update(_location(pick_update(BAG, "Robot2", 3)))
    assert (written.removed, written.added) == (3, 2)
    assert _place(live, BAG) == [{"picked_by": "Robot2", "picked_task": "3"}]
    assert _place(live, TV)[0].keys() == {"aisle_no", "rack_no", "bin_no"}  # the others stay


def test_a_pick_puts_its_robot_at_the_shelf(live: LiveKB) -> None:
    assert _position(live, "Robot2") == [("8", "16", None)]  # where the KB file starts it
    live.update(_location(_joined(pick_update(BAG, "Robot2", 3),
                                  robot_at_update("Robot2", (3, 21), 1_700_000_000_123))))
    assert _place(live, BAG) == [{"picked_by": "Robot2", "picked_task": "3"}]
    assert _position(live, "Robot2") == [("3", "21", "1700000000123")]
    assert _position(live, "Robot1") == [("9", "6", None)]


def test_an_object_not_at_its_shelf_is_missing_since_the_task(live: LiveKB) -> None:
    live.update(_location(_joined(missing_update(PASTA, "Robot1", 4), robot_at_update("Robot1", (5, 6), 2000))))
    assert _place(live, PASTA) == [{"missing_task": "4"}]
    assert _values(live, PASTA, "Reported_missing_by") == ["Robot1"]
    assert _position(live, "Robot1") == [("5", "6", "2000")]


def test_a_delivery_names_each_object_and_its_task(live: LiveKB) -> None:
    live.update(_location(pick_update(BAG, "Robot2", 1)))
    live.update(_location(pick_update(TV, "Robot2", 2)))
    live.update(_location(_joined(delivered_update([(BAG, 1), (TV, 2)]),
                                  robot_at_update("Robot2", DEPOT, 3000))))
    assert (_values(live, BAG, "Delivered_at_task"), _values(live, TV, "Delivered_at_task")) == (["1"], ["2"])
    assert _position(live, "Robot2") == [("1", "0", "3000")]  # at the depot now
    assert _place(live, BAG) == [{"picked_by": "Robot2", "picked_task": "1"}]  # delivered, still picked
    # Without the robot, only the deliveries.
    assert live.update(_location(delivered_update([(PASTA, 4)]))).added == 1


def test_a_robots_load_and_charge_go_into_the_capability_kb() -> None:
    capability = _writable("Capability")
    capability.update(with_prologue("Capability", load_update("Robot1", 12.5, 380.25, 4000)))
    assert _load(capability, "Robot1") == [{"payload": "60.6", "load_kg": "12.5", "charge_wh": "380.25",
                                            "updated_ms": "4000"}]
    capability.update(with_prologue("Capability", load_update("Robot1", 0.0, 370.0, 5000)))
    assert _load(capability, "Robot1") == [{"payload": "60.6", "load_kg": "0", "charge_wh": "370",
                                            "updated_ms": "5000"}]


def test_an_unknown_product_has_no_place_and_a_pick_of_it_takes_nothing_away(live: LiveKB) -> None:
    assert _place(live, "Nonexistent_widget_1") == []
    assert live.update(_location(pick_update("Nonexistent_widget_1", "Robot1", 2))).removed == 0


def test_a_robot_id_is_a_literal_whatever_it_holds(live: LiveKB) -> None:
    live.update(_location(pick_update(BAG, 'Robot "7" \\ spare', 9)))
    assert _place(live, BAG) == [{"picked_by": 'Robot "7" \\ spare', "picked_task": "9"}]


def _controller(live_kb: LiveKB, network: MemoryNetwork) -> Controller:
    """A robot that holds every module, writable, and has claimed nothing."""
    cfg = config("Robot1", {"Robot1": ALL}, kb_writable=True)
    client = network.client()
    own = RobotState("Robot1", PlannedState(1, 0, 400.0, 0.0, 60.0, 0), LiveState(1.0, 0.0))
    team = TeamView(own, {}, client)
    executor = TaskExecutor(cfg.execution, own.live, lambda live: None)
    return Controller(cfg, QueryHandler(cfg, live_kb, KBClient(client)), team, executor,
                      lambda state: None, lambda message: asyncio.sleep(0))  # type: ignore[arg-type,return-value]


async def test_the_controller_reads_back_why_nobody_picks_it() -> None:
    every = _writable(*ALL)
    controller = _controller(every, MemoryNetwork())
    assert not isinstance(await controller.gather(Task(1, BAG)), str)
    every.update(_location(_joined(pick_update(BAG, "Robot2", 3), robot_at_update("Robot2", (3, 21), 1000))))
    every.update(_location(_joined(missing_update(PASTA, "Robot3", 4),
                                   robot_at_update("Robot3", (5, 6), 2000))))
    # Task 1's place was read before the pick: read again for task 1, as first told.
    assert not isinstance(await controller.gather(Task(1, BAG)), str)
    assert await controller.gather(Task(5, BAG)) == "picked by Robot2 at task 3"
    assert await controller.gather(Task(5, PASTA)) == "missing from its place since task 4"
    assert await controller.gather(Task(5, "Nonexistent_widget_1")) == "no such object"
    assert controller.claims == {}  # gathering claims nothing: deciding does


# ------------------------------------------------------------------ the writer


class Radio:
    """``write(module, update, write_id)`` for a KnowledgeWriter: records
    what it is given and fails the first ``fail[i]`` tries of the i-th
    distinct update."""

    def __init__(self, fail: dict[int, int] | None = None, apply: Callable[[str], object] | None = None) -> None:
        self.calls: list[tuple[str, str]] = []
        #: The write id of each call.
        self.ids: list[str] = []
        self.fail = fail or {}
        self.apply = apply
        self._distinct: list[tuple[str, str]] = []
        self._changed = asyncio.Event()

    async def __call__(self, module: str, updates: list[NamedUpdate], write_id: str) -> None:
        # Compared as the holder renders them: the SPARQL Update they write.
        update = named_updates_sparql(updates)
        self.calls.append((module, update))
        self.ids.append(write_id)
        self._changed.set()
        if (module, update) not in self._distinct:
            self._distinct.append((module, update))
        if self.calls.count((module, update)) <= self.fail.get(self._distinct.index((module, update)), 0):
            raise QueryFailed(Response(Status.SERVICE_UNAVAILABLE, b"busy"))
        if self.apply is not None:
            self.apply(update)

    async def called(self, times: int = 1) -> None:
        """Until the writer has sent ``times`` writes (tries included)."""
        while len(self.calls) < times:
            self._changed.clear()
            await self._changed.wait()

    async def wait(self, writer: KnowledgeWriter, timeout: float = 5.0) -> None:
        """Until ``writer`` has nothing left to send, what may wait included
        (as when its robot turns idle)."""
        writer.flush()
        async with asyncio.timeout(timeout):
            await writer.drained()


@pytest.fixture
async def make() -> AsyncIterator[Callable[..., KnowledgeWriter]]:
    """``make(write, start=True)``: Robot1's writer, its clock at 1000, 2000, ... ms."""
    made: list[KnowledgeWriter] = []

    def build(write: Callable, start: bool = True, retry_s: float = 0.001, lazy_s: float = 10.0,
              **bounds: int) -> KnowledgeWriter:
        writer = KnowledgeWriter(write, "Robot1", itertools.count(1000, 1000).__next__, retry_s=retry_s,
                                 lazy_s=lazy_s, **bounds)
        if start:
            writer.start()
        made.append(writer)
        return writer

    yield build
    for writer in made:
        await writer.aclose()


def _joined(*updates: str) -> str:
    return " ;\n".join(updates)


def _at(at: tuple[int, int], ms: int) -> str:
    """Robot1's position, the last operation of what the writer sends."""
    return robot_at_update("Robot1", at, ms)


async def test_waiting_facts_go_out_in_order_one_update_per_module(make: Callable) -> None:
    every = _writable("Location", "Capability")
    radio = Radio(apply=every.update)
    writer = make(radio)
    one, two = _job(1, BAG, 3, 21), _job(2, PASTA, 5, 6)
    writer.picked(one)
    writer.missing(two)
    writer.load(12.5, 380.25)
    writer.delivered([one], DEPOT)
    assert writer.pending == 4  # two to send at once, and what waits for each of two modules
    await radio.wait(writer)
    assert radio.calls == [
        # The pick and the missing object go at once, as one update, and the
        # delivery rides with them; of the robot's positions only the latest
        # goes: one write never sets it twice.
        ("Location", _location(_joined(pick_update(BAG, "Robot1", 1), missing_update(PASTA, "Robot1", 2),
                                       delivered_update([(BAG, 1)]), _at(DEPOT, 4000)))),
        # The load waits for the robot to turn idle (or for LAZY_S).
        ("Capability", with_prologue("Capability", load_update("Robot1", 12.5, 380.25, 3000))),
    ]
    assert (writer.written, writer.dropped, writer.pending) == (2, 0, 0)
    assert _place(every, BAG) == [{"picked_by": "Robot1", "picked_task": "1"}]
    assert _place(every, PASTA) == [{"missing_task": "2"}]
    assert _values(every, BAG, "Delivered_at_task") == ["1"]
    assert _load(every, "Robot1")[0]["load_kg"] == "12.5"
    # A fact after the writer went idle goes out too.
    writer.picked(_job(3, TV))
    await radio.wait(writer)
    assert _place(every, TV) == [{"picked_by": "Robot1", "picked_task": "3"}] and writer.written == 3


async def test_what_may_wait_goes_alone_once_due(make: Callable) -> None:
    """A load and charge with no update of their module to ride with go by
    themselves after ``lazy_s``, without the robot turning idle."""
    radio = Radio()
    writer = make(radio, lazy_s=0.05)
    writer.load(12.5, 380.25)
    await asyncio.sleep(0)
    assert radio.calls == [] and writer.pending == 1
    async with asyncio.timeout(5):
        await writer.drained()
    assert radio.calls == [("Capability", with_prologue("Capability", load_update("Robot1", 12.5, 380.25, 1000)))]


async def test_an_update_joins_no_more_than_merged_max_bytes(make: Callable) -> None:
    radio = Radio()
    writer = make(radio, merged_max_bytes=300)
    for seq, obj in enumerate((BAG, TV, PASTA), start=1):
        writer.picked(_job(seq, obj))
    await radio.wait(writer)
    assert [module for module, _ in radio.calls] == ["Location"] * 3
    # Each pick apart; the robot's position rides with the first.
    assert [update.count("INSERT DATA") for _, update in radio.calls] == [2, 1, 1]


async def test_a_slow_write_holds_back_its_module_only(make: Callable) -> None:
    """Modules go side by side: the load goes out while a pick waits for its
    holder, and the next pick waits behind the first (one module, in order)."""
    release = asyncio.Event()
    radio = Radio()

    async def write(module: str, updates: list[NamedUpdate], write_id: str) -> None:
        if module == "Location" and not release.is_set() and len(radio.calls) == 0:
            await radio(module, updates, write_id)
            await release.wait()  # the first pick's holder is slow to answer
            return
        await radio(module, updates, write_id)

    writer = make(write)
    writer.picked(_job(1, BAG))
    await radio.called()
    writer.picked(_job(2, TV))
    writer.load(12.5, 380.25)
    writer.flush()
    async with asyncio.timeout(5):
        await radio.called(2)
    assert [module for module, _ in radio.calls] == ["Location", "Capability"]
    # The first pick being sent; the second, and the position riding with it, behind it.
    assert writer.pending == 3
    release.set()
    async with asyncio.timeout(5):
        await writer.drained()
    second = ("Location", _location(_joined(pick_update(TV, "Robot1", 2), _at((3, 7), 2000))))
    assert radio.calls[2] == second and (writer.written, writer.pending) == (3, 0)


async def test_a_failed_write_is_tried_again_before_the_next(make: Callable) -> None:
    radio = Radio(fail={0: WRITE_TRIES - 1})
    writer = make(radio)
    writer.picked(_job(1, BAG))
    await asyncio.sleep(0)  # the writer takes it: what comes next waits apart
    writer.picked(_job(2, TV))
    await radio.wait(writer)
    first = ("Location", _location(_joined(pick_update(BAG, "Robot1", 1), _at((3, 7), 1000))))
    second = ("Location", _location(_joined(pick_update(TV, "Robot1", 2), _at((3, 7), 2000))))
    assert radio.calls == [first] * WRITE_TRIES + [second]
    assert (writer.written, writer.dropped) == (2, 0)
    # Each try of a write under its id: a holder that made it makes it once.
    tries = radio.ids[:WRITE_TRIES]
    assert len(set(tries)) == 1 and radio.ids[-1] != tries[0]
    assert tries[0].startswith("Robot1.")


async def test_a_write_that_keeps_failing_is_dropped_and_the_next_goes_out(
    make: Callable, caplog: pytest.LogCaptureFixture
) -> None:
    radio = Radio(fail={0: WRITE_TRIES + 5})
    writer = make(radio)
    writer.picked(_job(1, BAG))
    await asyncio.sleep(0)
    writer.picked(_job(2, TV))
    await radio.wait(writer)
    first = ("Location", _location(_joined(pick_update(BAG, "Robot1", 1), _at((3, 7), 1000))))
    assert radio.calls[:WRITE_TRIES] == [first] * WRITE_TRIES
    assert radio.calls[WRITE_TRIES:] == [("Location", _location(_joined(pick_update(TV, "Robot1", 2),
                                                                        _at((3, 7), 2000))))]
    assert (writer.written, writer.dropped, writer.pending) == (1, 1, 0)
    assert f"not written after {WRITE_TRIES} tries" in caplog.text


@pytest.mark.parametrize("error", [PeerUnreachable("Robot2: no answer"), KBError("the KB refused it")],
                         ids=["transport", "kb"])
async def test_every_coapkb_error_counts_as_a_failed_write(make: Callable, error: Exception) -> None:
    calls: list[str] = []
    done = asyncio.Event()

    async def failing(module: str, update: str, write_id: str) -> None:
        calls.append(update)
        if len(calls) == WRITE_TRIES:
            done.set()
        raise error

    writer = make(failing)
    writer.picked(_job(1, BAG))
    await asyncio.wait_for(done.wait(), 5)
    await asyncio.sleep(0)  # the last failure's bookkeeping
    assert len(calls) == WRITE_TRIES and writer.dropped == 1 and writer.pending == 0


async def test_the_queue_is_bounded_and_drops_the_oldest(make: Callable) -> None:
    radio = Radio()
    writer = make(radio, start=False, queued_max=2)  # nothing goes out: everything waits
    for seq, obj in enumerate((BAG, TV, PASTA), start=1):
        writer.picked(_job(seq, obj))
    assert (writer.pending, writer.dropped) == (3, 1)  # two picks, and the position waiting
    writer.start()
    await radio.wait(writer)
    assert radio.calls == [("Location", _location(_joined(pick_update(TV, "Robot1", 2),
                                                          pick_update(PASTA, "Robot1", 3), _at((3, 7), 3000))))]


async def test_closing_the_writer_stops_it(make: Callable) -> None:
    radio = Radio(fail={0: 10**6})
    writer = make(radio, retry_s=60.0)  # stuck waiting to try again
    writer.picked(_job(1, BAG))
    async with asyncio.timeout(5):
        await radio.called()
        await writer.aclose()
    assert len(radio.calls) == 1


async def test_a_robot_has_one_position_after_facts_written_together(make: Callable, live: LiveKB) -> None:
    """A pick and the delivery after it, waiting together for the radio:
    the robot is where the later says (the depot), once."""
    radio = Radio(apply=live.update)
    writer = make(radio, start=False)
    one = _job(1, BAG, 3, 21)
    writer.picked(one)
    writer.delivered([one], DEPOT)
    writer.start()
    await radio.wait(writer)
    assert _place(live, BAG) == [{"picked_by": "Robot1", "picked_task": "1"}]
    assert _position(live, "Robot1") == [("1", "0", "2000")]


async def test_a_write_keeps_its_id_on_every_holder_it_is_sent_to() -> None:
    """``write_knowledge``: a holder that fails passes the write to the next
    one under the same id; sent again, the next one answers as before and
    changes nothing."""
    network = MemoryNetwork()
    seen: list[str | None] = []

    async def busy(request: Request) -> Response:
        seen.append(request.query.get("wid"))
        return Response.error(Status.SERVICE_UNAVAILABLE, "busy")

    failing = Router()
    failing.add(ResourceInfo("/kb", methods=("PATCH",)), busy)
    await network.serve(failing, endpoint("Robot2"))
    holder = _writable("Location")
    taking = Router()
    KBResources(holder).mount(taking)
    await network.serve(taking, endpoint("Robot3"))
    cfg = config("Robot1", {"Robot1": "Object", "Robot2": "Location", "Robot3": "Location"}, kb_writable=True)
    kb = KBClient(network.client(), writer="Robot1.5")
    update = [NamedUpdate("pick", (BAG, "Robot1", 1))]
    for _ in range(2):
        await write_knowledge(cfg, None, None, kb, "Location", update, lambda robot: True, "Robot1.5.1")
    assert seen == ["Robot1.5.1"] * 2
    assert len(holder.replicas["Location"].journal) == 1  # made once
    assert _place(holder, BAG) == [{"picked_by": "Robot1", "picked_task": "1"}]


async def test_waiting_facts_are_due_by_one_rule_whatever_the_rounding() -> None:
    """Seed 18055 of the simulator: the wait said due (0 s left) while the
    choice said not yet (``now - since`` rounds just below the lazy time), and
    the writer spun on a clock that stood still."""
    async def nothing_written(module: str, updates: list[NamedUpdate], write_id: str) -> None:
        raise AssertionError("the rule alone is tested: nothing is written")

    writer = KnowledgeWriter(nothing_written, "Robot1", lambda: 0)
    since = 12.818234786193416  # since + 10.0 - since rounds to just under 10.0
    now = since + LAZY_S
    assert now - since < LAZY_S
    later = _Later(since=since)
    assert writer._wait_left(later, now) == 0.0
    assert writer._wait_left(later, now - 1.0) == pytest.approx(1.0)
