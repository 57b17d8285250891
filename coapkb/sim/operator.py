"""The operator of a simulated run, and the holders' KBs read from outside.

With ``--writes N`` an operator writes to random robots during the run
(:class:`Operator`), and the checker judges what the holders' KBs show of
those writes (:class:`Holders`): every acknowledged insert on every running
holder at the end, replicas at one version showing the same triples, and a
restarted holder catching up (:mod:`.catch_up`).  Both read the KBs as a
robot's own queries would, never the replication's bookkeeping alone.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import pyoxigraph as ox

from ..agent.robot import Robot
from ..config import RobotConfig
from ..kb.client import KBClient, QueryFailed
from ..kb.live import LiveKB
from ..kb.results import expect_ask, expect_select
from ..model.results import QueryResult
from ..transport.base import TransportError
from ..world.vocabulary import ONTOLOGIES
from .catch_up import CatchUps
from .loop import Process
from .network import INITIAL_RTO_S, SimNetwork
from .observed import FilesQuads, WrittenViews

#: How long a restarted holder (no data folder) may take to catch up: its
#: catch-up's first two tries, from RFC 6298's first timeout with no sample
#: (1 s, then 2 s).  A holder's last copy dying sooner is a loss the
#: schedule excuses; later, the others should have had it.
CATCH_UP_WINDOW_S = 3 * INITIAL_RTO_S
#: The subject of each module's write log: the operator's writes add and
#: remove values of its multi-valued ``written`` property.
WRITE_LOG = "WriteLog"
#: With links that hold messages back: the share of adds removed again,
#: and how long after the add's answer (time for its deltas to spread, so
#: the remove has seen every copy and is judged as settled).
UNDO_SHARE = 0.3
UNDO_AFTER_S = 0.3
MOVE_ROBOT = (
    "PREFIX loc: <http://www.tcs.org/2018/Location#> DELETE {{ loc:{robot} loc:Robot_aisle_no ?a }} "
    "INSERT {{ loc:{robot} loc:Robot_aisle_no {aisle} }} WHERE {{ loc:{robot} loc:Robot_aisle_no ?a }}"
)


@dataclass(frozen=True)
class WriteOp:
    """One of the operator's writes, as sent and answered.

    ``kind``: ``insert`` or ``delete`` of the value ``value`` of the
    multi-valued log property of ``module``, or ``move`` (a robot's aisle,
    single-valued).  ``settled``: a delete sent while every holder of its
    module ran, reachable, at one version and showing the value: it saw
    every insert of it, so the value must stay gone unless inserted again."""

    label: str
    robot: str
    status: str
    module: str
    kind: str
    value: int
    sent_s: float
    answered_s: float
    settled: bool = False
    #: An acknowledged insert: how many holders had held the value when the
    #: operator had the answer (:meth:`Holders.copies`).
    copies: int = 0


def shows(live: LiveKB, module: str, value: int) -> bool:
    """Whether ``live``'s queries see ``value`` in ``module``'s write log."""
    ns = ONTOLOGIES[module][1]
    ask = f"ASK {{ <{ns}{WRITE_LOG}> <{ns}written> {value} }}"
    return expect_ask(live.query(ask), ask).value


def log_query(module: str) -> str:
    """The SELECT of ``module``'s write log: what the end of a run and an observer read."""
    ns = ONTOLOGIES[module][1]
    return f"SELECT ?v WHERE {{ <{ns}{WRITE_LOG}> <{ns}written> ?v }}"


def log_values(result: QueryResult, query: str) -> frozenset[int]:
    """The write log's values in an answer to :func:`log_query`."""
    return frozenset(int(str(row[0])) for row in expect_select(result, query).rows)


#: Per module at the end of a run: each running holder's version, the log
#: values its queries see, and the holders whose triples differ.
Outcome = tuple[dict[str, dict[str, str]], dict[str, dict[str, frozenset[int]]], dict[str, list[str]]]


