"""The Task Assigner's pure cost model: minimum cost wins, limits respected, deterministic."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coapkb.agent.robot_state import PlannedState
from coapkb.agent.task_assigner import RobotEnergy, TaskFacts, assign, plan_for, robot_sort_key
from coapkb.config import CostModel
from coapkb.world import Layout, Position, travel_distance

# 3 aisles of 10 racks; racks are 1.2 m, aisles 3.5 m apart, 2 m margins:
# rack r of any aisle is at y = 2 + (r - 0.5) * 1.2; the aisle is 2*2 + 10*1.2 = 16 m long.
LAYOUT = Layout(aisles=3, racks_per_aisle=10, rack_length_m=1.2, aisle_spacing_m=3.5, cross_aisle_margin_m=2.0)
DEPOT = Position(1, 0)
COST = CostModel(reserve_wh=20.0, unload_at_fraction=0.75)
ENERGY = RobotEnergy(per_m_empty=0.1, per_m_full=0.3, per_pick=0.5)


def distance(a: Position, b: Position) -> float:
    return travel_distance(a, b, LAYOUT)


def state(aisle: int = 1, rack: int = 0, battery: float = 500.0, load: float = 0.0, payload: float = 20.0,
          seq: int = 0) -> PlannedState:
    return PlannedState(aisle, rack, battery, load, payload, seq)


def task(aisle: int = 1, rack: int = 5, weight: float = 5.0, grip: str = "gripping",
         capable: dict[str, float] | None = None, seq: int = 1) -> TaskFacts:
    return TaskFacts(seq=seq, object="Thing_1", aisle=aisle, rack=rack, bin=1, weight_kg=weight, grip=grip,
                     capable={"Robot1": 20.0} if capable is None else capable)


def run(t: TaskFacts, states: dict[str, PlannedState], energy: dict[str, RobotEnergy] | None = None,
        cost: CostModel = COST):
    return assign(t, states, energy if energy is not None else {r: ENERGY for r in states}, distance, DEPOT, cost)


# --------------------------------------------------------------------------- arithmetic


def test_exact_cost_same_aisle_no_unload() -> None:
    # Robot at (1, 0) -> object at (1, 5): y(5) = 2 + 4.5 * 1.2 = 7.4 m along aisle 1.
    # Empty, so 0.1 Wh/m: 7.4 * 0.1 = 0.74 Wh; + 0.5 Wh to pick = 1.24 Wh.
    # Load after the pick 5 kg < 0.75 * 20 = 15 kg: no trip to the depot.
    result = run(task(weight=5.0), {"Robot1": state()})
    assert result.assigned_to == "Robot1"
    assert result.costs == {"Robot1": pytest.approx(1.24)}
    assert result.reasons == {}
    plan = result.plan
    assert plan is not None
    assert plan.to_object_m == pytest.approx(7.4)
    assert plan.to_depot_m == 0 and not plan.unloads
    assert (plan.after.aisle, plan.after.rack) == (1, 5)
    assert plan.after.load_kg == pytest.approx(5.0)
    assert plan.after.battery_wh == pytest.approx(500.0 - 1.24)
    assert plan.after.payload_kg == 20.0


def test_exact_cost_other_aisle_via_front() -> None:
    # (1, 0) -> (2, 5): across 3.5 m + min(front 0 + 7.4, back 2*16 - 0 - 7.4 = 24.6) = 10.9 m.
    # Already carrying 4 kg of 20 (fill 0.2): 0.1 + (0.3 - 0.1) * 0.2 = 0.14 Wh/m -> 10.9 * 0.14 = 1.526;
    # + 0.5 pick = 2.026 Wh.  Load 4 + 3 = 7 kg < 15: keeps it.
    result = run(task(aisle=2, rack=5, weight=3.0), {"Robot1": state(load=4.0)})
    assert result.costs["Robot1"] == pytest.approx(2.026)
    assert result.plan is not None and result.plan.to_object_m == pytest.approx(10.9)
    assert result.plan.after.load_kg == pytest.approx(7.0)


def test_unloads_at_depot_when_load_reaches_fraction() -> None:
    # Same trip as the first test (7.4 m empty + pick = 1.24 Wh), but 16 kg >= 0.75 * 20 = 15 kg:
    # carry it back 7.4 m to the depot (1, 0) at fill 16/20 = 0.8 -> 0.1 + 0.2 * 0.8 = 0.26 Wh/m,
    # 7.4 * 0.26 = 1.924 Wh.  Total 3.164 Wh; ends empty at the depot.
    result = run(task(weight=16.0), {"Robot1": state()})
    plan = result.plan
    assert plan is not None and plan.unloads
    assert plan.to_depot_m == pytest.approx(7.4)
    assert result.costs["Robot1"] == pytest.approx(3.164)
    assert (plan.after.aisle, plan.after.rack) == (DEPOT.aisle, DEPOT.rack)
    assert plan.after.load_kg == 0.0


def test_unload_threshold_is_inclusive_and_counts_existing_load() -> None:
    # 10 kg already + 5 kg = 15 kg = exactly 0.75 * 20: unloads.
    assert run(task(weight=5.0), {"Robot1": state(load=10.0)}).plan.unloads  # type: ignore[union-attr]
    # 9.9 + 5 = 14.9 kg: keeps the load.
    kept = run(task(weight=5.0), {"Robot1": state(load=9.9)}).plan
    assert kept is not None and not kept.unloads and kept.after.load_kg == pytest.approx(14.9)
    # A lower threshold makes the same pick unload.
    low = run(task(weight=5.0), {"Robot1": state()}, cost=CostModel(unload_at_fraction=0.25)).plan
    assert low is not None and low.unloads


# --------------------------------------------------------------------------- choice


def test_minimum_cost_robot_wins() -> None:
    states = {
        "Robot1": state(aisle=3, rack=10),  # far away
        "Robot2": state(aisle=1, rack=4),  # one rack from the object
        "Robot3": state(aisle=2, rack=5),
    }
    result = run(task(capable={"Robot1": 20.0, "Robot2": 20.0, "Robot3": 20.0}), states)
    assert result.assigned_to == "Robot2"
    finite = {r: c for r, c in result.costs.items() if c is not None}
    assert set(finite) == set(states)
    assert finite["Robot2"] == min(finite.values())
    assert finite["Robot2"] < finite["Robot1"] and finite["Robot2"] < finite["Robot3"]


def test_robot_energy_figures_matter() -> None:
    # Same place; Robot2 is twice as frugal -> it wins.
    states = {"Robot1": state(), "Robot2": state()}
    energy = {"Robot1": ENERGY, "Robot2": RobotEnergy(0.05, 0.15, 0.25)}
    result = run(task(capable={"Robot1": 20.0, "Robot2": 20.0}), states, energy)
    assert result.assigned_to == "Robot2"
    assert result.costs["Robot2"] == pytest.approx(0.62)


def test_incapable_robot_never_gets_the_task() -> None:
    # Robot1 sits right at the object but cannot pick by suction.
    states = {"Robot1": state(aisle=1, rack=5), "Robot2": state(aisle=3, rack=10)}
    result = run(task(grip="suction", capable={"Robot2": 20.0}), states)
    assert result.assigned_to == "Robot2"
    assert result.costs["Robot1"] is None
    assert "suction" in result.reasons["Robot1"]
    assert "Robot2" not in result.reasons


def test_nobody_capable_means_no_assignment() -> None:
    result = run(task(capable={}), {"Robot1": state(), "Robot2": state()})
    assert result.assigned_to is None and result.plan is None
    assert result.costs == {"Robot1": None, "Robot2": None}
    assert set(result.reasons) == {"Robot1", "Robot2"}


def test_payload_left_too_small() -> None:
    # Robot1 (close) has 12 of 20 kg on board: 12 + 9 = 21 > 20.  Robot2 (far, empty) gets it.
    states = {"Robot1": state(aisle=1, rack=5, load=12.0), "Robot2": state(aisle=3, rack=10)}
    result = run(task(weight=9.0, capable={"Robot1": 20.0, "Robot2": 20.0}), states)
    assert result.assigned_to == "Robot2"
    assert result.costs["Robot1"] is None
    assert "payload" in result.reasons["Robot1"]
    # The capacity that counts is Query_4's payload for the robot: too heavy for a 8 kg robot even when empty.
    small = run(task(weight=9.0, capable={"Robot1": 8.0}), {"Robot1": state(payload=100.0)})
    assert small.assigned_to is None and "payload" in small.reasons["Robot1"]
    # Exactly full is allowed.
    exact = run(task(weight=8.0, capable={"Robot1": 20.0}), {"Robot1": state(load=12.0)})
    assert exact.assigned_to == "Robot1"


def test_battery_reserve_respected() -> None:
    # The first test's pick costs 1.24 Wh.  With 21.24 Wh the battery ends at exactly the 20 Wh reserve: allowed.
    ok = run(task(), {"Robot1": state(battery=21.24 + 1e-9)})
    assert ok.assigned_to == "Robot1"
    # With 21.2 Wh it would end at 19.96 < 20: refused, and the reason names the reserve.
    low = run(task(), {"Robot1": state(battery=21.2)})
    assert low.assigned_to is None and low.costs["Robot1"] is None
    assert "reserve" in low.reasons["Robot1"]
    # A robot with a low battery loses to a dearer one that can afford it.
    states = {"Robot1": state(battery=21.2), "Robot2": state(aisle=3, rack=10, battery=500.0)}
    mixed = run(task(capable={"Robot1": 20.0, "Robot2": 20.0}), states)
    assert mixed.assigned_to == "Robot2"
    # Without a reserve the low robot can take it.
    free = run(task(), {"Robot1": state(battery=1.3)}, cost=CostModel(reserve_wh=0.0))
    assert free.assigned_to == "Robot1"


def test_missing_energy_figures_is_a_reason_not_a_crash() -> None:
    result = assign(task(), {"Robot1": state()}, {}, distance, DEPOT, COST)
    assert result.assigned_to is None and "energy" in result.reasons["Robot1"]


def test_ties_go_to_the_first_robot_in_natural_order() -> None:
    ids = ["Robot10", "Robot2", "Robot9", "Robot11"]
    states = {r: state() for r in ids}
    result = run(task(capable={r: 20.0 for r in ids}), states)
    assert len({result.costs[r] for r in ids}) == 1
    assert result.assigned_to == "Robot2"  # not "Robot10" (string order)
    assert list(result.costs) == ["Robot2", "Robot9", "Robot10", "Robot11"]
    assert sorted(ids, key=robot_sort_key) == ["Robot2", "Robot9", "Robot10", "Robot11"]
    # Insertion order of the mapping does not matter.
    again = run(task(capable={r: 20.0 for r in ids}), dict(reversed(list(states.items()))))
    assert again == result


def test_float_noise_does_not_split_a_tie() -> None:
    # Robot10's cost differs by float noise only (1e-12 Wh): still a tie, Robot2 wins.
    states = {"Robot10": state(), "Robot2": state()}
    energy = {"Robot10": ENERGY, "Robot2": RobotEnergy(0.1, 0.3, 0.5 + 1e-12)}
    result = run(task(capable={"Robot10": 20.0, "Robot2": 20.0}), states, energy)
    assert result.assigned_to == "Robot2"


def test_same_inputs_same_output() -> None:
    states = {f"Robot{i}": state(aisle=1 + i % 3, rack=i % 11, load=float(i % 4)) for i in range(1, 10)}
    capable = {f"Robot{i}": 10.0 + i for i in range(1, 10) if i % 3}
    t = task(aisle=2, rack=7, weight=4.0, capable=capable)
    first = run(t, states)
    for _ in range(5):
        assert run(t, dict(states)) == first


def test_plan_for_reports_reason_strings() -> None:
    assert isinstance(plan_for("RobotX", state(), task(), ENERGY, distance, DEPOT, COST), str)


# --------------------------------------------------------------------------- property

positions = st.builds(Position, st.integers(1, LAYOUT.aisles), st.integers(0, LAYOUT.racks_per_aisle + 1))


@st.composite
def scenarios(draw):
    n = draw(st.integers(1, 7))
    ids = [f"Robot{i}" for i in draw(st.lists(st.integers(1, 30), min_size=n, max_size=n, unique=True))]
    states, energy, capable = {}, {}, {}
    for r in ids:
        payload = draw(st.floats(1.0, 100.0))
        pos = draw(positions)
        states[r] = PlannedState(pos.aisle, pos.rack, draw(st.floats(0.0, 200.0)),
                                 draw(st.floats(0.0, payload)), payload)
        empty = draw(st.floats(0.01, 0.5))
        energy[r] = RobotEnergy(empty, empty + draw(st.floats(0.0, 0.5)), draw(st.floats(0.0, 3.0)))
        if draw(st.booleans()):
            capable[r] = payload
    target = draw(positions)
    facts = TaskFacts(1, "Thing_1", target.aisle, target.rack, 1, draw(st.floats(0.0, 60.0)), "gripping", capable)
    cost = CostModel(reserve_wh=draw(st.floats(0.0, 50.0)), unload_at_fraction=draw(st.floats(0.05, 1.0)))
    return facts, states, energy, cost


@settings(max_examples=300, deadline=None)
@given(scenarios())
def test_winner_is_cheapest_capable_and_fits(scenario) -> None:
    facts, states, energy, cost = scenario
    result = assign(facts, states, energy, distance, DEPOT, cost)
    assert set(result.costs) == set(states)
    finite = {r: c for r, c in result.costs.items() if c is not None}
    assert set(result.reasons) == set(states) - set(finite)
    if result.assigned_to is None:
        assert not finite and result.plan is None
        return
    winner = result.assigned_to
    assert winner in facts.capable
    assert states[winner].load_kg + facts.weight_kg <= facts.capable[winner] + 1e-9
    assert result.costs[winner] is not None
    assert all(result.costs[winner] <= c for c in finite.values())
    # Ties among the cheapest go to the first in natural order.
    cheapest = [r for r, c in finite.items() if c == result.costs[winner]]
    assert winner == min(cheapest, key=robot_sort_key)
    assert result.plan is not None and result.plan.robot_id == winner
    assert result.plan.after.battery_wh >= cost.reserve_wh - 1e-9
    assert 0.0 <= result.plan.after.load_kg <= facts.capable[winner] + 1e-9
    # Every robot with a finite cost is capable, fits, and keeps its reserve.
    for r in finite:
        assert r in facts.capable
        assert states[r].load_kg + facts.weight_kg <= facts.capable[r] + 1e-9
        assert states[r].battery_wh - finite[r] >= cost.reserve_wh - 1e-5
    # Deterministic.
    assert assign(facts, dict(reversed(list(states.items()))), energy, distance, DEPOT, cost) == result


# --------------------------------------------------------------------------- charging

DOCK = Position(3, 11)  # the back end of aisle 3
CHARGING = RobotEnergy(per_m_empty=0.1, per_m_full=0.3, per_pick=0.5, capacity_wh=100.0)


def test_a_short_battery_drives_to_a_dock_and_charges_first() -> None:
    # Straight to (1, 5) costs 1.24 Wh (test_exact_cost_same_aisle_no_unload) and leaves the
    # robot 15.6 m from the dock (7 m across + 8.6 m by the back cross-aisle) with 5 kg of
    # 20: 0.15 Wh/m, 2.34 Wh.  23 - 1.24 - 2.34 = 19.42 Wh < the 20 Wh reserve: charge first.
    result = assign(task(weight=5.0), {"Robot1": state(battery=23.0)}, {"Robot1": CHARGING}, distance, DEPOT,
                    COST, (DOCK,))
    plan = result.plan
    assert result.assigned_to == "Robot1" and plan is not None and plan.charge is not None
    # To the dock: 7 m across + 16 m up aisle 3, empty: 2.3 Wh, arriving with 20.7 Wh.
    assert plan.charge.dock == DOCK and plan.charge.to_dock_m == pytest.approx(23.0)
    assert plan.charge.arrive_wh == pytest.approx(20.7) and plan.charge.full_wh == 100.0
    # 79.3 Wh at 500 W: 570.96 s at the dock, 0.05 Wh each.
    assert plan.charge.charge_s == pytest.approx(79.3 / 500 * 3600)
    # Then from the dock to (1, 5), 15.6 m empty (1.56 Wh), and the pick (0.5 Wh).
    assert plan.to_object_m == pytest.approx(15.6)
    assert result.costs == {"Robot1": pytest.approx(2.3 + 2.06 + 570.96 * 0.05)}
    assert plan.after.battery_wh == pytest.approx(100.0 - 2.06)
    assert (plan.after.aisle, plan.after.rack, plan.after.load_kg) == (1, 5, pytest.approx(5.0))


def test_enough_battery_for_the_task_and_the_dock_goes_straight() -> None:
    # 24 - 1.24 - 2.34 = 20.42 Wh >= 20: no detour, the cost of before.
    result = assign(task(weight=5.0), {"Robot1": state(battery=24.0)}, {"Robot1": CHARGING}, distance, DEPOT,
                    COST, (DOCK,))
    assert result.plan is not None and result.plan.charge is None
    assert result.costs == {"Robot1": pytest.approx(1.24)}


def test_a_robot_that_need_not_charge_wins_over_a_nearer_one_that_must() -> None:
    states = {"Robot1": state(battery=23.0), "Robot2": state(aisle=3, rack=10, battery=500.0)}
    capable = {"Robot1": 20.0, "Robot2": 20.0}
    result = assign(task(weight=5.0, capable=capable), states, {r: CHARGING for r in states}, distance, DEPOT,
                    COST, (DOCK,))
    assert result.assigned_to == "Robot2" and result.plan is not None and result.plan.charge is None
    assert result.costs["Robot1"] == pytest.approx(2.3 + 2.06 + 570.96 * 0.05)


def test_the_cheapest_dock_is_chosen_and_charging_time_follows_the_rate() -> None:
    # 21 - 1.24 - 1.11 (7.4 m back to the nearest dock, loaded) < 20: charge first.  The
    # (3, 11) dock is out of reach above the reserve (it would arrive with 18.7 Wh); the
    # one at the front end of aisle 1 is where the robot stands: no detour at all.
    docks = (DOCK, Position(1, 0))
    fast = CostModel(reserve_wh=20.0, unload_at_fraction=0.75, charge_w=1000.0, charge_time_wh_per_s=0.01)
    plan = assign(task(weight=5.0), {"Robot1": state(battery=21.0)}, {"Robot1": CHARGING}, distance, DEPOT,
                  fast, docks).plan
    assert plan is not None and plan.charge is not None and plan.charge.dock == Position(1, 0)
    assert plan.charge.to_dock_m == 0 and plan.charge.charge_s == pytest.approx(79.0 / 1000 * 3600)
    assert plan.cost_wh == pytest.approx(1.24 + 284.4 * 0.01)


def test_no_dock_or_no_capacity_means_refusal_as_before() -> None:
    for energy, docks in ((CHARGING, ()), (ENERGY, (DOCK,))):
        result = assign(task(weight=5.0), {"Robot1": state(battery=21.0)}, {"Robot1": energy}, distance, DEPOT,
                        COST, docks)
        assert result.assigned_to is None
        assert result.reasons["Robot1"].startswith("battery 21.0 Wh would fall below the 20.0 Wh reserve")


def test_a_battery_that_reaches_no_dock_above_the_reserve_is_refused() -> None:
    # 22 Wh, 2.3 Wh to the dock: it would arrive with 19.7 Wh, under the reserve.
    result = assign(task(weight=5.0), {"Robot1": state(battery=22.0)}, {"Robot1": CHARGING}, distance, DEPOT,
                    COST, (DOCK,))
    assert result.assigned_to is None and "no charging dock" in result.reasons["Robot1"]
