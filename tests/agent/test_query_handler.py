"""Query Handler: each named query runs where its KB module lives, and every
failure becomes a QueryError that names the query, the peer and the KB."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import pytest
from agent_helpers import config, endpoint

from coapkb.agent.query_handler import ModuleUnavailable, QueryError, QueryHandler
from coapkb.kb.client import KBClient
from coapkb.kb.errors import QueryEvaluationError
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.store import KnowledgeBase
from coapkb.model.results import SelectResult
from coapkb.transport.base import ResourceInfo
from coapkb.transport.memory import MemoryNetwork
from coapkb.transport.messages import Request, Response
from coapkb.transport.router import Router

EXISTS = {"name": "Gucci_bag_14"}


def handler(network: MemoryNetwork, kb: KnowledgeBase | None, wire: str = "compact", cache: bool = False,
            down: Callable[[str], str | None] = lambda robot_id: None, on_failure: Any = None,
            **changes: object) -> QueryHandler:
    cfg = config("Robot1", **changes)
    return QueryHandler(cfg, kb, KBClient(network.client(), cache=cache), wire=wire, down=down,
                        on_failure=on_failure)


async def test_own_module_runs_locally_without_traffic(network: MemoryNetwork, kbs: dict) -> None:
    queries = handler(network, kbs["Location"])
    result = await queries.run("warehouse-layout", {})
    assert isinstance(result, SelectResult) and len(result.rows) == 1
    assert (queries.stats.local, queries.stats.remote) == (1, 0)
    assert queries.client.transport.counters.messages_sent == 0


@pytest.mark.parametrize("wire", ["compact", "seed"])
async def test_other_modules_go_to_the_teammate_holding_them(
    network: MemoryNetwork, kbs: dict, serve_kbs: Callable, wire: str
) -> None:
    object_server = await serve_kbs("Robot2", ["Object"])
    capability_server = await serve_kbs("Robot3", ["Capability"])
    queries = handler(network, kbs["Location"], wire=wire)
    exists = await queries.run("object-exists", EXISTS)
    assert isinstance(exists, SelectResult) and len(exists.rows) == 1
    assert await queries.run("robot-specs", {}) == kbs["Capability"].query(NAMED_QUERIES["robot-specs"].render({}))
    assert (queries.stats.local, queries.stats.remote, queries.stats.failed) == (0, 2, 0)
    assert len(queries.stats.remote_latencies) == 2
    assert object_server.counters.messages_received == capability_server.counters.messages_received == 1


async def test_central_baseline_sends_every_query_to_the_server(
    network: MemoryNetwork, serve_kbs: Callable
) -> None:
    central = await serve_kbs("Central", ["Object", "Location", "Capability"])
    queries = handler(network, None, holders={"Robot1": (), "Robot2": (), "Robot3": ()}, central=endpoint("Central"))
    await queries.run("object-exists", EXISTS)
    await queries.run("warehouse-layout", {})
    assert central.counters.messages_received == 2 and queries.stats.remote == 2


async def test_cached_answers_are_counted_and_cost_no_traffic(network: MemoryNetwork, serve_kbs: Callable) -> None:
    await serve_kbs("Robot2", ["Object"])
    queries = handler(network, None, cache=True)
    first = await queries.run("object-exists", EXISTS)
    assert await queries.run("object-exists", EXISTS) == first
    assert (queries.stats.remote, queries.stats.cached) == (1, 1)
    assert queries.client.transport.counters.messages_sent == 1


async def test_nobody_holding_a_module_is_a_query_error(network: MemoryNetwork, kbs: dict) -> None:
    queries = handler(network, kbs["Location"], holders={"Robot1": "Location", "Robot2": "Object"})
    with pytest.raises(QueryError, match="no teammate holds the Capability KB"):
        await queries.run("robot-specs", {})


async def test_unreachable_teammate_is_a_query_error_naming_it(network: MemoryNetwork, kbs: dict) -> None:
    queries = handler(network, kbs["Location"])
    with pytest.raises(ModuleUnavailable, match=r"no live robot holds the Object KB \(Robot2: object-exists to "
                       r"coap://robot2:5683 failed: .*nobody listens") as info:
        await queries.run("object-exists", EXISTS)
    assert info.value.module == "Object" and list(info.value.why) == ["Robot2"]
    assert queries.stats.failed == 1 and queries.stats.remote == 0


async def test_failed_queries_are_reported_for_failure_detection(network: MemoryNetwork, kbs: dict) -> None:
    failures: list[tuple[str, str]] = []

    async def failed(robot_id: str, exc: Exception) -> None:
        failures.append((robot_id, type(exc).__name__))

    queries = handler(network, kbs["Location"], holders=REPLICATED, on_failure=failed)
    with pytest.raises(ModuleUnavailable):
        await queries.run("robot-specs", {})
    assert sorted(failures) == [("Robot2", "PeerGone"), ("Robot3", "PeerGone")]  # nobody listens there


async def test_holders_known_down_are_not_asked(network: MemoryNetwork, kbs: dict, serve_kbs: Callable) -> None:
    await serve_kbs("Robot2", ["Object"])  # up, but the team view has declared it down
    queries = handler(network, kbs["Location"], down=lambda robot_id: "killed" if robot_id == "Robot2" else None)
    with pytest.raises(ModuleUnavailable, match=r"no live robot holds the Object KB \(Robot2: down \(killed\)\)"):
        await queries.run("object-exists", EXISTS)
    assert queries.client.transport.counters.messages_sent == 0


async def serve_silent(network: MemoryNetwork, robot_id: str, query: str) -> None:
    """``robot_id`` is up but never answers the named query ``query``."""
    silent = Router()

    async def never(request: Request) -> Response:
        await asyncio.Event().wait()
        raise AssertionError("unreachable")

    silent.add(ResourceInfo(f"/kb/q/{query}"), never)
    await network.serve(silent, endpoint(robot_id))


async def test_a_teammate_that_does_not_answer_in_time_is_a_query_error(network: MemoryNetwork, kbs: dict) -> None:
    await serve_silent(network, "Robot2", "object-exists")
    queries = handler(network, kbs["Location"], query_timeout_s=0.05)
    with pytest.raises(QueryError, match="no answer within 0.05s"):
        await queries.run("object-exists", EXISTS)
    assert queries.stats.failed == 1


async def test_an_error_answer_is_a_query_error_with_its_diagnostic(network: MemoryNetwork, kbs: dict) -> None:
    await network.serve(Router(), endpoint("Robot2"))  # up, but serves no KB: 4.04
    queries = handler(network, kbs["Location"])
    with pytest.raises(QueryError, match="4.04 NOT_FOUND"):
        await queries.run("object-exists", EXISTS)


class _BrokenStore:
    def query(self, text: str) -> None:
        raise QueryEvaluationError("the store broke")


async def test_a_failing_local_query_is_a_query_error(network: MemoryNetwork) -> None:
    queries = handler(network, _BrokenStore())  # type: ignore[arg-type]
    with pytest.raises(QueryError, match="warehouse-layout on own Location KB: the store broke"):
        await queries.run("warehouse-layout", {})
    assert queries.stats.failed == 1


# --------------------------------------------------------------------------- replicas

REPLICATED = {"Robot1": ("Location", "Object"), "Robot2": ("Object", "Capability"), "Robot3": ("Capability", "Location")}


async def test_a_dead_holder_is_failed_over_to_the_replica(network: MemoryNetwork, kbs: dict,
                                                           serve_kbs: Callable) -> None:
    # Robot2 holds Capability too, but nobody listens there: Robot3's replica answers.
    replica = await serve_kbs("Robot3", ["Capability", "Location"])
    queries = handler(network, kbs["Location"], holders=REPLICATED)
    assert await queries.run("robot-specs", {}) == kbs["Capability"].query(NAMED_QUERIES["robot-specs"].render({}))
    assert (queries.stats.failovers, queries.stats.remote, queries.stats.failed) == (1, 1, 0)
    assert replica.counters.messages_received == 1
    # The failed holder goes last from now on: no second failover.
    await queries.run("robots-for-grip", {"grip": "gripping"})
    assert queries.stats.failovers == 1 and replica.counters.messages_received == 2


async def test_a_holder_the_team_knows_is_down_is_not_asked_first(network: MemoryNetwork, kbs: dict,
                                                                  serve_kbs: Callable) -> None:
    await serve_kbs("Robot3", ["Capability", "Location"])
    cfg = config("Robot1", holders=REPLICATED)
    queries = QueryHandler(cfg, kbs["Location"], KBClient(network.client()), down=lambda r: "killed" if r == "Robot2" else None)
    await queries.run("robot-specs", {})
    assert (queries.stats.failovers, queries.stats.remote) == (0, 1)


async def test_a_slow_holder_is_hedged_to_the_replica(network: MemoryNetwork, kbs: dict,
                                                      serve_kbs: Callable) -> None:
    await serve_silent(network, "Robot2", "robot-specs")
    await serve_kbs("Robot3", ["Capability", "Location"])
    cfg = config("Robot1", holders=REPLICATED)
    queries = QueryHandler(cfg, kbs["Location"], KBClient(network.client()), hedge_floor_s=0.05)
    await queries.run("robot-specs", {})
    assert (queries.stats.hedged, queries.stats.remote, queries.stats.failed) == (1, 1, 0)


async def test_every_holder_down_names_each_failure(network: MemoryNetwork, kbs: dict) -> None:
    queries = handler(network, kbs["Location"], holders=REPLICATED)
    with pytest.raises(ModuleUnavailable, match=r"Capability KB \(Robot2: robot-specs to .* failed: .*; "
                       r"Robot3: robot-specs to .* failed: "):
        await queries.run("robot-specs", {})
    assert queries.stats.failed == 1
