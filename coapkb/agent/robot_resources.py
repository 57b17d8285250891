"""A robot's own resources (besides the KB's): its state for teammates and
the feeder, the task feed, decisions, claims, lease grants and statistics.

=================  ======  ==================================================
``/robot/state``   GET     live and planned state, last decision; observable (RFC 7641)
``/robot/plan``    GET     planned state only, for teammates; observable
``/robot/plan``    POST    ``?of=X&at=S``: compare notes on teammate X's plan after task S
``/robot/outcome`` GET     what the feeder acts on: decisions, jobs done or dropped, idle; observable
``/tasks``         POST    a new task ``{"seq": n, "object": name}`` (CBOR/JSON; :mod:`coapkb.feeder.tasks`)
``/tasks``         GET     the decisions taken so far
``/decisions``     GET     ``?seq=N``: this robot's decision on task N, whole
``/decisions``     POST    the leader's decision ("compute and communicate")
``/robot/claims``  GET     the objects the cluster assigned lately
``/robot/stats``   GET     traffic counters and query statistics
``/robot/lease``   GET     ``?r=X[&check]``: does this robot grant teammate X a lease (the fence)
=================  ======  ==================================================
"""

from __future__ import annotations

import json
import re
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, replace
from typing import Any

import cbor2

from .. import clock
from ..config import RobotConfig
from ..transport.base import ResourceInfo
from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..transport.router import Router
from .controller import Controller
from .decisions import CLAIMS_PATH, DecisionMessage, Task, encode_claims
from .lease import LEASE_PATH
from .observed_states import OUTCOME_PATH, PLAN_PATH, STATE_PATH
from .robot_state import LiveState, RobotState
from .stats import RobotStats
from .team_view import TeamView

OBJECT_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,127}$")
#: How long one snapshot of a robot's statistics is served (``/robot/stats``).
STATS_SNAPSHOT_S = 5.0


class FinalOutcome:
    """Which state is final: the robot went idle with nothing queued, and
    has decided nothing since.  Its notification, on ``/robot/outcome`` and
    on ``/robot/state``, goes confirmed (``Response.confirm``): the feeder
    waits for it at the end of a run, and
    no later change would make up for its loss; the others go unconfirmed,
    each awaited by a feeder that asks again when one is late."""

    def __init__(self) -> None:
        #: (jobs done, last task decided) when the robot last went idle.
        self._at: tuple[int, int] | None = None

    @staticmethod
    def _key(state: RobotState) -> tuple[int, int]:
        return state.live.done, state.last.seq if state.last is not None else 0

    def on_live(self, before: LiveState, state: RobotState) -> None:
        live = state.live
        if before.activity != "idle" and live.activity == "idle" and not live.queued:
            self._at = self._key(state)

    def __call__(self, state: RobotState) -> bool:
        return self._at is not None and self._at == self._key(state) and state.live.activity == "idle"


#: Plans shown to a teammate's question that a later try gets again: a few
#: tasks' worth for each teammate (a try is held back seconds, not tasks).
PLANS_SHOWN_KEPT = 64


