"""The robot state codec: lossless, compact, and as docs/robot-state.cddl says."""

from __future__ import annotations

import math
from dataclasses import replace

import cbor2
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support import ROOT, require

from coapkb.agent.robot_state import ACTIVITIES, Decision, LiveState, PlannedState, RobotState

CDDL = (ROOT / "docs" / "robot-state.cddl").read_text()
PLAN = PlannedState(3, 21, 412.25, 0.8, 60.6, 5)
MISPLACED = "not where the KB says it is (misplaced)"
MISSED = ((4, MISPLACED), (7, "gone: picked by Robot4 at task 6"))

ids = st.sampled_from(["Robot1", "Robot2", "Robot10"])
floats = st.floats(min_value=0, max_value=1e4, allow_nan=False)
plans = st.builds(PlannedState, st.integers(0, 50), st.integers(0, 50), floats, floats, floats, st.integers(0, 1000))
missed = st.lists(st.tuples(st.integers(0, 10**6), st.text(max_size=40)), max_size=8).map(tuple)
#: Tasks fenced and why, as the executor sets them: a reason only with tasks
#: (an empty reason is sent as "" and read back as None).
fences = st.just(((), None)) | st.tuples(st.lists(st.integers(0, 1000), min_size=1, max_size=3).map(tuple),
                                         st.none() | st.text(min_size=1, max_size=30))
lives = st.builds(
    lambda base, fence, missed: replace(base, fenced=fence[0], fence_reason=fence[1], missed=missed),
    st.builds(LiveState, floats, floats, st.sampled_from(ACTIVITIES), st.none() | st.text(max_size=20),
              st.integers(0, 100), st.integers(0, 100)),
    fences,
    missed,
)
decisions = st.builds(
    Decision,
    st.integers(0, 1000),
    st.text(max_size=30),
    st.booleans(),
    st.none() | ids,
    st.dictionaries(ids, st.none() | floats, max_size=3),
    st.none() | st.text(max_size=40),
    floats,
    st.dictionaries(ids, st.text(max_size=30), max_size=3),
    st.integers(0, 5),
    st.lists(ids, max_size=3).map(tuple),
    st.none() | st.text(max_size=40),
    st.none() | st.text(min_size=1, max_size=40),
)
states = st.builds(RobotState, ids, plans, lives, st.none() | decisions, st.none() | plans, st.integers(0, 2**32 - 1),
                   st.none() | decisions)


@pytest.fixture(scope="module")
def validator() -> object:
    try:
        import cddl_verifier
    except ImportError:
        require(False, "cddl-verifier is not installed (a test dependency in pyproject.toml)")
    return cddl_verifier.Validator(CDDL)


@given(states)
def test_round_trip_is_exact(state: RobotState) -> None:
    assert RobotState.decode(state.encode()) == state


@given(states)
def test_plan_carries_what_teammates_need(state: RobotState) -> None:
    seen = RobotState.decode(state.encode_plan())
    assert (seen.robot_id, seen.plan, seen.prev) == (state.robot_id, state.plan, state.prev)


def test_matches_the_cddl(validator: object) -> None:
    plan = PlannedState(3, 21, 412.25, 0.8, 60.6, 5)
    state = RobotState(
        "Robot1", plan, LiveState(3.0, 21.0, "picking", "Gucci_bag_14", 0, 4),
        Decision(5, "Gucci_bag_14", False, "Robot1", {"Robot1": 2.12, "Robot3": None}, None, 0.02,
                 {"Robot3": "cannot pick by gripping"}),
        PlannedState(9, 6, 414.37, 0.0, 60.6, 4),
    )
    unavailable = replace(state, last=Decision(6, "Gucci_bag_15", unavailable="no live robot holds the Object KB"))
    charging = replace(state, live=LiveState(2.0, 26.0, "charging", "Gucci_bag_14", 1, 4))
    for data, root in ((state.encode(), "robot-state"), (state.encode_plan(), "robot-plan"),
                       (unavailable.encode(), "robot-state"), (charging.encode(), "robot-state")):
        outcome = validator.validate(data, root_type=root)  # type: ignore[attr-defined]
        assert outcome.valid, [str(d) for d in outcome.diagnostics]