class Holders:
    """The KBs of a run's robot processes, read from outside them.

    ``robots`` and ``current`` are the run's own (each robot's latest
    process, and its status), read as they change."""

    def __init__(self, configs: Mapping[str, RobotConfig], robots: Mapping[str, Robot],
                 current: Mapping[str, Process], elapsed_s: Callable[[], float], files: FilesQuads) -> None:
        self.configs = configs
        self.files = files
        self.robots = robots
        self.current = current
        self._elapsed_s = elapsed_s
        #: Robot -> when its current process had started.
        self.started_s: dict[str, float] = {}
        #: Every robot process's KB, the dead ones' as they were at their death.
        self.lives: list[tuple[str, LiveKB]] = []
        #: Replicas found at one version showing different triples.
        self.split_versions: list[str] = []
        self._views = WrittenViews()

    def of(self, module: str) -> list[str]:
        """The robots the team makes holders of ``module``."""
        return [r for r, c in sorted(self.configs.items()) if module in c.team[r].kbs]

    def started(self, robot_id: str, live: LiveKB | None, at_s: float) -> None:
        """``robot_id``'s new process started at ``at_s``, serving ``live``
        (None: a read-only KB)."""
        self.started_s[robot_id] = at_s
        if live is not None:
            self.lives.append((robot_id, live))
            live.listeners.append(lambda modules: self._compare_at_version(robot_id, modules))

    def running(self) -> dict[str, dict[str, LiveKB]]:
        """Module -> running robot -> its LiveKB."""
        held: dict[str, dict[str, LiveKB]] = {}
        for robot_id, robot in self.robots.items():
            live = robot.replicator.live if robot.replicator is not None else None
            if live is None or self.current[robot_id].status != "running":
                continue
            for module in live.names:
                held.setdefault(module, {})[robot_id] = live
        return held

    def agree(self) -> bool:
        """Every module's running holders at one version."""
        return all(
            len({live.module_version(module) for live in holders.values()}) == 1
            for module, holders in self.running().items()
        )

    def copies(self, module: str, value: int) -> int:
        """How many holders of ``module`` have held ``value`` by now: a
        process showing it now, or one killed since, whose state (as it was
        at its death) showed it; what an acknowledgement may count on."""
        held = {robot_id for robot_id, live in self.lives if module in live.names and shows(live, module, value)}
        return len(held)

    def outcome(self) -> Outcome:
        """Per module at the end: each running holder's version, the log
        values its queries see, and the holders whose triples differ."""
        versions: dict[str, dict[str, str]] = {}
        values: dict[str, dict[str, frozenset[int]]] = {}
        differences: dict[str, list[str]] = {}
        # Each store read once, and compared by what changed since its files
        # (:class:`FilesQuads`): this runs at the end of every run.
        changed: dict[str, frozenset[ox.Quad]] = {}
        for module, holders in sorted(self.running().items()):
            select = log_query(module)
            versions[module] = {r: live.module_version(module).hex() for r, live in sorted(holders.items())}
            values[module] = {
                r: log_values(live.query(select), select)
                for r, live in sorted(holders.items())
            }
            for robot_id, live in holders.items():
                if robot_id not in changed:
                    changed[robot_id] = self.files.changed(live)
            first_id, *rest = sorted(holders)
            first = holders[first_id]
            for other_id in rest:
                other = holders[other_id]
                differ = sorted(str(q) for q in self.files.differ(first, changed[first_id], other, changed[other_id],
                                                                  module))
                if differ:
                    differences.setdefault(module, []).append(
                        f"{first_id} and {other_id} differ by {len(differ)} triples, e.g. {'; '.join(differ[:2])}")
        return versions, values, differences

    def _compare_at_version(self, robot_id: str, modules: frozenset[str]) -> None:
        """After ``robot_id``'s view changed: every other running holder at the
        same version of a changed module must show the same triples."""
        holders = self.running()
        for module in sorted(modules):
            mine = holders.get(module, {}).get(robot_id)
            if mine is None:
                continue
            version = mine.module_version(module)
            for other_id, other in sorted(holders[module].items()):
                if other_id != robot_id and other.module_version(module) == version:
                    view, theirs = self._views.of(mine, module), self._views.of(other, module)
                    if theirs != view:
                        differ = sorted(str(t) for t in view ^ theirs)[:3]
                        self.split_versions.append(
                            f"{robot_id} and {other_id} at version {version.hex()} of {module} show different "
                            f"triples at {self._elapsed_s():.3f}s: {'; '.join(differ)}")