class RobotResources:
    """The handlers of one robot's resources (see the module docstring)."""

    def __init__(self, config: RobotConfig, team: TeamView, controller: Controller, final_outcome: FinalOutcome,
                 stats: Callable[[], RobotStats]) -> None:
        self.config = config
        self.team = team
        self.controller = controller
        self.final_outcome = final_outcome
        self._stats = stats
        self._next_seq = 1
        #: (teammate, task) -> the plan this robot showed when asked for it
        #: after that task (:meth:`_compare_notes`), the latest
        #: :data:`PLANS_SHOWN_KEPT`: every later try gets the same answer.
        self._plans_shown: OrderedDict[tuple[str, int], bytes] = OrderedDict()
        #: Object of the last ``bounds.posts_remembered`` tasks taken, by sequence number
        #: (a repeated post is recognised: the feeder repeats only its latest).
        self.accepted: dict[int, str] = {}
        #: Content format -> (when taken, the stats answer): see _get_stats.
        self._stats_snapshots: dict[int | None, tuple[float, Response]] = {}

    def mount(self, router: Router) -> None:
        add = router.add
        add(ResourceInfo(STATE_PATH, rt="coapkb.state", ct=(60, 50), obs=True, title="robot state"), self._get_state)
        add(ResourceInfo(PLAN_PATH, rt="coapkb.plan", ct=(60,), obs=True, title="planned state",
                         methods=("GET", "POST")), self._plan)
        add(ResourceInfo(OUTCOME_PATH, rt="coapkb.outcome", ct=(60,), obs=True, title="decisions and jobs"),
            self._get_outcome)
        add(
            ResourceInfo("/tasks", rt="coapkb.tasks", ct=(60, 50), title="task feed", methods=("GET", "POST")),
            self._tasks,
        )
        add(ResourceInfo("/decisions", rt="coapkb.decisions", methods=("GET", "POST")), self._decisions)
        add(ResourceInfo("/robot/stats", rt="coapkb.stats", ct=(60, 50), title="traffic and query stats"),
            self._get_stats)
        add(ResourceInfo(CLAIMS_PATH, rt="coapkb.claims", ct=(60,), title="objects the cluster assigned"),
            self._get_claims)
        add(ResourceInfo(LEASE_PATH, rt="coapkb.lease", title="lease grants (the fence)"), self._get_lease)

    # ---------------------------------------------------------------- handlers

    async def _get_state(self, request: Request) -> Response:
        own = self.team.own
        if request.accept == ContentFormat.JSON:
            return self._confirmed_if_final(_encode(own.to_dict(), request.accept), own)
        return self._confirmed_if_final(_cbor_state(own.encode(), request.accept), own)

    async def _get_outcome(self, request: Request) -> Response:
        own = self.team.own
        return self._confirmed_if_final(_cbor_state(own.encode_outcome(), request.accept), own)

    def _confirmed_if_final(self, response: Response, own: RobotState) -> Response:
        """A final state goes confirmed on either resource: a feeder that
        records the whole state observes ``/robot/state`` instead of
        ``/robot/outcome``, and waits for it alike (a lost NON final state
        cost it 4-5 s at 20 % loss, until its refresh)."""
        return replace(response, confirm=self.final_outcome(own)) if response.status.is_success else response

    async def _plan(self, request: Request) -> Response:
        if request.method == Method.POST:
            return await self._compare_notes(request)
        return await self._get_plan(request)

    async def _compare_notes(self, request: Request) -> Response:
        """``POST ?of=X&at=S[&by=A]``: teammate A goes on without X's plan
        after task S unless this robot has it (TeamView._plan_from_survivors).
        Answered with that plan (2.04), or 4.04, and then this robot goes on
        without it too: a change of state, so not a GET, which must be safe
        (RFC 7252 §5.8.1).  Only the cluster's robots may ask, and only a
        member's question binds: a robot this one has left out decides in a
        membership of its own, and following it split the majority's (found
        in the simulator, seed 90301 of three robots: a robot cut off for
        17 s asked about a slow member, and the one asked left that member
        out alone).  The asker is the secured peer, else ``by``."""
        about = request.query.get("of")
        seq = _task_number(request)
        if about is None or seq is None:
            return Response.error(Status.BAD_REQUEST, "give the robot and the task: /robot/plan?of=ROBOT&at=SEQ")
        if isinstance(seq, Response):
            return seq
        asker = request.peer or request.query.get("by")
        if asker is not None and not self.team.in_cluster(asker):
            return Response.error(Status.FORBIDDEN, f"{asker} is not of {self.config.robot_id}'s cluster")
        state = self.team.state_of(about)
        # Each try of a question is a new exchange, and every try gets the
        # first one's answer.  Once it has promised to go on without that
        # plan, it says so to every later try, though the plan came since: a
        # try answered with the plan after an earlier one was answered
        # without it had the asker count the teammate in and this robot leave
        # it out (found in the simulator, seed 1308 of three robots with
        # messages held back).  Once it has shown the plan, it shows it
        # again, though it holds only later ones since: a try held back past
        # the next tasks was answered without it, and this robot left out the
        # teammate that the asker, answered with the plan, counted in (seed
        # 4608, likewise).
        shown = self._shown_before(about, seq)
        if shown is not None and not self.team.membership.forgoes(about, seq):
            return Response(Status.CHANGED, shown, ContentFormat.CBOR)
        if state is None or state.plan_at(seq) is None or self.team.membership.forgoes(about, seq):
            if self.team.membership.heeds(asker):
                await self.team.membership.forgo(about, seq)
            return Response.error(Status.NOT_FOUND, f"no plan of {about} after task {seq}")
        shown = self._plans_shown[(about, seq)] = state.encode_plan()
        while len(self._plans_shown) > PLANS_SHOWN_KEPT:
            self._plans_shown.popitem(last=False)
        return Response(Status.CHANGED, shown, ContentFormat.CBOR)

    def _shown_before(self, about: str, seq: int) -> bytes | None:
        """The plan of ``about`` after task ``seq`` that a question was shown, if one was."""
        return self._plans_shown.get((about, seq))

    async def _get_plan(self, request: Request) -> Response:
        probed = request.query.get("probe")
        if probed is not None:
            # A teammate finds ``probed`` silent: does this robot reach it?
            if await self.team.reaches(probed):
                return _cbor_state(self.team.own.encode_plan(), request.accept)
            return Response.error(Status.GATEWAY_TIMEOUT, f"{probed} does not answer {self.config.robot_id} either")
        about = request.query.get("of")
        if about is None or about == self.config.robot_id:
            return _cbor_state(self.team.own.encode_plan(), request.accept)
        # A teammate's plan as this robot observed it: survivors compare notes
        # on a robot that died (TeamView._plan_from_survivors).
        state = self.team.state_of(about)
        seq = _task_number(request)
        if isinstance(seq, Response):
            return seq
        if seq is not None:
            if state is None or state.plan_at(seq) is None:
                return Response.error(Status.NOT_FOUND, f"no plan of {about} after task {seq}")
        if state is None:
            return Response.error(Status.NOT_FOUND, f"no state of {about}")
        return _cbor_state(state.encode_plan(), request.accept)

    async def _get_lease(self, request: Request) -> Response:
        """``?r=X``: does this robot grant teammate X a lease (2.05) or not
        (4.03, why)?  ``&t=TASK``: for a job of that task, granted only once
        this robot has decided it (5.03 until then) with X a member.
        ``&check``: probe X first, so a robot that stopped answering is
        found down now (the feeder asks before re-assigning X's tasks).
        ``&counts``: no lease, only whether this robot counts X as up and a
        member (2.05, else 4.03, why), which X asks before it counts on this
        robot again (:class:`~.teammate_revival.TeammateRevival`).  The
        requester must be X or the feeder, when known."""
        about = request.query.get("r", "")
        if request.peer is not None and request.peer not in (about, "feeder"):
            return Response.error(Status.FORBIDDEN, f"{request.peer} may not ask about {about}'s lease")
        if "counts" in request.query:
            why = self.team.membership.counts(about)
            return Response(Status.CONTENT) if why is None else Response.error(Status.FORBIDDEN, why)
        task = request.query.get("t")
        if task is not None and not (task.isdigit() and 0 < int(task) < 2**32):
            return Response.error(Status.BAD_REQUEST, f"t={task[:20]!r}: a task number was expected")
        if "check" in request.query:
            await self.team.probe(about)
        else:
            self.team.revival.asked_by(about)  # alive: if down here, perhaps this robot was the one cut off
        why = self.team.membership.grant(about)
        if why is not None:
            return Response.error(Status.FORBIDDEN, why)
        return self._granted_for(about, int(task)) if task is not None else Response(Status.CONTENT)

    def _granted_for(self, robot_id: str, seq: int) -> Response:
        """A lease for teammate ``robot_id``'s job of task ``seq``: only once
        this robot has decided the task, and with ``robot_id`` a member.  A
        robot its teammates left out at that task, still granted from before
        and not knowing, decided it as a member and picked it, which they
        gave another (the fence covered old tasks, not new ones).  A process
        that has decided nothing yet (the run's start, or restarted and not
        yet joined: it may decide nothing before the cluster's jobs are
        done) grants by the membership alone, as before: waiting for it
        held a robot's job, and the feeder's next task, for good (simulator
        seeds 5 and 467 of nine robots with power cuts).  One that has taken
        a task's post decides it: it says "not yet" like any other (seed 116
        of nine robots with partitions: at the run's start, a robot that had
        not decided task 1 yet granted a teammate cut off from it, then left
        that teammate out of task 1, which the teammate picked)."""
        last = self.team.own.last
        if (last.seq if last is not None else 0) < seq and (last is not None or self.accepted):
            return Response.error(Status.SERVICE_UNAVAILABLE, f"{self.config.robot_id} has not decided task {seq} yet",
                                  max_age=1)
        decided = next((d for d in reversed(self.controller.log) if d.seq == seq), None)
        if decided is not None and decided.members and robot_id not in decided.members:
            return Response.error(Status.FORBIDDEN,
                                  f"{self.config.robot_id} decided task {seq} without {robot_id} (epoch {decided.epoch})")
        return Response(Status.CONTENT)

    async def _tasks(self, request: Request) -> Response:
        if request.method == Method.GET:
            return _encode([asdict(d) for d in self.controller.log], request.accept)
        try:
            body = _decode_body(request)
            seq, name = body["seq"], body["object"]
            join = _joiners(body.get("join", []))
            missed = body.get("missed", [])
            restarted = body.get("restarted", [])
            again = body.get("again")
            restocked = body.get("restocked", False)
        except (ValueError, KeyError, TypeError, AttributeError, cbor2.CBORDecodeError):
            return Response.error(
                Status.BAD_REQUEST,
                'expected {"seq": int, "object": name[, "join": [robot or [robot, boot], ...]][, "missed": [robot, ...]]'
                '[, "restarted": [robot, ...]][, "again": int]'
                '[, "restocked": true]} '
                'in CBOR or JSON',
            )
        if not isinstance(seq, int) or not isinstance(name, str) or not OBJECT_NAME.match(name):
            return Response.error(Status.BAD_REQUEST, "seq must be an integer and object a local name")
        if again is not None and (type(again) is not int or not 0 < again < seq):
            return Response.error(Status.BAD_REQUEST, "again must name an earlier task")
        if type(restocked) is not bool:
            return Response.error(Status.BAD_REQUEST, "restocked must be true or false")
        if not all(r in self.config.team for r in join):
            return Response.error(Status.BAD_REQUEST, "join must list robots of the team")
        if not isinstance(missed, list) or not all(isinstance(r, str) and r in self.config.team for r in missed):
            return Response.error(Status.BAD_REQUEST, "missed must list robots of the team")
        if not isinstance(restarted, list) or not all(isinstance(r, str) and r in self.config.team for r in restarted):
            return Response.error(Status.BAD_REQUEST, "restarted must list robots of the team")
        # A joiner says which process took the post: its teammates expect that one.
        taken = (Response(Status.CHANGED, cbor2.dumps({"boot": self.team.own.boot}), ContentFormat.CBOR)
                 if self.config.robot_id in join else Response(Status.CHANGED))
        if seq < self._next_seq and self.accepted.get(seq) == name:
            # A repeat of a post already taken (its answer was lost and the
            # feeder asked again as a new exchange): same answer, no new task.
            # Repeated to robots joining together, it names each one's process.
            for robot_id, boot in join.items():
                if robot_id != self.config.robot_id:
                    await self.team.membership.named(robot_id, seq, boot)
            for robot_id in missed:
                if robot_id != self.config.robot_id:
                    await self.team.membership.missed(robot_id, seq, decided=self.team.own.decided(seq))
            for robot_id in restarted:
                if robot_id != self.config.robot_id:
                    await self.team.membership.restarted(robot_id, seq)
            return taken
        if self.config.robot_id in join and seq >= self._next_seq:
            # Restarted, or left out by its teammates and joining them again:
            # this robot joins the team at this task (the feeder fed it none
            # of those between), and a process that took earlier tasks
            # leaves those it has not done to go round again.
            if self.accepted:
                self.controller.rejoin_at(seq)
            self._next_seq = seq
        if seq != self._next_seq:
            return Response.error(Status.CONFLICT, f"expected task {self._next_seq}, got {seq}")
        self._next_seq += 1
        self.accepted[seq] = name
        self.accepted.pop(seq - self.controller.bounds.posts_remembered, None)
        self.controller.submit(Task(seq, name, tuple(join), join, again, restocked))
        return taken

    async def _get_claims(self, request: Request) -> Response:
        """``/robot/claims``: the objects the cluster assigned lately, for a restarted teammate."""
        return Response(Status.CONTENT, encode_claims(self.controller.claims.handed()), ContentFormat.CBOR)

    async def _decisions(self, request: Request) -> Response:
        if request.method == Method.GET:
            return self._get_decision(request)
        return await self._post_decision(request)

    def _get_decision(self, request: Request) -> Response:
        """``?seq=N``: this robot's decision on task N, whole (a teammate whose
        knowledge did not arrive takes it instead of deciding alone)."""
        try:
            seq = int(request.query.get("seq", ""))
        except ValueError:
            return Response.error(Status.BAD_REQUEST, "give the task: /decisions?seq=N")
        message = self.controller.recent.get(seq)
        if message is None:
            return Response.error(Status.NOT_FOUND, f"no decision on task {seq} here (yet)")
        return _cbor_state(cbor2.dumps(message.to_dict()), request.accept)

    async def _post_decision(self, request: Request) -> Response:
        try:
            message = DecisionMessage.from_dict(cbor2.loads(request.payload))
        except (ValueError, KeyError, TypeError, cbor2.CBORDecodeError) as exc:
            return Response.error(Status.BAD_REQUEST, f"not a decision: {exc}")
        self.controller.receive_decision(message)
        return Response(Status.CHANGED)

    async def _get_stats(self, request: Request) -> Response:
        # Serving the stats counts traffic, so every fresh snapshot differs: a
        # retried first block of a block-wise transfer on a lossy link would
        # start a new answer each time.  One snapshot serves for a few seconds.
        now = clock.monotonic()
        snapshot = self._stats_snapshots.get(request.accept)
        if snapshot is None or now - snapshot[0] > STATS_SNAPSHOT_S:
            snapshot = (now, _encode(self._stats().to_dict(), request.accept))
            self._stats_snapshots[request.accept] = snapshot
        return snapshot[1]


