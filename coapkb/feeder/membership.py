"""Who the feeder counts on, robot by robot: restarted robots joining at a
task boundary, robots back before their teammates noticed (taken back),
and down robots fenced off before their tasks go round again."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Any

from .. import clock
from ..agent.robot_state import RobotState
from ..transport.messages import Request
from .channel import Channel
from .fence import fence, settle
from .orphans import executed_next, idle, orphans, unexecuted
from .record import TaskRecord
from .tasks import task_post

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PendingTask:
    """A task as posted: what a robot taken back is given again."""

    seq: int
    object: str
    post: Request


class Membership:
    """The feeder's view of which process of each robot it feeds, shared by
    the clusters' feeding loops."""

    def __init__(self, channel: Channel) -> None:
        self.channel = channel
        #: Restarted robots, up again and waiting to join at the next task.
        self._restarted: set[str] = set()
        #: Robot -> the first task of its current process (0: every task of this feeder).
        self._incarnation: dict[str, int] = {}
        #: Down robots whose tasks may go round again: the survivors no
        #: longer grant them a lease, and it has run out (:meth:`fence`).
        self._fenced_off: set[str] = set()
        #: Robot -> jobs its process had done before this feeder's first task
        #: (an earlier feeder's): not among this feeder's records.
        self._done_before: dict[str, int] = {}
        #: Set at each restart: what a cluster with every robot down awaits.
        self._rejoined = asyncio.Event()
        #: Notified at each restart: what a task being decided watches.
        self._restarts = asyncio.Condition()
        #: Robots a newer membership of their cluster left out, and why: down
        #: for the feeder until they join again with the same process.
        self._left_out: dict[str, str] = {}

    def set_done_before(self, robot_id: str, done: int) -> None:
        """``robot_id`` had done ``done`` jobs, all of them an earlier feeder's."""
        self._done_before[robot_id] = done

    async def rejoin(self, robot_id: str) -> None:
        """``robot_id`` runs again as a new process (same endpoint): it joins
        the team at the next task fed to its cluster.  Its old process is
        gone, so no wait counts on it any more, even if no request has failed
        yet: a feeder that never heard from the old process could not tell
        the new one from it, and waited for its decision on the task being
        decided for good (found in the simulator)."""
        self._restarted.add(robot_id)
        self._left_out.pop(robot_id, None)  # a new process joins as one
        self.channel.forget_posts(robot_id)
        await self.channel.watcher.declare_down(robot_id, "restarted")
        self._rejoined.set()
        async with self._restarts:
            self._restarts.notify_all()

    async def until_restarting(self, robots: Collection[str]) -> list[str]:
        """Wait until some of ``robots`` run again as new processes not
        joined yet; those that do."""
        async with self._restarts:
            await self._restarts.wait_for(lambda: any(r in self._restarted for r in robots))
        return sorted(r for r in robots if r in self._restarted)

    async def ready_for(self, cluster: Sequence[str], seq: int,
                        records: list[TaskRecord]) -> tuple[list[str], list[TaskRecord]]:
        """Before task ``seq`` is posted to ``cluster``: the robots joining
        at it, and their old processes' unexecuted tasks (to go round
        again); the robots back are taken back.  While every robot of the
        cluster is down after that, for at most a task timeout, it waits
        for one to restart (told at once) or to answer again as the process
        its teammates still count (asked once every request timeout), and
        does it all again.  Found in the simulator (nine robots with power
        cuts and forged syncs): a power cut and a freeze left a cluster
        without anyone for 15 s and the feeder gave the run up at its next
        task (seed 2); a restart told while robots were taken back made the
        last one down (seeds 728 and 770, the feeder starved).  Past the
        bound, the task finds them all down, and the run fails saying so."""
        watcher = self.channel.watcher
        timeout = self.channel.settings.task_timeout_s
        deadline = clock.monotonic() + timeout
        joining: list[str] = []
        left_behind: list[TaskRecord] = []
        waited = False
        while True:
            self._rejoined.clear()
            now_joining = sorted([*self.joining(cluster), *await self._back_from_left_out(cluster, records)])
            if now_joining:
                left_behind += self.prepare_join(records, now_joining, seq)
                joining += now_joining
            await self.take_back(cluster, records)
            remaining = deadline - clock.monotonic()
            if any(r not in watcher.down for r in cluster) or remaining <= 0:
                return joining, left_behind
            if not waited:
                log.warning("every robot of a cluster (%s) is down: waiting up to %gs for one to come back",
                            ", ".join(cluster), timeout)
                waited = True
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(min(watcher.request_timeout_s, remaining)):
                    await self._rejoined.wait()

    async def left_out(self, robot_id: str, why: str) -> None:
        """``robot_id``'s teammates left it out of a newer membership (the
        record voids its decision): it decides apart, in a membership of its
        own, until it joins theirs again.  It is down for the feeder, fed
        nothing, and its unexecuted tasks go round again once no majority
        grants it a lease (:meth:`recover`); then, holding no task of its
        own, it joins at the next task, as a restarted robot does, with the
        same process (:meth:`ready_for`).  Found in the simulator (nine robots
        with partitions, seeds 6028 and 16092): a robot cut off at the
        start, left out, never learned it; deciding on in a membership of its
        own, it split its cluster's decisions once another member was cut off."""
        if robot_id in self._left_out or robot_id in self._restarted:
            return
        log.warning("%s is %s: it joins again once it holds no task", robot_id, why)
        self._left_out[robot_id] = why
        await self.channel.watcher.declare_down(robot_id, f"{why}: it joins again once it holds no task")

    async def _back_from_left_out(self, cluster: Sequence[str], records: list[TaskRecord]) -> list[str]:
        """The robots left out (:meth:`left_out`) ready to join again: asked
        once (all at once, for a few round trips: one frozen or cut off is
        not back yet), the same process, idle, and no task of its own left
        unexecuted."""
        watcher = self.channel.watcher
        out = [r for r in cluster if r in self._left_out]
        if not out:
            return []
        timeout = self._not_back_yet_s()
        ready = []
        for robot_id, state in zip(out, await asyncio.gather(*(self.channel.state(r, timeout) for r in out)),
                                   strict=True):
            if state is None or not self._same_process(robot_id, state):
                continue  # silent, or restarted: a new process joins when whoever restarted it says so
            watcher.states[robot_id] = state  # what it did meanwhile: done, dropped
            if idle(watcher.states, robot_id) and not unexecuted(records, watcher, robot_id, self._incarnation,
                                                                 self._done_before):
                ready.append(robot_id)
        return ready

    def restarting(self, robot_id: str) -> bool:
        """Whether ``robot_id`` runs again as a new process that has not joined yet."""
        return robot_id in self._restarted

    def joining(self, cluster: Sequence[str]) -> list[str]:
        return sorted(r for r in cluster if r in self._restarted)

    def prepare_join(self, records: list[TaskRecord], joining: list[str], seq: int) -> list[TaskRecord]:
        """Before restarted robots join at task ``seq``: their previous
        processes' unexecuted tasks (returned, to go round again), then count
        on them afresh."""
        found = self._left_behind(joining, records)
        watcher = self.channel.watcher
        for robot_id in joining:
            self._restarted.discard(robot_id)
            self._incarnation[robot_id] = seq
            if self._left_out.pop(robot_id, None) is not None:
                # The same process: its count goes on from the jobs done before.
                self._done_before[robot_id] = watcher.states[robot_id].live.done
            else:
                self._done_before.pop(robot_id, None)  # a new process: its count starts at 0
            self._fenced_off.discard(robot_id)
            watcher.readmit(robot_id)
        return found

    def left_by_restarts(self, cluster: Sequence[str], records: list[TaskRecord]) -> list[TaskRecord]:
        """The unexecuted tasks of the processes before a restart, of the
        cluster's robots that have not joined again yet: they go round now,
        and the robot joins at the first of them.  Found otherwise only at
        the join, they were lost when no task was left to join at (found in
        the simulator, seed 27361 of the storage and forgery profile: Robot2
        killed holding tasks 7 and 9, back as a new process, and the feeder,
        cut off meanwhile, past its last task).  Its old process is gone
        (killed: it cannot pick anything), so no fence is needed."""
        return self._left_behind([r for r in cluster if r in self._restarted], records)

    def _left_behind(self, restarted: Sequence[str], records: list[TaskRecord]) -> list[TaskRecord]:
        """The unexecuted tasks of ``restarted`` robots' processes before their restart."""
        if not restarted:
            return []
        watcher = self.channel.watcher
        for robot_id in restarted:
            # A restart the feeder was told of: the old process is gone even if
            # no failed request told yet (killed: it cannot pick anything).
            watcher.down.setdefault(robot_id, "restarted")
        return orphans(records, watcher, self._incarnation, restarted, only=restarted, done_before=self._done_before)

    def orphans(self, records: list[TaskRecord]) -> list[TaskRecord]:
        """The cluster's tasks to send round again now (see :func:`~coapkb.feeder.orphans.orphans`)."""
        return orphans(records, self.channel.watcher, self._incarnation, self._fenced_off,
                       done_before=self._done_before)

    def executed_next(self, robot_id: str, records: Sequence[TaskRecord]) -> bool:
        """Whether ``robot_id``'s current process, as last observed, had done
        a job past every one ``records`` (the cluster's) give it: the job of
        the task being recorded (see :func:`~coapkb.feeder.orphans.executed_next`)."""
        return executed_next(records, self.channel.watcher, robot_id, self._incarnation, self._done_before)

    def undecided(self, cluster: Sequence[str], records: list[TaskRecord]) -> list[TaskRecord]:
        """Tasks no robot decided (each that took one went down first), to
        send round again once every robot of the cluster runs as a process
        started after the task: the processes that took it are dead, so
        nobody can pick it (found in the simulator: the three robots of a
        cluster restarted in turn, each before the previous one had joined).
        A robot whose process is known gone (nobody listens at its address)
        counts as one started after it: found in the simulator, the last of
        the three was killed and came back only after the last task, so it
        never joined.  While one of them may still run, the task stays as it
        is (failed)."""
        taken = {r.reassigned_from for r in records if r.reassigned_from is not None}
        gone = self.channel.watcher.gone
        found = []
        for record in records:
            if record.decisions or record.orphaned is not None or record.seq in taken:
                continue
            if all(self._incarnation.get(r, 0) > record.seq or r in gone for r in cluster):
                record.orphaned = "every robot that took it went down before deciding it"
                found.append(record)
        return found

    async def take_back(self, cluster: Sequence[str], records: Sequence[TaskRecord],
                        deciding: PendingTask | None = None) -> None:
        """Feed again a robot the feeder has down but its teammates still
        count as a member (their last decision names it): it was only slow
        or cut off, and under "compute by all" they wait for its plan after
        every task.  It is asked once; if it answers with the same process (a
        new one joins instead, at a task boundary), it is given the tasks it
        missed, in order (``deciding``, the task being decided, last), and
        fed from now on like the others."""
        for robot_id in cluster:
            await self._take_back(robot_id, records, deciding)

    async def _take_back(self, robot_id: str, records: Sequence[TaskRecord],
                         deciding: PendingTask | None = None) -> int | None:
        """:meth:`take_back` for one robot: the last task it was given again,
        or None if it was not taken back."""
        watcher = self.channel.watcher
        if (not records or robot_id not in watcher.down or robot_id not in records[-1].members
                or robot_id in self._fenced_off or robot_id in self._restarted):
            return None
        # A dead robot is asked at each task boundary until its teammates
        # leave it out (a task or two): a few round trips, not a liveness
        # timeout, since silence here only means "not back yet".
        state = await self.channel.state(robot_id, self._not_back_yet_s())
        if state is None or not self._same_process(robot_id, state):
            return None
        # A process that joined at task J decided nothing before it and takes nothing older.
        seen = max(state.last.seq if state.last is not None else 0, self._incarnation.get(robot_id, 1) - 1)
        missed = [PendingTask(r.seq, r.object, task_post(r.seq, r.object, r.joined, r.reassigned_from))
                  for r in records if r.seq > seen]
        if deciding is not None and deciding.seq > seen:
            missed.append(deciding)
        log.warning("%s answers again and its teammates still count it: fed again from task %d",
                    robot_id, seen + 1)
        watcher.readmit(robot_id)
        for task in missed:  # the robot takes tasks strictly in order
            await self.channel.post_task(robot_id, task.post, task.seq, task.object)
        return missed[-1].seq if missed else seen

    def _not_back_yet_s(self) -> float:
        """How long a robot down is waited for when asked whether it is back:
        a few round trips, not a liveness timeout, since silence here only
        means "not back yet"."""
        watcher = self.channel.watcher
        srtt = watcher.round_trip.srtt
        return watcher.request_timeout_s if srtt is None else min(watcher.request_timeout_s, max(0.25, 3 * srtt))

    def _same_process(self, robot_id: str, state: RobotState) -> bool:
        """Whether ``state`` is the process of ``robot_id`` this feeder fed:
        its ``boot`` if one was observed; else it decided a task fed to this
        process (a new process decides nothing before it joins, and joins
        only at a task this feeder posts).  Found in the simulator (seed
        3866): the feeder, cut off from the start, never observed a robot
        that its teammates went on counting, and could never take it back."""
        known = self.channel.watcher.states.get(robot_id)
        if known is not None:
            return state.boot == known.boot
        return state.decided(max(1, self._incarnation.get(robot_id, 0)))

    async def take_back_while(self, cluster: Sequence[str], records: Sequence[TaskRecord],
                              deciding: PendingTask, decided: asyncio.Future[Any]) -> None:
        """:meth:`take_back` once every request timeout until ``decided`` is
        done: a robot cut off when task ``deciding`` was posted, and back
        since, misses it, while its teammates (who never found it down) wait
        for its plan on it, for as long as it answers them; no task boundary
        comes to take it back at.  Found in the simulator (seed 356 with
        the first repair at 0.2 s): the wait lasted 68 s."""
        period = self.channel.watcher.request_timeout_s
        while not decided.done():
            await asyncio.wait({decided}, timeout=period)
            if not decided.done():
                await self.take_back(cluster, records, deciding)

    async def recover(self, cluster: Sequence[str], records: list[TaskRecord]) -> None:
        """Once the cluster's survivors are idle: fence off every down robot
        that holds unexecuted tasks (so they may go round again), or, if its
        teammates still grant it (it came back), wait until it has done them."""
        watcher = self.channel.watcher
        for robot_id in cluster:
            if robot_id in watcher.down and robot_id not in self._fenced_off and unexecuted(
                records, watcher, robot_id, self._incarnation, self._done_before
            ):
                if await fence(self.channel, cluster, robot_id):
                    self._fenced_off.add(robot_id)
                else:
                    # Back, and still a member: the tasks posted to the others
                    # only while it was down are its own too, and one of them
                    # may be assigned to it.  Found in the simulator (seed
                    # 21011 of the storage and forgery profile): the last task,
                    # posted while Robot2 was frozen, went to Robot2, which
                    # never had its post.
                    given = await self._take_back(robot_id, records)
                    await settle(self.channel, robot_id, through=given)
