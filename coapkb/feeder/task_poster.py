"""One task fed to its cluster: posted to the robots joining at it first,
then to the others up, and every robot's decision on it awaited and kept
in the task's record (only the survivors' decisions count)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping, Sequence

import cbor2

from .. import clock
from ..agent.observed_states import States
from ..agent.robot_state import Decision
from ..transport.messages import Request, Response
from .channel import Channel
from .membership import Membership, PendingTask
from .record import TaskRecord
from .tasks import FeederError, task_post

log = logging.getLogger(__name__)


class TaskPoster:
    """Posts each task to its cluster and records what the robots decided."""

    def __init__(self, channel: Channel, membership: Membership) -> None:
        self.channel = channel
        self.membership = membership

    async def feed_task(
        self, index: int, cluster: list[str], seq: int, name: str, joining: Sequence[str] = (),
        again: int | None = None, restocked: bool = False, records: Sequence[TaskRecord] = (),
    ) -> TaskRecord:
        """Post task ``seq`` (object ``name``) to cluster ``index`` and wait
        for the decisions of its robots up; robots taken back meanwhile are
        given it too (``records``: the cluster's tasks so far)."""
        channel, watcher = self.channel, self.channel.watcher
        fed = clock.monotonic()
        request = task_post(seq, name, joining, again, restocked)
        live = [r for r in cluster if r not in watcher.down]
        if not live:
            why = "; ".join(f"{r}: {watcher.down[r]}" for r in cluster)
            others = len(watcher.down) - len(cluster)
            raise FeederError(f"every robot of cluster {index + 1} is down ({why})"
                              + (f"; {others} robots of other clusters too" if others else ""))
        boots = await self._post_to_joiners(request, seq, name, joining)
        joined = list(boots)
        missed = [r for r in joining if r not in boots] if joined else []
        if joining:
            request = task_post(seq, name, joined, again, restocked, boots, missed)
        # Robots joining together had the post before their processes were
        # known: it goes to them again, naming each other's, and those that
        # did not take it.  A joiner that took a post naming a co-joiner who
        # then missed it waited for that one's plan for good (found in the
        # simulator, seed 337 of nine robots with power cuts).
        again_to = joined if len(joined) > 1 or missed else []
        targets = [*(r for r in live if r not in joining), *again_to]
        answers = dict(zip(targets, await asyncio.gather(*(channel.post_task(r, request, seq, name) for r in targets)),
                           strict=True))
        took = {r for r, answer in answers.items() if answer is not None} | set(joined)

        def naming(restarted: Sequence[str]) -> Request:
            return task_post(seq, name, joined, again, restocked, boots, missed, restarted)

        def decided(states: States, robot_id: str) -> bool:
            return robot_id in states and states[robot_id].decided(seq)

        def undecided(states: States) -> list[str]:
            return [r for r in cluster if r not in watcher.down and not decided(states, r)]

        deciding = asyncio.ensure_future(channel.wait_for(
            lambda s: not undecided(s),
            channel.settings.task_timeout_s,
            f"decisions on task {seq} ({name}) from {', '.join(r for r in cluster if r not in watcher.down)}",
            pending=undecided, of=len(live),
        ))
        told = asyncio.ensure_future(self._tell_restarts([r for r in cluster if r not in joining], took, seq, name,
                                                         naming))
        try:
            if records:
                await self.membership.take_back_while(cluster, records, PendingTask(seq, name, request), deciding)
            states = await deciding
        finally:
            deciding.cancel()
            told.cancel()
        record = TaskRecord(object=name, cluster=index + 1, seq=seq, coordination_s=clock.monotonic() - fed,
                            joined=joined)
        decisions = {r: d for r in cluster if decided(states, r) and (d := states[r].last) is not None}
        if len({(d.assigned_to, d.unavailable, d.error, d.epoch) for d in decisions.values()}) > 1:
            # Robots that differ, if only in the membership epoch, may have
            # decided and then died before the feeder noticed: ask each once,
            # so the dead ones' decisions are void (simulator, seed 5822 of the
            # compute-and-communicate swarm profile: a follower that held the
            # restarted leader's last plan decided in its epoch and died; the
            # other, without that plan, decided alike in the next).
            await asyncio.gather(*(watcher.probe(r) for r in decisions if r not in watcher.down))
        for robot_id, why in self._record(record, cluster, decisions, records).items():
            await self.membership.left_out(robot_id, why)
        return record

    async def _tell_restarts(self, members: Sequence[str], took: set[str], seq: int, name: str,
                             naming: Callable[[Sequence[str]], Request]) -> None:
        """Until task ``seq`` is decided: each member that runs again as a
        new process is named to those that took the post (the post again,
        naming it restarted).  The new process did not take the task (it
        joins at a later one), and the process the others count on is gone,
        though they may not have found it down.  Found in the simulator: a
        joiner that had never seen the old process took the new one for the
        member and waited for its plan for good (nine robots with power
        cuts, seed 5563); followers whose leader restarted after it took the
        post waited for its decision until they gave the task up
        (compute-and-communicate swarm profile, seed 3005)."""
        named: set[str] = set()
        while True:
            named.update(await self.membership.until_restarting([r for r in members if r not in named]))
            repeat = naming(sorted(named))
            await asyncio.gather(*(self.channel.post_task(r, repeat, seq, name) for r in sorted(took - named)))

    async def _post_to_joiners(self, request: Request, seq: int, name: str,
                               joining: Sequence[str]) -> dict[str, int]:
        """Post task ``seq`` to the robots joining at it, before their
        teammates; the joiners it reached, each with the process that took
        it (its boot, 0 if it did not say), which the teammates are told to
        expect.  One it did not reach (found down:
        the process that was to join died, and another may have started since)
        is not named to its teammates: they would admit it at this task and
        wait for a plan after the previous one, which no process of it
        publishes, until their wait ran out and they decided nothing (found in
        the simulator: a robot killed again soon after its restart, and
        restarted once more just after the feeder posted its join).  It
        joins at a later task, once the feeder is told of its restart."""
        channel, watcher = self.channel, self.channel.watcher
        answers = await asyncio.gather(*(channel.post_task(r, request, seq, name) for r in joining))
        for robot_id, answer in zip(joining, answers, strict=True):
            if answer is not None and robot_id in watcher.down and not self.membership.restarting(robot_id):
                # It took the join: the requests that failed meanwhile had
                # reached its port before the new process listened.  Counted
                # down, it was taken back later as a member and fed from its
                # old process's task, which it refused, and the run stopped
                # (found in the simulator, seed 6294 of nine robots).
                watcher.readmit(robot_id, _boot_in(answer))
        missed = [r for r in joining if r in watcher.down]
        if missed:
            log.warning("%s did not take task %d, at which %s to join: %s not named to the teammates",
                        ", ".join(missed), seq, "it was" if len(missed) == 1 else "they were",
                        "it is" if len(missed) == 1 else "they are")
        return {r: _boot_in(answer) for r, answer in zip(joining, answers, strict=True) if r not in watcher.down}

    def _record(self, record: TaskRecord, cluster: list[str], decisions: Mapping[str, Decision],
                records: Sequence[TaskRecord]) -> dict[str, str]:
        """Keep in ``record`` the decisions that count, and why the others do
        not.  The decision is the survivors': a robot that decided and then
        went down executes nothing (its task, if any, goes round again),
        unless it was seen to have done the job first; and one left out of a
        newer membership by the others took no part in it.  ``records``:
        the cluster's tasks before this one.  Returns the robots the newest
        membership left out, and why."""
        down = self.channel.watcher.down

        def standing(decision: Decision) -> tuple[bool, int]:
            # A majority's membership first: a robot its teammates left out
            # while it was cut off, back and joining alone, starts one of its
            # own whose epoch is the task's number, ahead of theirs, and
            # its decisions are fenced anyway.  Taken for the newest, it
            # voided the majority's, and each task it dropped was sent round
            # again after they had picked it (simulator, the rejoin fault).
            members = decision.members or tuple(cluster)
            return len(members) * 2 > len(cluster), decision.epoch

        newest = max(decisions.values(), key=standing, default=None)
        # A robot that took the task, did the job, and went down only then
        # (its last observed state counts the job): its decision is what
        # happened.  Voided, it left the record giving a picked object to
        # nobody (simulator, power cuts: the survivor, its holders gone,
        # settled the task unavailable).
        did_it = {r for r in decisions if r in down and decisions[r].assigned_to == r
                  and self.membership.executed_next(r, records)}
        survivors = [r for r in decisions if r not in down or r in did_it]
        for robot_id in cluster:
            decision = decisions.get(robot_id)
            if decision is None:
                record.absent[robot_id] = down.get(robot_id, "no decision")
                continue
            if robot_id in down and robot_id not in did_it and survivors:
                record.absent[robot_id] = f"{down[robot_id]} (its decision is void)"
                continue
            if newest is not None and decision is not newest and standing(decision) < standing(newest) \
                    and robot_id not in (newest.members or cluster):
                record.absent[robot_id] = f"left out of membership epoch {newest.epoch} (its decision is void)"
                continue
            record.decisions[robot_id] = decision.assigned_to
            record.epochs[robot_id] = decision.epoch
            if not record.members:
                # A robot's outcome names the members only once they changed:
                # at epoch 0 they are the cluster the feeder fed.
                record.members = list(decision.members or (sorted(cluster) if decision.epoch == 0 else ()))
            if decision.error:
                record.errors[robot_id] = decision.error
            if decision.unavailable and record.unavailable is None:
                record.unavailable = decision.unavailable
            if decision.skipped:
                record.skipped = True
                record.skip_reason = record.skip_reason or decision.skip_reason
            if decision.costs and not record.costs:
                # Sent in single precision: its seven digits, not float32's binary tail.
                record.costs = {r: None if c is None else float(f"{c:.7g}") for r, c in decision.costs.items()}
                record.reasons = dict(decision.reasons)
        assigned = {d for d in record.decisions.values() if d is not None}
        record.assigned_to = assigned.pop() if len(assigned) == 1 else None
        # Out: the robots every member of the newest membership is seen to
        # decide without, whether they decided apart (void) or nothing (down:
        # frozen through it, simulator seed 27897).  One member that still
        # counted a robot (or was not heard from) would admit it in another
        # epoch than the others when it joins again (seed 4246 of nine
        # robots with partitions: a false suspicion by one member, the
        # other cut off).
        if newest is None or not newest.members or not all(m in record.decisions for m in newest.members):
            return {}
        counted = [decisions[r] for r in record.decisions]
        return {r: f"left out of membership epoch {newest.epoch} at task {record.seq}" for r in cluster
                if r not in record.decisions and all(d.members and r not in d.members for d in counted)}


def _boot_in(answer: Response | None) -> int:
    """The process a joiner's answer to its post names (0: not said)."""
    if answer is None or not answer.payload:
        return 0
    try:
        boot = cbor2.loads(answer.payload).get("boot", 0)
    except (cbor2.CBORDecodeError, AttributeError, ValueError):
        return 0
    return boot if type(boot) is int and boot > 0 else 0