@given(states)
def test_outcome_carries_what_the_feeder_acts_on(state: RobotState) -> None:
    seen = RobotState.decode(state.encode_outcome())
    acted_on = replace(state.live, aisle=0, rack=0, executing=None)  # where and what: for people (/robot/state)
    assert (seen.robot_id, seen.plan.seq, seen.live, seen.boot, seen.prev) == ("", state.plan.seq, acted_on,
                                                                              state.boot, None)
    if state.last is None:
        assert seen.last is None
        return
    last, got = state.last, seen.last
    assert got is not None
    assert (got.seq, got.object, got.skipped, got.assigned_to, got.error, got.epoch, got.unavailable) == (
        last.seq, "", last.skipped, last.assigned_to, last.error, last.epoch, last.unavailable)
    assert got.members == (last.members if last.epoch else ())
    carries = last.assigned_to in (None, state.robot_id)
    assert got.reasons == (last.reasons if carries else {})
    assert got.costs.keys() == (last.costs.keys() if carries else set())
    for robot, cost in got.costs.items():  # in single precision: within float32's relative step
        sent = last.costs[robot]
        assert (cost is None) == (sent is None)
        if cost is not None and sent is not None and math.isfinite(sent) and abs(sent) < 3e38:
            assert cost == pytest.approx(sent, rel=2**-23, abs=1e-38)


def test_the_outcome_is_half_the_state_and_matches_the_cddl(validator: object) -> None:
    costs = {"Robot1": 12.345678912, "Robot2": 10.98765432, "Robot3": None}
    members = ("Robot1", "Robot2", "Robot3")
    loser = RobotState(
        "Robot1", PlannedState(12, 7, 512.3456789123, 23.4567891, 60.6, 14),
        LiveState(11.5, 6.25, "travelling", "Gucci_bag_14", 1, 13),
        Decision(14, "Hermes_scarf_231", False, "Robot2", costs, None, 0.123456789,
                 {"Robot3": "cannot pick by suction"}, 0, members),
        PlannedState(11, 3, 520.123456789, 13.456789, 60.6, 13), boot=3123456789,
    )
    winner = replace(loser, robot_id="Robot2")
    assert len(loser.encode_outcome()) * 2 < len(loser.encode())
    assert len(winner.encode_outcome()) < len(winner.encode()) - 50
    # Its zeros are integers and its costs single floats: 35 and 97 bytes (41 and 111 as float64 and 0.0).
    assert (len(loser.encode_outcome()), len(winner.encode_outcome())) == (35, 97)
    for state in (loser, winner, replace(loser, last=replace(loser.last, epoch=1))):
        outcome = validator.validate(state.encode_outcome(), root_type="robot-outcome")  # type: ignore[attr-defined]
        assert outcome.valid, [str(d) for d in outcome.diagnostics]


def test_compact_enough_for_slow_links() -> None:
    state = RobotState(
        "Robot1", PlannedState(3, 21, 412.25, 0.8, 60.6, 5), LiveState(3.0, 21.0),
        Decision(5, "Gucci_bag_14", False, "Robot1", {"Robot1": 2.12, "Robot2": 3.5, "Robot3": None}),
        PlannedState(9, 6, 414.37, 0.0, 60.6, 4),
    )
    assert len(state.encode_plan()) < 80
    assert len(state.encode()) < 200


@pytest.mark.parametrize("garbage", [b"", b"\xff", b"\x80", b"\x83\x01\x02\x03", b"\xa1\x01\x02"])
def test_garbage_is_a_value_error(garbage: bytes) -> None:
    with pytest.raises(ValueError):
        RobotState.decode(garbage)


def test_incarnation_travels_in_both_forms_and_is_optional(validator: object) -> None:
    state = RobotState("Robot1", PlannedState(3, 21, 412.25, 0.8, 60.6, 5), LiveState(3.0, 21.0), boot=2**32 - 1)
    assert RobotState.decode(state.encode()) == state
    assert RobotState.decode(state.encode_plan()).boot == state.boot
    for data, root in ((state.encode(), "robot-state"), (state.encode_plan(), "robot-plan")):
        assert validator.validate(data, root_type=root).valid  # type: ignore[attr-defined]
    assert len(state.encode_plan()) < 80




def test_the_decision_a_restarted_robot_joined_on_travels_until_it_decides(validator: object) -> None:
    """A joiner's state shows the teammate's decision it took its membership
    from, after the incarnation (0 if unnamed); neither its plan nor its
    outcome carries it, and its first decision of its own drops it."""
    on = Decision(9, "Gucci_bag_14", assigned_to="Robot3", epoch=4, members=("Robot1", "Robot2", "Robot3"))
    for boot in (0, 5):
        state = RobotState("Robot1", PlannedState(3, 21, 412.25, 0.8, 60.6, 9), LiveState(3.0, 21.0), boot=boot,
                           joined=on)
        assert RobotState.decode(state.encode()) == state
        assert validator.validate(state.encode(), root_type="robot-state").valid  # type: ignore[attr-defined]
        assert RobotState.decode(state.encode_plan()).joined is None
        assert RobotState.decode(state.encode_outcome()).joined is None
        decided = state.with_plan(replace(state.plan, seq=10), Decision(10, "Box", assigned_to="Robot1"))
        assert decided.joined is None

