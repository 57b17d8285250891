"""A robot's state, as its teammates see it through Observe (RFC 7641).

``/robot/plan`` carries what teammates need to assign tasks; ``/robot/state``
adds the live part and the last decision, for people; ``/robot/outcome`` is
the part of it the feeder acts on.
Two parts with different jobs:

* ``plan``: the state the Task Assigner reasons with (where the robot will be,
  its battery and load once its assigned tasks are done) and ``seq``, the last
  task it has decided.  It changes only at decisions, so every robot that
  waits for its teammates' ``seq`` computes on identical inputs, which is what
  makes "compute by all" agree.
* ``live``: what the robot is doing now (the Task Executor's progress), for
  people and monitors; never used for decisions.
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass, field, replace
from typing import Any, overload

import cbor2

#: A process's ``boot`` is drawn from 1 up to this, excluded: nonzero, so it
#: is always sent; and this value names no process (:data:`NO_PROCESS`).
BOOT_LIMIT = 2**32
#: The process a joiner that took no post is named with: whatever process
#: of it is found is another one, counted a restart.
NO_PROCESS = BOOT_LIMIT


@dataclass(frozen=True)
class PlannedState:
    aisle: int
    rack: int
    battery_wh: float
    load_kg: float
    payload_kg: float
    #: Sequence number of the last task this robot has decided (0 = none yet).
    seq: int = 0


@dataclass(frozen=True)
class Decision:
    """One robot's outcome for one task."""

    seq: int
    object: str
    skipped: bool = False
    assigned_to: str | None = None
    #: Cost in Wh per robot; None for robots that cannot take the task.
    costs: dict[str, float | None] = field(default_factory=dict)
    error: str | None = None
    coordination_s: float = 0.0
    #: Why a robot cannot take the task (robot id -> reason), for people.
    reasons: dict[str, str] = field(default_factory=dict)
    #: The membership the decision was taken in: its epoch (membership
    #: changes so far) and the robots taking part, so survivors' agreement
    #: on who is in the team is visible in the record.
    epoch: int = 0
    members: tuple[str, ...] = ()
    #: Why the task cannot be done now: a KB module it needs has no live holder.
    unavailable: str | None = None
    #: Why the task is skipped: no such object, already picked (by whom, at
    #: which task), or missing from its place.
    skip_reason: str | None = None


@dataclass(frozen=True)
class LiveState:
    aisle: float
    rack: float
    activity: str = "idle"  # idle | travelling | picking | unloading | charging
    executing: str | None = None
    queued: int = 0
    done: int = 0
    #: Tasks whose jobs this robot dropped without executing them: it lost
    #: its lease (a majority of its cluster refused it or is unreachable),
    #: so the team may have given them to another (TaskExecutor).
    fenced: tuple[int, ...] = ()
    fence_reason: str | None = None
    #: The latest tasks whose object was not at the shelf: (task, why).
    missed: tuple[tuple[int, str], ...] = ()


