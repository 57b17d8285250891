"""Robots of the agent unit tests: configurations, knowledge bases and
teammates served through the in-memory transport (no processes, no sockets)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Iterable
from pathlib import Path

import pytest

from coapkb.config import ExecutionModel, RobotConfig, Teammate
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.base import Endpoint
from coapkb.transport.memory import MemoryNetwork, MemoryServerTransport
from coapkb.transport.router import Router

ONTOLOGIES = Path(__file__).resolve().parents[2] / "ontologies"
#: The seed's cluster: who holds which KB module.
HOLDERS = {"Robot1": "Location", "Robot2": "Object", "Robot3": "Capability"}


def endpoint(robot_id: str) -> Endpoint:
    return Endpoint("coap", robot_id.lower(), 5683)


def config(
    robot_id: str = "Robot1",
    holders: dict[str, str | tuple[str, ...]] | None = None,
    **changes: object,
) -> RobotConfig:
    """``robot_id``'s configuration in a team where robot ``r`` holds ``holders[r]``."""
    holders = HOLDERS if holders is None else holders
    team = {
        r: Teammate(r, endpoint(r), (kbs,) if isinstance(kbs, str) else tuple(kbs)) for r, kbs in holders.items()
    }
    values: dict[str, object] = dict(
        robot_id=robot_id, bind=endpoint(robot_id), kb_files=(), team=team, query_timeout_s=1.0,
        execution=ExecutionModel(time_scale=1e6),
    )
    values.update(changes)
    return RobotConfig(**values)  # type: ignore[arg-type]


@pytest.fixture(scope="session")
def kbs() -> dict[str, KnowledgeBase]:
    """Each committed KB module, loaded once for the whole session (read-only)."""
    return {m: KnowledgeBase.load([ONTOLOGIES / f"{m}.owl"]) for m in ("Location", "Object", "Capability")}


@pytest.fixture
async def network() -> AsyncIterator[MemoryNetwork]:
    yield MemoryNetwork()



@pytest.fixture
def serve_kbs(network: MemoryNetwork, kbs: dict[str, KnowledgeBase]) -> Callable:
    """``await serve_kbs(robot_id, modules)``: that robot's KB resources on the memory network."""

    async def serve(robot_id: str, modules: Iterable[str]) -> MemoryServerTransport:
        modules = list(modules)
        router = Router()
        if modules:
            kb = kbs[modules[0]] if len(modules) == 1 else KnowledgeBase.load(
                [ONTOLOGIES / f"{m}.owl" for m in modules])
            KBResources(kb).mount(router)
        return await network.serve(router, endpoint(robot_id))

    return serve


@pytest.fixture(scope="session")
def all_kbs() -> KnowledgeBase:
    """The three modules in one store: a robot that answers every query itself."""
    return KnowledgeBase.load([ONTOLOGIES / f"{m}.owl" for m in ("Location", "Object", "Capability")])
