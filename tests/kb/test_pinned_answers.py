"""Answers pinned to a task (LiveKB.query_at, ``/kb/q/NAME?at=TASK``): every
robot deciding one task reads the knowledge as first told for it, though a
write lands between their questions; the next task reads the write."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
from support import ONTOLOGIES

from coapkb.kb.client import KBClient, decode
from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.model.results import QueryResult
from coapkb.transport.base import Endpoint
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import ContentFormat, Method, Request, Status
from coapkb.transport.router import Router

OBJECT = "Gucci_bag_14"
PLACE = NAMED_QUERIES["pick-place"].render({"name": OBJECT})
HOLDER = Endpoint("coap", "robot1", 5683)
LOC = "http://www.tcs.org/2018/Location#"


def pick_update(obj: str, robot: str, seq: int) -> str:
    """A pick as a robot writes it: off the shelf, picked by ``robot`` at task ``seq``."""
    return (f"PREFIX loc: <{LOC}>\n"
            f"DELETE WHERE {{ loc:{obj} loc:Inventory_aisle_no ?a . loc:{obj} loc:Inventory_rack_no ?r . "
            f"loc:{obj} loc:Inventory_bin_no ?b }} ;\n"
            f'INSERT DATA {{ loc:{obj} loc:Picked_by "{robot}" . loc:{obj} loc:Picked_at_task {seq} }}')


def _location(pinned_answers: int = 1024) -> LiveKB:
    return LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "R.1", wall_ms=wall_ms,
                  pinned_answers=pinned_answers)


def _place(result: QueryResult) -> list[tuple[str, ...]]:
    """What a ``pick-place`` answer says, as plain text: (variable=value, ...) per row."""
    return [tuple(f"{k}={v}" for k, v in sorted(row.items())) for row in result.as_dicts()]  # type: ignore[union-attr]


SHELF = [("aisle_no=3", "bin_no=3", "rack_no=21")]  #: where the KB file puts the bag


@pytest.fixture
def live() -> LiveKB:
    return _location()


def test_a_tasks_first_answer_stands_after_a_write(live: LiveKB) -> None:
    before = live.query_at(5, PLACE)
    assert _place(before) == SHELF
    live.update(pick_update(OBJECT, "Robot2", 4))
    # The robot that asks second about task 5 hears what the first heard.
    assert live.query_at(5, PLACE) == before
    # Task 6, and a plain query, see the pick.
    after = live.query_at(6, PLACE)
    assert _place(after) == [("picked_by=Robot2", "picked_task=4")]
    assert live.query(PLACE) == after
    # Task 5's answer is still the one first given.
    assert live.query_at(5, PLACE) == before


def test_pinning_is_per_question_not_per_task(live: LiveKB) -> None:
    other = NAMED_QUERIES["pick-place"].render({"name": "Canon_tv_538"})
    live.query_at(5, PLACE)
    live.update(pick_update("Canon_tv_538", "Robot3", 4))
    # A question first asked for task 5 after the write reads the write.
    assert _place(live.query_at(5, other)) == [("picked_by=Robot3", "picked_task=4")]


def test_only_the_latest_pinned_answers_are_kept() -> None:
    live = _location(pinned_answers=2)
    first = live.query_at(1, PLACE)
    live.query_at(2, PLACE)
    assert live.query_at(1, PLACE) is first  # asked again: kept, and now the latest
    live.query_at(3, PLACE)  # task 2's answer is the oldest: forgotten
    live.update(pick_update(OBJECT, "Robot2", 3))
    assert live.query_at(1, PLACE) is first
    assert _place(live.query_at(2, PLACE)) == [("picked_by=Robot2", "picked_task=3")]


# ------------------------------------------------------------ over the wire


@pytest.fixture
async def served(live: LiveKB) -> AsyncIterator[tuple[LiveKB, KBClient]]:
    """``live`` behind KBResources on the in-memory network, and a client."""
    network = MemoryNetwork()
    router = Router()
    KBResources(live).mount(router)
    server = await network.serve(router, HOLDER)
    yield live, KBClient(network.client(), cache=False)
    await server.aclose()


def _get(query_name: str, /, **query: str) -> Request:
    return Request(Method.GET, f"/kb/q/{query_name}", query, accept=ContentFormat.CBOR)


async def test_the_named_query_at_a_task_is_answered_as_first_told(served: tuple[LiveKB, KBClient]) -> None:
    live, client = served
    server = client.transport
    first = await server.request(HOLDER, _get("pick-place", name=OBJECT, at="7"), timeout=5)
    assert first.status == Status.CONTENT and first.content_format == ContentFormat.CBOR
    assert _place(decode(first)) == SHELF
    live.update(pick_update(OBJECT, "Robot1", 6))
    again = await server.request(HOLDER, _get("pick-place", name=OBJECT, at="7"), timeout=5)
    assert again.status == Status.CONTENT and again.payload == first.payload and again.etag == first.etag
    later = await server.request(HOLDER, _get("pick-place", name=OBJECT, at="8"), timeout=5)
    assert _place(decode(later)) == [("picked_by=Robot1", "picked_task=6")]
    unpinned = await server.request(HOLDER, _get("pick-place", name=OBJECT), timeout=5)
    assert _place(decode(unpinned)) == _place(decode(later))


async def test_a_pinned_answer_comes_in_the_format_asked(served: tuple[LiveKB, KBClient]) -> None:
    _, client = served
    request = Request(Method.GET, "/kb/q/pick-place", {"name": OBJECT, "at": "1"}, accept=ContentFormat.JSON)
    response = await client.transport.request(HOLDER, request, timeout=5)
    assert response.status == Status.CONTENT and response.content_format == ContentFormat.JSON
    assert _place(decode(response)) == SHELF


@pytest.mark.parametrize("at", ["abc", "-1", "1.5", "", " 3", "0x10", "1" * 13])
async def test_at_must_be_a_task_number(served: tuple[LiveKB, KBClient], at: str) -> None:
    _, client = served
    response = await client.transport.request(HOLDER, _get("pick-place", name=OBJECT, at=at), timeout=5)
    assert response.status == Status.BAD_REQUEST, response
    assert "at= takes a task number" in response.payload.decode()


async def test_at_on_a_read_only_kb_is_checked_and_then_ignored() -> None:
    router = Router()
    KBResources(KnowledgeBase.load([ONTOLOGIES / "Location.owl"])).mount(router)
    bad = await router.handle(_get("pick-place", name=OBJECT, at="abc"))
    assert bad.status == Status.BAD_REQUEST
    good = await router.handle(_get("pick-place", name=OBJECT, at="3"))
    assert good.status == Status.CONTENT
    assert _place(decode(good)) == SHELF


async def test_the_query_handler_asks_its_holder_for_the_tasks_answer(served: tuple[LiveKB, KBClient]) -> None:
    """A robot without the Location KB on a writable team sends ``at=`` with
    ``pick-place``: a write between two robots' questions does not split them."""
    from coapkb.agent.query_handler import QueryHandler
    from coapkb.config import RobotConfig, Teammate

    live, client = served
    team = {"Robot1": Teammate("Robot1", HOLDER, ("Location",)),
            "Robot2": Teammate("Robot2", Endpoint("coap", "robot2", 5683), ())}
    config = RobotConfig(robot_id="Robot2", bind=team["Robot2"].endpoint, kb_files=(), team=team,
                         query_timeout_s=2.0, kb_writable=True)
    queries = QueryHandler(config, None, client)
    before = await queries.run("pick-place", {"name": OBJECT}, at=9)
    live.update(pick_update(OBJECT, "Robot1", 8))
    assert _place(await queries.run("pick-place", {"name": OBJECT}, at=9)) == _place(before) == SHELF
    after = await queries.run("pick-place", {"name": OBJECT}, at=10)
    assert _place(after) == [("picked_by=Robot1", "picked_task=8")]