_PLAN = [3, 4, 500.0, 1.5, 60.0, 2]
_LIVE = [3.0, 4.0, 0, None, 0, 0]
#: Found by fuzzing: states of the right shape with values of the wrong type
#: decoded, and failed later where they were used (the first one in encode:
#: float() of a CBOR tag).
WRONG_TYPES = {
    "tag-for-a-float": bytes.fromhex("8466526f626f743286030"
                                     "4f97b5fd0f93e00f953800286010"
                                     "0f96058f90000fb404e4ccccccccccd0019303"
                                     "9"),
    "text-for-an-aisle": cbor2.dumps(["Robot1", ["3", 4, 500.0, 1.5, 60.0, 2], None]),
    "bool-for-a-seq": cbor2.dumps(["Robot1", [3, 4, 500.0, 1.5, 60.0, True], None]),
    "unknown-activity": cbor2.dumps(["Robot1", _PLAN, None, [3.0, 4.0, 9, None, 0, 0], None]),
    "negative-activity": cbor2.dumps(["Robot1", _PLAN, None, [3.0, 4.0, -1, None, 0, 0], None]),
    "number-for-an-id": cbor2.dumps([7, _PLAN, None]),
    "costs-not-a-map": cbor2.dumps(["Robot1", _PLAN, None, _LIVE, [2, "Box", False, None, [1], None, 0.1, {}]]),
    "members-not-text": cbor2.dumps(["Robot1", _PLAN, None, _LIVE, [2, "Box", False, None, {}, None, 0.1, {}, 1, [5]]]),
}


@pytest.mark.parametrize("data", WRONG_TYPES.values(), ids=WRONG_TYPES.keys())
def test_values_of_the_wrong_type_are_a_value_error(data: bytes) -> None:
    with pytest.raises(ValueError, match="not a robot state"):
        RobotState.decode(data)


# What became of a task: the tasks whose object was not at the shelf
# (``LiveState.missed``) and why a task was skipped (``Decision.skip_reason``).


@given(states)
def test_the_outcome_keeps_what_the_feeder_records(state: RobotState) -> None:
    seen = RobotState.decode(state.encode_outcome())
    assert (seen.live.done, seen.live.fenced, seen.live.fence_reason, seen.live.missed) == (
        state.live.done, state.live.fenced, state.live.fence_reason, state.live.missed)
    if state.last is not None:
        assert seen.last is not None and seen.last.skip_reason == state.last.skip_reason


def test_the_missed_tasks_travel_with_or_without_a_fence() -> None:
    alone = RobotState("Robot1", PLAN, LiveState(3.0, 21.0, "idle", None, 0, 2, missed=MISSED))
    raw = cbor2.loads(alone.encode())
    assert raw[3][6:] == [[], "", [list(m) for m in MISSED]]  # the fence's place kept, empty
    assert RobotState.decode(alone.encode()).live.missed == MISSED
    fenced = replace(alone, live=replace(alone.live, fenced=(9,), fence_reason="Robot2 refused"))
    live = RobotState.decode(fenced.encode_outcome()).live
    assert (live.fenced, live.fence_reason, live.missed) == ((9,), "Robot2 refused", MISSED)
    # Nothing missed: the live state is as long as before there was a "missed".
    plain = replace(alone, live=replace(alone.live, missed=()))
    assert len(cbor2.loads(plain.encode())[3]) == 6


def test_a_skip_reason_is_sent_only_when_there_is_one() -> None:
    skipped = Decision(3, "Gucci_bag_14", skipped=True, skip_reason="picked by Robot2 at task 1")
    state = RobotState("Robot1", PLAN, LiveState(3.0, 21.0), skipped)
    assert cbor2.loads(state.encode())[4][-1] == "picked by Robot2 at task 1"
    assert RobotState.decode(state.encode_outcome()).last == replace(skipped, object="", coordination_s=0.0)
    unreasoned = replace(state, last=replace(skipped, skip_reason=None))
    assert len(cbor2.loads(unreasoned.encode())[4]) == 11
    assert RobotState.decode(unreasoned.encode()).last.skip_reason is None  # type: ignore[union-attr]