class Operator:
    """The operator's writes, as they were answered, and what became of
    the acknowledged ones (:attr:`lost_copies`)."""

    def __init__(self, holders: Holders, network: SimNetwork, clock: Callable[[], float],
                 note: Callable[[str], None], catch_ups: CatchUps) -> None:
        self.holders = holders
        self._network = network
        self._clock = clock
        self._note = note
        self._catch_ups = catch_ups
        #: The writes, as they were answered.
        self.write_log: list[WriteOp] = []
        #: (module, value) -> how an acknowledged value's last copy died (no data folder).
        self.lost_copies: dict[tuple[str, int], str] = {}
        #: (module, value) -> how the last copy of a settled delete of it died (no data folder).
        self.lost_removals: dict[tuple[str, int], str] = {}

    async def write(self, process: Process, rng: random.Random, writes: int, horizon_s: float,
                    fed_at: float, undo: bool = False) -> None:
        """``writes`` writes from ``process``, at random times over
        ``horizon_s`` from ``fed_at``, each to a random robot and a module
        it holds.  A write adds a value to the module's log (a multi-valued
        property), adds the same value at two holders at once, removes a
        value added before, adds a value at one holder while another
        removes it, or moves a robot (a single value: the latest write wins).
        With ``undo`` (links that hold messages back), a third of the adds
        are removed again at the same robot once acknowledged and spread
        (:data:`UNDO_AFTER_S`): a try of the add held back until after the
        remove must be answered as the repeat it is, not bring the value
        back (the write's id, docs/knowledge.md "A write tried again")."""
        # A writer named by its process, not a random one: a seed runs alike.
        client = KBClient(await self._network.for_process(process).open_client("coap"), timeout=10.0,
                          writer=process.name)
        configs = self.holders.configs
        times = sorted(rng.uniform(0, horizon_s) for _ in range(writes))
        loop = asyncio.get_running_loop()
        pending: list[asyncio.Task[str]] = []
        inserted: dict[str, list[int]] = {}
        for i, at in enumerate(times):
            await asyncio.sleep(max(0.0, fed_at + at - loop.time()))
            robot = rng.choice(sorted(configs))
            module = rng.choice(configs[robot].team[robot].kbs)
            others = [r for r in self.holders.of(module) if r != robot]
            draw = rng.random()
            ops: list[tuple[str, str, int]] = []  # (robot, kind, value)
            if module == "Location" and draw < 0.25:
                ops.append((robot, "move", rng.randint(1, 9)))
            elif draw < 0.55 or (draw < 0.85 and not inserted.get(module)):
                ops.append((robot, "insert", i))
            elif draw < 0.65 and others:
                ops += [(robot, "insert", i), (rng.choice(others), "insert", i)]
            elif draw < 0.85:
                ops.append((robot, "delete", rng.choice(inserted[module])))
            elif others:
                ops += [(robot, "insert", i), (rng.choice(others), "delete", i)]
            else:
                ops.append((robot, "insert", i))
            undone = undo and len(ops) == 1 and ops[0][1] == "insert" and rng.random() < UNDO_SHARE
            for to, kind, value in ops:
                if kind == "insert" and not undone:
                    inserted.setdefault(module, []).append(value)
                elif kind == "delete":
                    self._catch_ups.deleting(module, value)
                send = self._send_and_undo if undone else self._send
                pending.append(loop.create_task(send(client, to, module, f"w{i}", kind, value)))
        await asyncio.gather(*pending)

    async def _send_and_undo(self, client: KBClient, robot: str, module: str, label: str, kind: str,
                             value: int) -> str:
        """Add ``value`` at ``robot``; once acknowledged, and spread, remove
        it there.  The last answer's status."""
        status = await self._send(client, robot, module, label, kind, value)
        if status != "2.04":
            return status
        await asyncio.sleep(UNDO_AFTER_S)
        self._catch_ups.deleting(module, value)
        return await self._send(client, robot, module, f"{label}-undo", "delete", value)

    def owed(self, robot_id: str) -> dict[str, set[int]]:
        """What ``robot_id``, restarting now, must catch up with: per module
        it holds, the acknowledged values every other running holder shows."""
        live = self.holders.running()
        owed: dict[str, set[int]] = {}
        for module in self.holders.configs[robot_id].team[robot_id].kbs:
            others = [kb for r, kb in live.get(module, {}).items() if r != robot_id]
            acknowledged = {op.value for op in self.write_log
                            if op.module == module and op.kind == "insert" and op.status == "2.04"}
            if others:
                owed[module] = {v for v in acknowledged if all(shows(kb, module, v) for kb in others)}
        return owed

    def last_copies(self, dying: str) -> None:
        """Acknowledged values that die with ``dying``'s memory (no data
        folder): no other holder's process, running or frozen, shows them,
        and each such process started too recently to have caught up
        (:data:`CATCH_UP_WINDOW_S`); and settled deletes that die with it
        (every other such process still shows the value).  A holder up for
        longer that lacks the value is the protocol's failure, not the
        schedule's."""
        robots, current, started_s = self.holders.robots, self.holders.current, self.holders.started_s
        robot = robots.get(dying)
        live = robot.replicator.live if robot is not None and robot.replicator is not None else None
        if live is None:
            return
        now = self._clock()
        others = {r_id: r.replicator.live for r_id, r in robots.items()
                  if r_id != dying and r.replicator is not None and r.replicator.live is not None
                  and current[r_id].status != "dead"}
        for op in self.write_log:
            if op.status != "2.04" or op.module not in live.names:
                continue
            holding = {r: kb for r, kb in others.items() if op.module in kb.names}
            if not all(now - started_s[r] < CATCH_UP_WINDOW_S for r in holding):
                continue
            key = (op.module, op.value)
            if op.kind == "insert" and key not in self.lost_copies and shows(live, *key):
                if not any(shows(kb, *key) for kb in holding.values()):
                    self.lost_copies[key] = self._lost(dying, now, holding)
            # The same for a delete: the dying holder had it, and every other
            # still shows the value (the add came to it first, the remove not yet).
            elif (op.kind == "delete" and op.settled and key not in self.lost_removals and not shows(live, *key)
                  and holding and all(shows(kb, *key) for kb in holding.values())):
                self.lost_removals[key] = self._lost(dying, now, holding)

    def _lost(self, dying: str, now: float, holding: Iterable[str]) -> str:
        started_s = self.holders.started_s
        young = "".join(f"; {r} had started {now - started_s[r]:.3f}s before" for r in sorted(holding))
        return f"{dying} was killed at {now:.3f}s with the last copy in memory (no data folder){young}"

    def _all_holders_settled(self, module: str, value: int) -> bool:
        """Every holder of ``module`` runs, reachable, at one version, showing
        ``value``: a delete sent now has seen every insert of it."""
        live = self.holders.running().get(module, {})
        holders = self.holders.of(module)
        if sorted(live) != holders or any(self._network.isolated(r) for r in holders):
            return False
        if len({kb.module_version(module) for kb in live.values()}) != 1:
            return False
        return all(shows(kb, module, value) for kb in live.values())

    def _text(self, module: str, kind: str, value: int) -> str:
        if kind == "move":
            robots = sorted(self.holders.configs)
            return MOVE_ROBOT.format(robot=robots[value % len(robots)], aisle=value)
        ns = ONTOLOGIES[module][1]
        verb = "INSERT" if kind == "insert" else "DELETE"
        return f"{verb} DATA {{ <{ns}{WRITE_LOG}> <{ns}written> {value} }}"

    async def _send(self, client: KBClient, robot: str, module: str, label: str, kind: str, value: int) -> str:
        """One write, noted with its answer's status (``lost``: no answer), which it returns."""
        sent = self._clock()
        settled = kind == "delete" and self._all_holders_settled(module, value)
        try:
            await client.update(self.holders.configs[robot].bind, self._text(module, kind, value))
            status = "2.04"
        except QueryFailed as exc:
            status = exc.response.status.dotted
        except TransportError:
            status = "lost"
        copies = self.holders.copies(module, value) if status == "2.04" and kind == "insert" else 0
        self._note(f"write {label} {kind} {value} to {robot} ({module}): {status}")
        self.write_log.append(WriteOp(label, robot, status, module, kind, value, round(sent, 6),
                                      round(self._clock(), 6), settled, copies))
        return status
