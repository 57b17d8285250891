"""Task Assigner (the seed's Fig. 2): cost of every robot-task pair, minimum wins.

Pure functions: the same inputs give the same assignment on every robot,
which is what lets "compute by all" agree without a further message.  The
cost is battery consumption in Wh: travel on the warehouse's aisle graph at
a load-dependent energy per metre, plus an energy to pick, plus the trip to
the depot when the pick fills the robot up.  Each robot's energy figures come
from the Capability KB (robots differ).

Batteries run down and charge: a robot must end every task able to reach
the nearest charging dock (Location KB) without dipping below the reserve.
When a task would leave it short, it first drives to a dock and charges to
full; that task's cost then also holds the detour and the charging time
(``[cost] charge_w`` sets how long a charge takes, ``charge_time_wh_per_s``
what a second at the dock costs), so a robot that needs no charge wins over
one that does.  Every input is in the shared planned states and the KBs, so
every robot still computes the same assignment.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

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
    payload (linear in between), Wh per pick, and its battery capacity (Wh),
    which a charge fills (None: unknown, so the robot cannot plan a charge)."""

    per_m_empty: float
    per_m_full: float
    per_pick: float
    capacity_wh: float | None = None

    def travel(self, metres: float, load_kg: float, payload_kg: float) -> float:
        fill = load_kg / payload_kg if payload_kg > 0 else 1.0
        return metres * (self.per_m_empty + (self.per_m_full - self.per_m_empty) * fill)


@dataclass(frozen=True)
class ChargeStop:
    """A detour to a charging dock before the task: drive there, charge to full."""

    dock: Position
    to_dock_m: float
    #: Battery on arrival at the dock and when it leaves (its capacity), Wh.
    arrive_wh: float
    full_wh: float
    #: Simulated seconds at the dock.
    charge_s: float


@dataclass(frozen=True)
class Plan:
    """The cost of one robot doing one task, and where that leaves it."""

    robot_id: str
    cost_wh: float
    after: PlannedState
    #: Distance to the object: from the robot's place, or from the dock when it charges first.
    to_object_m: float
    #: Distance carried to the depot after the pick; 0 when the robot keeps its load.
    to_depot_m: float
    #: The charge before the task, if the battery needs one.
    charge: ChargeStop | None = None

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


