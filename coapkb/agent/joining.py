"""Where a restarted robot joins its cluster: the membership a teammate
decided the task before the join in (docs/failover.md, "A robot that
starts again")."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Collection, Mapping, Sequence
from functools import partial
from typing import NamedTuple

from ..cancelling import cancel_and_wait
from ..transport.base import ClientTransport, Endpoint, PeerGone, TransportError
from ..transport.messages import ContentFormat, Method, Request
from .observed_states import STATE_PATH, ObservedStates
from .robot_state import Decision, RobotState

log = logging.getLogger(__name__)

#: How soon a joining robot observes a silent teammate again.
JOIN_RETRY_S = 0.5


class Shown(NamedTuple):
    """The decision a teammate showed the joiner, which takes its membership."""

    teammate: str
    decision: Decision


async def shown_to_join(transport: ClientTransport, endpoints: Mapping[str, Endpoint], teammates: Sequence[str],
                        co_joiners: Sequence[str], seq: int, patience: float, joiner: str) -> tuple[Shown | None, bool]:
    """The decision whose membership a robot joining at ``seq`` takes: one
    of ``teammates`` shows it (:func:`decided_before`), or, if none that
    decided ``seq - 1`` is left, a co-joiner that joined on one
    (:func:`joined_on`); and whether a teammate is past the task without
    the joiner (it was left out)."""
    shown, past = await decided_before(transport, endpoints, teammates, seq, patience, joiner)
    if shown is None and not past and co_joiners:
        shown, past = await joined_on(transport, endpoints, co_joiners, seq, patience, joiner)
    return shown, past


def plans_shown(observed: ObservedStates, teammates: Collection[str], shown: Shown) -> None:
    """The plans the decision a join takes was computed on (those it costs,
    right after the task before it), and the plan of the teammate that
    showed it: a process of each had decided that far, so one first
    observed later with an earlier plan is a restart's, as for a decision
    carried out (:meth:`.TeamView.used_plans`).  Found in the simulator,
    seed 420 of the rejoin profile: a joiner cut off until after a
    teammate's restart took the new process for the member it joined
    with, and waited for its plan for good.  Only ``teammates`` not
    joining: co-joiners are new processes, known as such."""
    decision = shown.decision
    for robot_id in decision.costs:
        if robot_id in teammates:
            observed.saw_plan(robot_id, decision.seq - 1)
    if shown.teammate in teammates:
        observed.saw_plan(shown.teammate, decision.seq)


async def decided_before(transport: ClientTransport, endpoints: Mapping[str, Endpoint], teammates: Sequence[str],
                         seq: int, patience: float, joiner: str) -> tuple[Shown | None, bool]:
    """The decision of task ``seq - 1`` the first of ``teammates`` to show
    one shows (with its membership), all of them observed at once (some may
    be down); None if none can show it.  A decision of task ``seq`` itself
    that counts ``joiner`` a member does as well: the teammate admitted it
    there and decided the task without a plan of it (a repeat skipped on
    its claim needs none), and waits for its plan for the next (found in
    the simulator: a joiner that took such a teammate for one past its join
    started a membership of its own, alone).  And whether one of them may
    have decided it unseen: it was already past the task (False: no process
    that decided it is left, each being a new one that decided nothing, or
    none listening).

    A teammate that stays silent is waited for, however long: silence is
    no sign that its process is gone (one cut off, or frozen, decided the
    task and decides on in the membership the joiner must take; a joiner
    that started a fresh one without it after a wait split the cluster in
    two memberships: simulator seed 1114 of nine robots with power cuts).
    Every fault the team is built for ends, and a process that died
    answers "nobody here".  Each observation that gets no answer within
    ``patience`` seconds is started again, so a teammate back from a
    partition is reached at the first retransmission after it, not at the
    end of a backoff grown through the partition; and the wait is logged
    once after that long."""

    def shows(robot_id: str, state: RobotState) -> Shown | bool | None:
        """A decision to take; False if this process never decided (restarted,
        not yet joined), True if it is past the task without ``joiner``; None
        to observe on."""
        last = state.last
        if last is None:
            return False
        if last.seq < seq - 1:
            return None
        # Past seq - 1 only by a task that needs no plans (with the joiner a
        # member), or having left it out.
        return Shown(robot_id, last) if _takes(last, seq, joiner) else True

    # Tasks made here and read in the teammates' order (a set of done tasks
    # iterates in an order that follows id()).
    watches = [asyncio.create_task(_observed(transport, r, endpoints[r], patience, partial(shows, r)))
               for r in teammates]
    past = False
    waited = False
    try:
        pending = set(watches)
        while pending:
            done, pending = await asyncio.wait(pending, timeout=None if waited else patience,
                                               return_when=asyncio.FIRST_COMPLETED)
            if not done and not waited:
                silent = [r for r, w in zip(teammates, watches, strict=True) if w in pending]
                log.warning("no teammate showed its decision of task %d within %gs; waiting on for %s",
                            seq - 1, patience, ", ".join(silent))
                waited = True
            for watch in watches:
                if watch in done:
                    found = watch.result()
                    if isinstance(found, Shown):
                        return found, past
                    past = past or found
    finally:
        await cancel_and_wait(watches)
    return None, past


async def joined_on(transport: ClientTransport, endpoints: Mapping[str, Endpoint], co_joiners: Sequence[str],
                    seq: int, patience: float, joiner: str) -> tuple[Shown | None, bool]:
    """The decision a co-joiner (a robot joining at ``seq`` too) joined on
    (:attr:`.RobotState.joined`), or took since counting ``joiner`` in, for
    a joiner that found no teammate left that decided ``seq - 1``: a
    co-joiner that reached one before it died took its membership, and this
    robot must take the same (found in the simulator, seed 103234 of three
    robots with power cuts: a joiner starved of CPU read the survivor's
    state only once the survivor was killed and started a fresh membership
    while its co-joiner had joined the survivor's; the two decided on in two
    epochs).  None if no co-joiner shows one within ``patience`` seconds: a
    co-joiner that joined on none, or is still joining (it may find none
    either), shows nothing to take.  And, as :func:`decided_before` says,
    whether one went past the task without ``joiner``: it was left out.
    Left is a narrower race: a co-joiner that reads the survivor's state
    after this robot gave up on the survivor and on it."""

    def shows(robot_id: str, state: RobotState) -> Shown | bool | None:
        # Its own decisions count from the join's task on: one of seq - 1 is
        # a left-out robot's, fed again with the same process, alone.
        last = state.last if state.last is not None and state.last.seq >= seq else None
        decision = last or (state.joined if state.joined is not None and state.joined.seq >= seq - 1 else None)
        if decision is not None:
            return Shown(robot_id, decision) if _takes(decision, seq, joiner) else True
        # Joined on nothing: its plan right after seq - 1, none before it (TeamView.join).
        return False if state.plan.seq == seq - 1 and state.prev is None else None

    watches = [asyncio.create_task(_observed(transport, r, endpoints[r], patience, partial(shows, r)))
               for r in co_joiners]
    past = False
    try:
        async with asyncio.timeout(patience):
            for watch in asyncio.as_completed(watches):
                found = await watch
                if isinstance(found, Shown):
                    return found, past
                past = past or found
    except TimeoutError:
        log.info("no co-joiner showed a decision of task %d to join on within %gs", seq - 1, patience)
    finally:
        await cancel_and_wait(watches)
    return None, past


def _takes(decision: Decision, seq: int, joiner: str) -> bool:
    """Whether a joiner at ``seq`` takes the membership of ``decision``
    (one of ``seq - 1``, or of ``seq`` counting the joiner in: see
    :func:`decided_before`)."""
    return decision.seq == seq - 1 or (decision.seq == seq and joiner in decision.members)


async def _observed(transport: ClientTransport, robot_id: str, endpoint: Endpoint, patience: float,
                    shows: Callable[[RobotState], Shown | bool | None]) -> Shown | bool:
    """Observe teammate ``robot_id``'s state until ``shows`` makes something of it;
    False if no process is there.  An observation that gets no answer
    within ``patience`` seconds is started again."""
    request = Request(Method.GET, STATE_PATH, accept=ContentFormat.CBOR)
    while True:
        try:
            async with asyncio.timeout(patience) as first_answer:
                async for response in transport.observe(endpoint, request):
                    first_answer.reschedule(None)  # observing: its state changes when it decides
                    if response.status.is_success:
                        found = shows(RobotState.decode(response.payload))
                        if found is not None:
                            return found
        except PeerGone as exc:
            log.debug("catching up from %s: %s", robot_id, exc)
            return False
        except (TransportError, ValueError, TimeoutError) as exc:
            log.debug("catching up from %s: %s", robot_id, exc or "no answer")
        await asyncio.sleep(JOIN_RETRY_S)  # silent, or the observation ended: again