@dataclass(frozen=True)
class RobotState:
    robot_id: str
    plan: PlannedState
    live: LiveState
    last: Decision | None = None
    #: The plan before the last decision: a teammate that is one task ahead
    #: still shows the state the others need for that task.
    prev: PlannedState | None = None
    #: This process's incarnation (a random number drawn at start, 0 =
    #: unnamed): a restarted robot has a new one, so teammates can tell it
    #: from the process they knew even before it decides anything.
    boot: int = 0
    #: The teammate's decision whose membership a restarted robot joined
    #: on (of the task before its join, or of that task counting it in),
    #: until it decides one itself: a co-joiner that no longer reaches that
    #: teammate joins on the same membership (:func:`.joining.joined_on`).
    joined: Decision | None = None

    def with_plan(self, plan: PlannedState, last: Decision) -> RobotState:
        return replace(self, plan=plan, last=last, prev=self.plan, joined=None)

    def decided(self, seq: int) -> bool:
        """Whether this robot has decided task ``seq`` (or one after it)."""
        return self.last is not None and self.last.seq >= seq

    def plan_at(self, seq: int) -> PlannedState | None:
        """The planned state right after task ``seq`` was decided, if still known."""
        for plan in (self.plan, self.prev):
            if plan is not None and plan.seq == seq:
                return plan
        return None

    def to_dict(self) -> dict[str, Any]:
        """Readable form (for JSON clients and records)."""
        return asdict(self)

    def encode(self) -> bytes:
        """Compact CBOR (docs/robot-state.cddl): positional arrays, no key
        strings; several teammates observe this on slow links."""
        return self._encode(_plan_array(self.plan))

    def _encode(self, plan: list[object] | None) -> bytes:
        return cbor2.dumps(
            [
                self.robot_id,
                plan,
                _prev_item(self.plan, self.prev),
                [self.live.aisle, self.live.rack, ACTIVITIES.index(self.live.activity), self.live.executing,
                 self.live.queued, self.live.done,
                 *self._live_tail()],
                None if self.last is None else _decision_array(self.last),
                # The decision joined on needs the incarnation before it, 0 if unnamed.
                *([self.boot, _decision_array(self.joined)] if self.joined is not None else self._boot()),
            ],
            canonical=True,  # smallest lossless float widths
        )

    def encode_outcome(self) -> bytes:
        """What the feeder acts on, as a ``robot-outcome`` (docs/robot-state.cddl):
        :meth:`encode`'s array without what only people and teammates read.

        No previous plan (teammates read it on ``/robot/plan``).  The last
        decision without its coordination time (the feeder times tasks
        itself), its members only once the membership has changed (epoch
        above 0: before that they are the cluster the feeder fed), and its
        costs and reasons only from the robot the task went to, or from
        every robot when it went to none: every robot of a cluster computes
        the same costs, and the feeder records one robot's.  The feeder
        observes every robot after every task, so this is about half of
        what it was sent.  The robot's id and the decision's object are
        empty: the feeder knows whom it observes and what it fed as task
        ``seq`` (about 20 bytes of each of four notifications a task)."""
        last = self.last
        if last is not None:
            carries = last.assigned_to is None or last.assigned_to == self.robot_id
            last = replace(last, object="", coordination_s=0, members=last.members if last.epoch else (),
                           costs=_single_precision(last.costs) if carries else {},
                           reasons=last.reasons if carries else {})
        # Of the plan only its task, of the live part not where the robot is
        # nor what it picks: people read those on /robot/state (a recording
        # feeder observes that instead).  The zeros in their places are
        # integers: one byte each, where 0.0 takes three.
        live = replace(self.live, aisle=0, rack=0, executing=None)
        return replace(self, robot_id="", prev=None, live=live, last=last, joined=None)._encode([self.plan.seq])

    def _live_tail(self) -> list[object]:
        live = self.live
        tail: list[object] = [list(live.fenced), live.fence_reason or ""] if live.fenced or live.missed else []
        if live.missed:
            tail.append([[seq, why] for seq, why in live.missed])
        return tail

    def _boot(self) -> list[int]:
        return [self.boot] if self.boot else []

    def encode_plan(self) -> bytes:
        """Only what teammates need to assign tasks: id, plan, previous plan."""
        return cbor2.dumps(
            [self.robot_id, _plan_array(self.plan), _prev_item(self.plan, self.prev), *self._boot()], canonical=True
        )

    @classmethod
    def decode(cls, data: bytes) -> RobotState:
        """Decode :meth:`encode` or :meth:`encode_plan` output (the latter with an idle live part).

        Raises ``ValueError`` for anything docs/robot-state.cddl does not
        allow, types included: a teammate's state feeds the Task Assigner's
        arithmetic, so a text where a number belongs must stop here."""
        try:
            raw = cbor2.loads(data)
            _check(type(raw) is list and 3 <= len(raw) <= 7, "a robot state is an array of 3 to 7 items", raw)
            robot_id, plan = _text(raw[0], "robot-id") or "", _plan(raw[1])
            prev = _prev(plan, raw[2])
            if len(raw) in (3, 4):  # the plan form, with or without the incarnation
                boot = _uint(raw[3], "boot") if len(raw) == 4 else 0
                return cls(robot_id, plan, LiveState(float(plan.aisle), float(plan.rack)), None, prev, boot)
            live = raw[3]
            _check(type(live) is list and 6 <= len(live) <= 9, "live-state is an array of 6 to 9 items", live)
            fenced = tuple(_uint(seq, "fenced") for seq in _list(live[6], "fenced")) if len(live) > 6 else ()
            _check(type(live[2]) is int and 0 <= live[2] < len(ACTIVITIES), "unknown activity", live[2])
            live_state = LiveState(_float(live[0], "live aisle"), _float(live[1], "live rack"), ACTIVITIES[live[2]],
                                   _text(live[3], "executing", null=True), _uint(live[4], "queued"),
                                   _uint(live[5], "done"), fenced,
                                   (_text(live[7], "fence-reason") or None) if len(live) > 7 else None,
                                   _missed(live[8]) if len(live) > 8 else ())
            boot = _uint(raw[5], "boot") if len(raw) > 5 else 0
            joined = _decision(raw[6]) if len(raw) > 6 else None
            return cls(robot_id, plan, live_state, _decision(raw[4]) if raw[4] is not None else None, prev, boot,
                       joined)
        except (cbor2.CBORDecodeError, IndexError, KeyError, TypeError, ValueError, RecursionError) as exc:
            raise ValueError(f"not a robot state: {exc}"[:300]) from None


ACTIVITIES = ("idle", "travelling", "picking", "unloading", "charging")


def _single_precision(costs: dict[str, float | None]) -> dict[str, float | None]:
    """``costs`` rounded to the nearest float32: five bytes each in CBOR, not
    nine.  The feeder only records and prints them (to 0.01 Wh); the robots
    decide on their own float64 costs, never on these."""
    return {robot: _single(cost) for robot, cost in costs.items()}


