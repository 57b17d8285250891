"""The faults that act on what a simulated run holds, beyond one process
or link: a trap sprung the moment a robot starts a pick, a power cut of
every holder of a module at once, a sync forged with a non-holder's
credential, and the torn journal a killed robot leaves on its disk.

They run in the run's ``faults`` process and carry out the plain faults
they need (kill, restart, freeze, cut and their ends) through the run's
own :meth:`~coapkb.sim.run.SimulatedTeam.inject`, which records them.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Coroutine, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from rdflib import Literal, URIRef

from ..agent.robot import Robot
from ..config import RobotConfig
from ..harness.team import TeamSpec
from ..kb.journal import encode_record
from ..kb.replication import SYNC_PATH
from ..model.deltas import CausalContext, Delta, Dot, Stamp
from ..transport.base import TransportError
from ..transport.messages import ContentFormat, Method, Request
from ..wire.sync import SyncMessage, encode_sync
from ..world.vocabulary import ONTOLOGIES
from .disk import SimDisk, restore_differences
from .faults import FaultEvent
from .loop import Process, Scheduler
from .network import SimNetwork
from .operator import WRITE_LOG, Holders


class Run(Protocol):
    """What the saboteur reads and does of a run (:class:`~coapkb.sim.run.SimulatedTeam`)."""

    @property
    def configs(self) -> Mapping[str, RobotConfig]: ...
    @property
    def robots(self) -> Mapping[str, Robot]: ...
    @property
    def current(self) -> Mapping[str, Process]: ...
    @property
    def holders(self) -> Holders: ...
    @property
    def scheduler(self) -> Scheduler: ...
    @property
    def network(self) -> SimNetwork: ...
    @property
    def disk(self) -> SimDisk: ...
    @property
    def team(self) -> TeamSpec: ...
    @property
    def ending(self) -> bool:
        """Every task is done: a trap set now is not sprung."""
    @property
    def elapsed_s(self) -> float: ...

    def note(self, text: str) -> None: ...

    def inject(self, event: FaultEvent) -> None: ...


@dataclass(frozen=True)
class Forgery:
    """A sync a non-holder's credential sent in a holder's writer name, and
    its answer: it must be refused, and its value never show."""

    victim: str
    forger: str
    module: str
    value: int
    status: str


class Saboteur:
    """What the run's ``faults`` process does to ``run``; ``disk_rng``
    draws the torn tails."""

    def __init__(self, run: Run, disk_rng: random.Random) -> None:
        self.run = run
        self._disk_rng = disk_rng
        #: The plain faults the traps and power cuts injected when they sprang.
        self.sprung: list[FaultEvent] = []
        #: The forged syncs sent, and their answers.
        self.forgeries: list[Forgery] = []
        #: What the traps, power cuts and forgers run.
        self._running: list[asyncio.Task[None]] = []
        #: Robots a power cut is killing: their disks lose what was not synced.
        self._powered_off: set[str] = set()
        #: How a dead robot's data folder would restore otherwise than it held (:func:`restore_differences`).
        self.restores: list[str] = []

    @property
    def done(self) -> bool:
        """Every trap, power cut and forger has ended."""
        return all(task.done() for task in self._running)

    def trap(self, event: FaultEvent) -> None:
        """Set ``event``'s trap: a freeze or a cut-off sprung at a pick."""
        self._start(self._trap(event))

    def forge(self, victim: str, forger: str) -> None:
        """A sync of ``victim``'s module sent with ``forger``'s credential."""
        self._start(self._forge(victim, forger))

    def _start(self, work: Coroutine[Any, Any, None]) -> None:
        self._running.append(self.run.scheduler.start(self.run.current["faults"], work))

    def torn_disk(self, robot_id: str) -> None:
        """What a killed robot leaves on its disk: its folder released (the
        OS closes a dead process's files and its lock), and, half the time,
        the start of a record it never finished writing (a torn tail, which
        the restart must cut)."""
        robot = self.run.robots.get(robot_id)
        keeper = robot.keeper if robot is not None else None
        if keeper is None:
            return
        keeper.journal.close()
        if robot_id in self._powered_off:
            # The page cache gone with the power: what no sync covered is lost.
            self._powered_off.discard(robot_id)
            for name, size in self.run.disk.power_cut(keeper.journal.path):
                self.run.note(f"disk {robot_id}: the power cut lost {size} unsynced bytes of {name}")
        if self._disk_rng.random() < 0.5:
            journals = sorted(keeper.journal.path.glob("journal.*"), key=lambda p: int(p.suffix[1:]))
            if journals:
                # A prefix of a whole record: what a write cut by the power leaves.
                record = encode_record(bytes(self._disk_rng.randrange(256) for _ in range(40)))
                torn = record[:self._disk_rng.randint(1, len(record) - 1)]
                with open(journals[-1], "ab") as tail:
                    tail.write(torn)
                self.run.note(f"disk {robot_id}: {len(torn)} bytes of a torn record after {journals[-1].name}")
        self.restores += restore_differences(robot_id, keeper.live, keeper.journal.path)

    def power_cut(self, robot_id: str, down_s: float) -> None:
        """Every holder of a module ``robot_id`` holds killed at once (a power
        cut), and restarted ``down_s`` later."""
        modules = self.run.configs[robot_id].team[robot_id].kbs
        if not modules:
            return
        holders = [r for r in self.run.holders.of(modules[0]) if self.run.current[r].status != "dead"]
        for holder in holders:
            self._powered_off.add(holder)
            self.sprung.append(FaultEvent(round(self.run.elapsed_s, 3), "kill", (holder,)))
            self.run.inject(self.sprung[-1])

        async def restart() -> None:
            await asyncio.sleep(down_s)
            for holder in holders:
                self.sprung.append(FaultEvent(round(self.run.elapsed_s, 3), "restart", (holder,)))
                self.run.inject(self.sprung[-1])
        self._start(restart())

    async def _forge(self, victim: str, forger: str) -> None:
        """``forger``'s credential used against ``victim``: a sync of a module
        ``victim`` holds and ``forger`` does not, carrying a delta in
        ``victim``'s own writer name at its next dot (the write it would make
        next would be taken for a duplicate and lost), stamped far ahead, that
        adds a value no one wrote to the module's log."""
        robot = self.run.robots.get(victim)
        live = robot.replicator.live if robot is not None and robot.replicator is not None else None
        held = [m for m in self.run.configs[victim].team[victim].kbs if m not in self.run.configs[forger].team[forger].kbs]
        if live is None or not held or self.run.current[victim].status == "dead":
            self.run.note(f"forge {victim} as {forger}: nothing to forge")
            return
        module = held[0]
        ns = ONTOLOGIES[module][1]
        value = -1 - len(self.forgeries)
        triple = (URIRef(f"{ns}{WRITE_LOG}"), URIRef(f"{ns}written"), Literal(value))
        writer = live.writer
        next_dot = Dot(writer, live.replicas[module].context.vv.get(writer, 0) + 1)
        stamp = Stamp(int(self.run.scheduler.clock.now * 1000) + 3_600_000, 0, writer)
        message = SyncMessage(module, CausalContext(), [Delta(next_dot, stamp, (triple,))], forward=True)
        request = Request(Method.POST, SYNC_PATH, payload=encode_sync(message), content_format=ContentFormat.CBOR,
                          peer=forger)
        client = await self.run.network.for_process(self.run.current["faults"]).open_client("coap")
        try:
            status = (await client.request(self.run.configs[victim].bind, request, timeout=10.0)).status.dotted
        except TransportError:
            status = "lost"
        self.run.note(f"forge {victim} as {forger} ({module} value {value}): {status}")
        self.forgeries.append(Forgery(victim, forger, module, value, status))

    async def _trap(self, event: FaultEvent) -> None:
        """Spring ``event``'s trap the moment its robot starts a pick (looked
        at every 10 ms of simulated time until the trap expires)."""
        target = event.targets[0]
        while self.run.elapsed_s < event.until_s and not self.run.ending:
            robot = self.run.robots.get(target)
            if (robot is not None and self.run.current[target].status == "running"
                    and robot.executor.live.activity == "picking"):
                if event.action == "freeze-picking":
                    start, end = FaultEvent(round(self.run.elapsed_s, 3), "freeze", (target,)), "resume"
                else:
                    everyone = tuple(r for r in ["feeder", *self.run.team.robot_ids] if r != target)
                    start, end = FaultEvent(round(self.run.elapsed_s, 3), "cut", (target,), other=everyone), "heal"
                self.sprung.append(start)
                self.run.inject(start)
                await asyncio.sleep(event.amount)
                self.sprung.append(FaultEvent(round(self.run.elapsed_s, 3), end, (target,)))
                self.run.inject(self.sprung[-1])
                return
            await asyncio.sleep(0.01)