def test_missed_and_skip_reasons_match_the_cddl(validator: object) -> None:
    missed = RobotState("Robot1", PLAN, LiveState(3.0, 21.0, "picking", "Barilla_pasta_1", 1, 4, missed=MISSED),
                        Decision(8, "Gucci_bag_14", True, None, {}, None, 0.02, {}, 0, ("Robot1", "Robot2"), None,
                                 "picked by Robot2 at task 1"),
                        PlannedState(9, 6, 414.37, 0.0, 60.6, 4), boot=7)
    fenced = replace(missed, live=replace(missed.live, fenced=(3, 5), fence_reason="lost its lease"))
    eight = replace(missed, live=replace(missed.live, missed=tuple((s, MISPLACED) for s in range(1, 9))))
    no_reason = replace(missed, last=replace(missed.last, skip_reason=None))  # type: ignore[arg-type]
    for state in (missed, fenced, eight, no_reason):
        for data, root in ((state.encode(), "robot-state"), (state.encode_outcome(), "robot-outcome")):
            outcome = validator.validate(data, root_type=root)  # type: ignore[attr-defined]
            assert outcome.valid, [str(d) for d in outcome.diagnostics]


_PLAN = [3, 4, 500.0, 1.5, 60.0, 2]
#: A live state whose ninth item, ``missed``, is this.
MALFORMED_MISSED = {
    "not-an-array": 7,
    "an-entry-not-an-array": [4],
    "an-entry-of-one": [[4]],
    "an-entry-of-three": [[4, "why", 1]],
    "a-text-seq": [["4", "why"]],
    "a-negative-seq": [[-4, "why"]],
    "a-bool-seq": [[True, "why"]],
    "a-null-why": [[4, None]],
    "a-number-why": [[4, 5]],
    "a-map-entry": [{4: "why"}],
}


@pytest.mark.parametrize("value", MALFORMED_MISSED.values(), ids=MALFORMED_MISSED.keys())
def test_a_malformed_missed_is_a_value_error(value: object) -> None:
    data = cbor2.dumps(["Robot1", _PLAN, None, [3.0, 4.0, 0, None, 0, 1, [], "", value], None])
    with pytest.raises(ValueError, match="not a robot state"):
        RobotState.decode(data)


def test_a_live_state_of_ten_items_is_a_value_error() -> None:
    data = cbor2.dumps(["Robot1", _PLAN, None, [3.0, 4.0, 0, None, 0, 1, [], "", [], "more"], None])
    with pytest.raises(ValueError, match="6 to 9 items"):
        RobotState.decode(data)


@pytest.mark.parametrize("reason", [5, b"why", ["why"], True])
def test_a_skip_reason_that_is_not_text_is_a_value_error(reason: object) -> None:
    decision = [3, "Gucci_bag_14", True, None, {}, None, 0.0, {}, 0, [], None, reason]
    with pytest.raises(ValueError, match="skip-reason must be text"):
        RobotState.decode(cbor2.dumps(["Robot1", _PLAN, None, [3.0, 4.0, 0, None, 0, 1], decision]))


def test_a_decision_of_thirteen_items_is_a_value_error() -> None:
    decision = [3, "Gucci_bag_14", True, None, {}, None, 0.0, {}, 0, [], None, "why", "more"]
    with pytest.raises(ValueError, match="8 to 12 items"):
        RobotState.decode(cbor2.dumps(["Robot1", _PLAN, None, [3.0, 4.0, 0, None, 0, 1], decision]))


def test_a_previous_plan_unchanged_but_for_its_task_travels_as_that_task(validator: object) -> None:
    plan = PlannedState(3, 21, 412.25, 0.8, 60.6, 5)
    unchanged = RobotState("Robot2", plan, LiveState(3.0, 21.0), prev=replace(plan, seq=4), boot=7)
    moved = replace(unchanged, prev=PlannedState(9, 6, 414.37, 0.0, 60.6, 4))
    for state in (unchanged, moved):
        assert RobotState.decode(state.encode_plan()) == replace(state, live=LiveState(3.0, 21.0))
        assert RobotState.decode(state.encode()) == state
        for data, root in ((state.encode(), "robot-state"), (state.encode_plan(), "robot-plan")):
            outcome = validator.validate(data, root_type=root)  # type: ignore[attr-defined]
            assert outcome.valid, [str(d) for d in outcome.diagnostics]
    assert len(moved.encode_plan()) - len(unchanged.encode_plan()) >= 20