def _task_number(request: Request) -> int | Response | None:
    """``?at=S``: the task number, None if not given, or the 4.00 to answer."""
    at = request.query.get("at")
    if at is None:
        return None
    try:
        return int(at)
    except ValueError:
        return Response.error(Status.BAD_REQUEST, "at must be a task number")


def _joiners(join: Any) -> dict[str, int]:
    """A post's ``join`` list: robot -> the boot of the process that took the
    post (0 where not named: any process of it).  Raises TypeError if malformed."""
    if not isinstance(join, list):
        raise TypeError("join must be a list")
    joiners = {}
    for entry in join:
        if isinstance(entry, str):
            joiners[entry] = 0
        elif (isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], str)
              and type(entry[1]) is int and entry[1] >= 0):
            joiners[entry[0]] = entry[1]
        else:
            raise TypeError("a joiner is a robot or [robot, boot]")
    return joiners


def _decode_body(request: Request) -> Any:
    """A CBOR (default) or JSON request body."""
    if request.content_format == ContentFormat.JSON:
        return json.loads(request.payload)
    return cbor2.loads(request.payload)


def _encode(value: Any, accept: int | None) -> Response:
    if accept == ContentFormat.JSON:
        return Response(Status.CONTENT, json.dumps(value).encode(), ContentFormat.JSON)
    if accept not in (None, ContentFormat.CBOR):
        return Response.error(Status.NOT_ACCEPTABLE, "use content-format 60 (cbor) or 50 (json)")
    return Response(Status.CONTENT, cbor2.dumps(value), ContentFormat.CBOR)


def _cbor_state(payload: bytes, accept: int | None) -> Response:
    if accept not in (None, ContentFormat.CBOR):
        return Response.error(Status.NOT_ACCEPTABLE, "use content-format 60 (cbor) or 50 (json)")
    return Response(Status.CONTENT, payload, ContentFormat.CBOR)