def _single(cost: float | None) -> float | None:
    if cost is None or not abs(cost) < _FLOAT32_MAX:  # none, infinite, NaN or too large: as it is
        return cost
    rounded: float = _FLOAT32.unpack(_FLOAT32.pack(cost))[0]
    return rounded


_FLOAT32 = struct.Struct("<f")
_FLOAT32_MAX = 3.4e38


def _plan_array(plan: PlannedState | None) -> list[object] | None:
    if plan is None:
        return None
    # Floats stay float64: every robot must compute on exactly the numbers
    # the owner computes with, or "compute by all" could disagree.
    return [plan.aisle, plan.rack, float(plan.battery_wh), float(plan.load_kg), float(plan.payload_kg), plan.seq]


def _prev_item(plan: PlannedState, prev: PlannedState | None) -> object:
    """The previous plan, or only its ``seq`` where it is the plan but for
    that (the robot the task did not go to: two of three in a cluster,
    some 30 bytes less in each of their notifications)."""
    if prev is not None and replace(prev, seq=plan.seq) == plan:
        return prev.seq
    return _plan_array(prev)


def _prev(plan: PlannedState, raw: object) -> PlannedState | None:
    if raw is None:
        return None
    if type(raw) is int:
        return replace(plan, seq=_uint(raw, "prev seq"))
    return _plan(_list(raw, "prev"))


def _invalid(what: str, value: object) -> ValueError:
    return ValueError(f"{what}, got {value!r}")


def _check(ok: bool, what: str, value: object) -> None:
    if not ok:
        raise _invalid(what, value)


# Each reader returns its value as it is, narrowed by the test it passes.

def _uint(value: object, what: str) -> int:
    if type(value) is int and value >= 0:  # type() is int: no bool
        return value
    raise _invalid(f"{what} must be a uint", value)


def _float(value: object, what: str) -> float:
    if type(value) is float or type(value) is int:
        return value
    raise _invalid(f"{what} must be a number", value)


@overload
def _text(value: object, what: str) -> str: ...
@overload
def _text(value: object, what: str, *, null: bool) -> str | None: ...
def _text(value: object, what: str, *, null: bool = False) -> str | None:
    if type(value) is str or null and value is None:
        return value
    raise _invalid(f"{what} must be text{' or null' if null else ''}", value)


def _list(value: object, what: str) -> list[Any]:
    if type(value) is list:
        return value
    raise _invalid(f"{what} must be an array", value)


def _missed(raw: object) -> tuple[tuple[int, str], ...]:
    entries = _list(raw, "missed")
    for entry in entries:
        _check(type(entry) is list and len(entry) == 2, "a missed task is [seq, why]", entry)
    return tuple((_uint(seq, "missed seq"), _text(why, "missed why") or "") for seq, why in entries)


def _plan(raw: list[Any]) -> PlannedState:
    _check(type(raw) is list and len(raw) in (1, 6), "planned-state is an array of 6 items (1 in an outcome)", raw)
    if len(raw) == 1:  # an outcome's: the task alone
        return PlannedState(0, 0, 0.0, 0.0, 0.0, _uint(raw[0], "seq"))
    aisle, rack, battery, load, payload, seq = raw
    return PlannedState(_uint(aisle, "aisle"), _uint(rack, "rack"), _float(battery, "battery-wh"),
                        _float(load, "load-kg"), _float(payload, "payload-kg"), _uint(seq, "seq"))


def _decision_array(d: Decision) -> list[object]:
    return [d.seq, d.object, d.skipped, d.assigned_to, d.costs, d.error, d.coordination_s, d.reasons,
            d.epoch, list(d.members), d.unavailable, *([d.skip_reason] if d.skip_reason else [])]


def _decision(raw: list[Any]) -> Decision:
    # Eight items: a robot from before membership epochs (epoch 0, members
    # unnamed); ten: from before "unavailable"; eleven: no skip reason.
    _check(type(raw) is list and 8 <= len(raw) <= 12, "decision is an array of 8 to 12 items", raw)
    seq, obj, skipped, assigned_to, costs, error, coordination_s, reasons, *later = raw
    epoch, members, unavailable, skip_reason = (later + [0, [], None, None][len(later):])[:4]
    _check(type(skipped) is bool, "skipped must be a bool", skipped)
    _check(type(costs) is dict and all(type(k) is str and (v is None or type(v) in (float, int))
                                       for k, v in costs.items()), "costs must map text to number or null", costs)
    _check(type(reasons) is dict and all(type(k) is str and type(v) is str for k, v in reasons.items()),
           "reasons must map text to text", reasons)
    return Decision(
        _uint(seq, "seq"), _text(obj, "object"), skipped, _text(assigned_to, "assigned-to", null=True), costs,
        _text(error, "error", null=True), _float(coordination_s, "coordination-s"), reasons, _uint(epoch, "epoch"),
        tuple(_text(m, "members") for m in _list(members, "members")),
        _text(unavailable, "unavailable", null=True), _text(skip_reason, "skip-reason", null=True),
    )
