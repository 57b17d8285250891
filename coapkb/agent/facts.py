"""What a task's decision needs from the knowledge base (the seed's
Query_1-4, as the Task Assigner reads them), asked through the Query
Handler: the object's existence, place, grip and weight, the robots that
can pick it that way, and, asked once per process, the warehouse layout,
the charging docks and every teammate's energy figures."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any

from ..config import RobotConfig
from ..kb.named_queries import MAX_LIST_ITEMS
from ..model.results import SelectResult
from ..world import Layout, Position, layout_from_row
from .decisions import Task
from .query_handler import QueryError, QueryHandler
from .task_assigner import RobotEnergy, TaskFacts, robot_sort_key

#: The skip reason of an object no KB knows.
NO_SUCH_OBJECT = "no such object"


class FactGatherer:
    """One robot's questions to the KB about a task, and the answers that
    do not change during a run, kept."""

    def __init__(self, config: RobotConfig, queries: QueryHandler) -> None:
        self.config = config
        self.queries = queries
        self._layout: Layout | None = None
        self._energy: dict[str, RobotEnergy] | None = None
        self._docks: tuple[Position, ...] | None = None

    async def layout(self) -> Layout:
        if self._layout is None:
            rows = _first(await self.queries.run("warehouse-layout", {}), "warehouse-layout")
            if not rows:
                raise QueryError("the Location KB has no warehouse layout")
            self._layout = layout_from_row(rows[0])
        return self._layout

    async def docks(self) -> tuple[Position, ...]:
        """The charging docks, asked once of the Location KB (in its order:
        the tie-break between equally good docks)."""
        if self._docks is None:
            rows = _first(await self.queries.run("charging-docks", {}), "charging-docks")
            self._docks = tuple(Position(int(r["aisle_no"]), int(r["rack_no"])) for r in rows)
        return self._docks

    async def energy(self) -> dict[str, RobotEnergy]:
        """Every teammate's energy figures, asked once of the Capability KB."""
        if self._energy is None:
            rows = await self._about_team("robot-specs", {})
            self._energy = {
                str(r["robo_id"]): RobotEnergy(
                    float(r["e_empty"]), float(r["e_loaded"]), float(r["e_pick"]), float(r["battery"])
                )
                for r in rows
                if str(r["robo_id"]) in self.config.team
            }
        return self._energy

    async def gather(self, task: Task) -> TaskFacts | str:
        """What the task's pick needs from the KBs, or why nobody picks it:
        no such object, already picked (by whom, at which task), missing."""
        self.queries.begin(task.seq)
        params = {"name": task.object}
        if self.queries.wire == "seed":
            exists, where, features = await self._seed_queries(params)
        else:
            # One exchange per KB holder: existence, grip and weight from the
            # Object KB, the place and what became of the object from the
            # Location KB (``pick-facts`` and ``pick-place``: the seed's
            # Query_1-3 as the assigner uses them).  The place is read as the
            # holder first told it for this task: every robot alike.
            exists, where = (
                _first(rows, label)
                for rows, label in zip(
                    await asyncio.gather(self.queries.run("pick-facts", params),
                                         self.queries.run("pick-place", params, at=task.seq)),
                    ("pick-facts", "pick-place"),
                )
            )
            features = [row for row in exists if row.get("grip") is not None and row.get("weight") is not None]
            why = _gone(where)
            if exists and why is not None:
                return why
            where = [row for row in where if row.get("aisle_no") is not None]
        if not exists:
            return NO_SUCH_OBJECT
        if not where or not features:
            # Said apart: a new product written into the Object KB alone has
            # its features but no shelf yet.
            lacking = [what for what, missing in (
                ("no place (aisle, rack, bin) in the Location KB", not where),
                ("no grip and weight in the Object KB" if self.queries.wire != "seed"
                 else "not every feature Query_3 asks in the Object KB", not features),
            ) if missing]
            raise QueryError(f"{task.object} exists but has {' and '.join(lacking)}")
        grip = _local_name(features[0]["grip"])
        robots = await self._about_team("robots-for-grip", {"grip": grip})
        capable = {str(r["robo_id"]): float(r["payload"]) for r in robots if str(r["robo_id"]) in self.config.team}
        return TaskFacts(
            seq=task.seq,
            object=task.object,
            aisle=int(where[0]["aisle_no"]),
            rack=int(where[0]["rack_no"]),
            bin=int(where[0]["bin_no"]),
            weight_kg=float(features[0]["weight"]),
            grip=grip,
            capable=capable,
        )

    async def _about_team(self, query: str, params: Mapping[str, str]) -> list[dict[str, Any]]:
        """``query`` for this robot's team only (its ``-among`` form: the answer
        does not grow with the fleet in the KB), or for every robot when the
        team is longer than a list parameter takes.  The team is in one order
        on every robot, so a teammate's answer cache serves it once."""
        team = sorted(self.config.team, key=robot_sort_key)
        if len(team) <= MAX_LIST_ITEMS:
            query, params = f"{query}-among", {**params, "robots": ",".join(team)}
        return _first(await self.queries.run(query, params), query)

    async def _seed_queries(self, params: Mapping[str, str]) -> tuple[list[dict[str, Any]], ...]:
        """The seed's Query_1, Query_2 and Query_3, as its system sends them."""
        # Query_2 and Query_3 need only the name, so they go out with Query_1
        # (the transports keep several exchanges in flight): two round trips
        # on the critical path instead of four.  For an object that does not
        # exist their empty answers are simply dropped.
        answers = await asyncio.gather(
            self.queries.run("object-exists", params),
            self.queries.run("object-location", params),
            self.queries.run("object-features", params),
        )
        return tuple(_first(rows, label) for rows, label in zip(answers, ("Query_1", "Query_2", "Query_3")))


def _first(result: object, name: str) -> list[dict[str, Any]]:
    if not isinstance(result, SelectResult):
        raise QueryError(f"{name} did not return solutions")
    return result.as_dicts()


def _gone(rows: list[dict[str, Any]]) -> str | None:
    """What ``pick-place`` says became of an object: picked (by whom, at
    which task) or missing from its place; None if it is on its shelf."""
    for row in rows:
        if row.get("picked_by") is not None:
            return f"picked by {row['picked_by']} at task {row.get('picked_task')}"
    for row in rows:
        if row.get("missing_task") is not None and row.get("aisle_no") is None:
            return f"missing from its place since task {row['missing_task']}"
    return None


def _local_name(term: object) -> str:
    text = str(term)
    return text.rsplit("#", 1)[-1].rsplit("/", 1)[-1]