def robot_sort_key(robot_id: str) -> tuple[object, ...]:
    """Natural order, so Robot10 comes after Robot9 (the tie-break order)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", robot_id))


@dataclass(frozen=True)
class _Route:
    """The task itself from some start: energy, distances and where it ends."""

    wh: float
    to_object_m: float
    to_depot_m: float
    end: Position
    end_load_kg: float


def _route(
    start: Position, load_kg: float, task: TaskFacts, payload_kg: float, energy: RobotEnergy, distance: Distance,
    depot: Position, cost: CostModel,
) -> _Route:
    target = Position(task.aisle, task.rack)
    to_object = distance(start, target)
    wh = energy.travel(to_object, load_kg, payload_kg) + energy.per_pick
    load = load_kg + task.weight_kg
    if load >= cost.unload_at_fraction * payload_kg:  # full enough: unload at the depot
        to_depot = distance(target, depot)
        return _Route(wh + energy.travel(to_depot, load, payload_kg), to_object, to_depot, depot, 0.0)
    return _Route(wh, to_object, 0.0, target, load)


def _to_nearest_dock_wh(
    place: Position, load_kg: float, payload_kg: float, energy: RobotEnergy, docks: Sequence[Position],
    distance: Distance,
) -> float:
    """Energy to reach the nearest dock from ``place``; 0 without docks."""
    if not docks:
        return 0.0
    return energy.travel(min(distance(place, dock) for dock in docks), load_kg, payload_kg)


def plan_for(
    robot_id: str,
    state: PlannedState,
    task: TaskFacts,
    energy: RobotEnergy | None,
    distance: Distance,
    depot: Position,
    cost: CostModel,
    docks: Sequence[Position] = (),
) -> Plan | str:
    """The robot's plan for the task, or the reason it cannot take it.

    ``docks``: the charging docks; none means no robot can charge, and a
    task that would take a battery below the reserve is refused."""
    payload_kg = task.capable.get(robot_id)
    if payload_kg is None:
        return f"cannot pick by {task.grip}"
    if energy is None:
        return "no energy figures in the Capability KB"
    if state.load_kg + task.weight_kg > payload_kg + 1e-9:
        return f"payload left {payload_kg - state.load_kg:.2f} kg < {task.weight_kg:.2f} kg"
    here = Position(state.aisle, state.rack)

    def ends_above_reserve(battery_wh: float, route: _Route) -> bool:
        left = battery_wh - route.wh - _to_nearest_dock_wh(route.end, route.end_load_kg, payload_kg, energy, docks,
                                                           distance)
        return left >= cost.reserve_wh

    def plan(cost_wh: float, battery_wh: float, route: _Route, charge: ChargeStop | None = None) -> Plan:
        after = replace(state, aisle=route.end.aisle, rack=route.end.rack, battery_wh=battery_wh - route.wh,
                        load_kg=route.end_load_kg, payload_kg=payload_kg)
        return Plan(robot_id, cost_wh, after, route.to_object_m, route.to_depot_m, charge)

    direct = _route(here, state.load_kg, task, payload_kg, energy, distance, depot, cost)
    if ends_above_reserve(state.battery_wh, direct):
        return plan(direct.wh, state.battery_wh, direct)
    refusal = f"battery {state.battery_wh:.1f} Wh would fall below the {cost.reserve_wh:.1f} Wh reserve"
    if not docks or energy.capacity_wh is None:
        return refusal
    best: Plan | None = None
    for dock in docks:  # the cheapest dock to charge at; ties go to the first in the KB's order
        to_dock = distance(here, dock)
        arrive_wh = state.battery_wh - energy.travel(to_dock, state.load_kg, payload_kg)
        if arrive_wh < cost.reserve_wh:
            continue
        full_wh = max(energy.capacity_wh, arrive_wh)  # a charge never empties a battery started above it
        route = _route(dock, state.load_kg, task, payload_kg, energy, distance, depot, cost)
        if not ends_above_reserve(full_wh, route):
            continue
        charge_s = (full_wh - arrive_wh) / cost.charge_w * 3600.0
        cost_wh = (state.battery_wh - arrive_wh) + route.wh + charge_s * cost.charge_time_wh_per_s
        if best is None or round(cost_wh, 6) < round(best.cost_wh, 6):
            best = plan(cost_wh, full_wh, route, ChargeStop(dock, to_dock, arrive_wh, full_wh, charge_s))
    if best is None:
        return f"{refusal}, and no charging dock it can reach gives enough"
    return best


def assign(
    task: TaskFacts,
    states: Mapping[str, PlannedState],
    energy: Mapping[str, RobotEnergy],
    distance: Distance,
    depot: Position,
    cost: CostModel,
    docks: Sequence[Position] = (),
) -> Assignment:
    """Minimum-cost robot among ``states``; ties go to the first robot id in natural order."""
    costs: dict[str, float | None] = {}
    reasons: dict[str, str] = {}
    best: Plan | None = None
    for robot_id in sorted(states, key=robot_sort_key):
        plan = plan_for(robot_id, states[robot_id], task, energy.get(robot_id), distance, depot, cost, docks)
        if isinstance(plan, str):
            costs[robot_id], reasons[robot_id] = None, plan
            continue
        # Round so that float noise cannot split a tie differently on two robots.
        costs[robot_id] = round(plan.cost_wh, 6)
        if best is None or round(plan.cost_wh, 6) < round(best.cost_wh, 6):
            best = plan
    return Assignment(best.robot_id if best else None, costs, reasons, best)
