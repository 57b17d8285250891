"""Task Assigner (the seed's Fig. 2): cost of every robot-task pair, minimum wins.

Pure functions: the same inputs give the same assignment on every robot,
which is what lets "compute by all" agree without a further message.  The
cost is battery consumption in Wh: travel on the warehouse's aisle graph at
a load-dependent energy per metre, plus an energy to pick, plus the trip to
the depot when the pick fills the robot up.  Each robot's energy figures come
from the Capability KB (robots differ).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from typing import Callable, Mapping

from ..config import CostModel
from ..world import Position
from .robot_state import PlannedState

Distance = Callable[[Position, Position], float]


@dataclass(frozen=True)
class TaskFacts:
    """What the four queries established about one pick task."""

    seq: int
    object: str
    aisle: int
    rack: int
    bin: int
    weight_kg: float
    grip: str
    #: robot id -> payload capacity (kg), for robots that can pick with ``grip``.
    capable: Mapping[str, float]


@dataclass(frozen=True)
class RobotEnergy:
    """A robot's energy use (Capability KB): Wh per metre empty and with a full
    payload (linear in between), and Wh per pick."""

    per_m_empty: float
    per_m_full: float
    per_pick: float

    def travel(self, metres: float, load_kg: float, payload_kg: float) -> float:
        fill = load_kg / payload_kg if payload_kg > 0 else 1.0
        return metres * (self.per_m_empty + (self.per_m_full - self.per_m_empty) * fill)


@dataclass(frozen=True)
class Plan:
    """The cost of one robot doing one task, and where that leaves it."""

    robot_id: str
    cost_wh: float
    after: PlannedState
    to_object_m: float
    #: Distance carried to the depot after the pick; 0 when the robot keeps its load.
    to_depot_m: float

    @property
    def unloads(self) -> bool:
        return self.to_depot_m > 0


@dataclass(frozen=True)
class Assignment:
    assigned_to: str | None
    #: robot id -> cost in Wh, or None when the robot cannot take the task.
    costs: dict[str, float | None]
    #: robot id -> why it cannot take the task.
    reasons: dict[str, str]
    plan: Plan | None


def robot_sort_key(robot_id: str) -> tuple:
    """Natural order, so Robot10 comes after Robot9 (the tie-break order)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", robot_id))


def plan_for(
    robot_id: str,
    state: PlannedState,
    task: TaskFacts,
    energy: RobotEnergy | None,
    distance: Distance,
    depot: Position,
    cost: CostModel,
) -> Plan | str:
    """The robot's plan for the task, or the reason it cannot take it."""
    capacity = task.capable.get(robot_id)
    if capacity is None:
        return f"cannot pick by {task.grip}"
    if energy is None:
        return "no energy figures in the Capability KB"
    load = state.load_kg + task.weight_kg
    if load > capacity + 1e-9:
        return f"payload left {capacity - state.load_kg:.2f} kg < {task.weight_kg:.2f} kg"
    target = Position(task.aisle, task.rack)
    to_object = distance(Position(state.aisle, state.rack), target)
    wh = energy.travel(to_object, state.load_kg, capacity) + energy.per_pick
    to_depot, end, end_load = 0.0, target, load
    if load >= cost.unload_at_fraction * capacity:  # full enough: unload at the depot
        to_depot = distance(target, depot)
        wh += energy.travel(to_depot, load, capacity)
        end, end_load = depot, 0.0
    if state.battery_wh - wh < cost.reserve_wh:
        return f"battery {state.battery_wh:.1f} Wh would fall below the {cost.reserve_wh:.1f} Wh reserve"
    after = replace(
        state, aisle=end.aisle, rack=end.rack, battery_wh=state.battery_wh - wh, load_kg=end_load, payload_kg=capacity
    )
    return Plan(robot_id, wh, after, to_object, to_depot)


def assign(
    task: TaskFacts,
    states: Mapping[str, PlannedState],
    energy: Mapping[str, RobotEnergy],
    distance: Distance,
    depot: Position,
    cost: CostModel,
) -> Assignment:
    """Minimum-cost robot among ``states``; ties go to the first robot id in natural order."""
    costs: dict[str, float | None] = {}
    reasons: dict[str, str] = {}
    best: Plan | None = None
    for robot_id in sorted(states, key=robot_sort_key):
        plan = plan_for(robot_id, states[robot_id], task, energy.get(robot_id), distance, depot, cost)
        if isinstance(plan, str):
            costs[robot_id], reasons[robot_id] = None, plan
            continue
        # Round so that float noise cannot split a tie differently on two robots.
        costs[robot_id] = round(plan.cost_wh, 6)
        if best is None or round(plan.cost_wh, 6) < round(best.cost_wh, 6):
            best = plan
    return Assignment(best.robot_id if best else None, costs, reasons, best)
