"""Whole teams on loopback, robots as real OS processes: the invariants of the seed's workflow.

Every run is checked against the knowledge bases directly (loaded here, not
through the team) and against an offline replay of the Task Assigner, so the
same task list must give the same assignments whatever the mode, transport,
strategy or team size.
"""

from __future__ import annotations

import asyncio
import json
import os
import select
import signal
import subprocess
import sys
import time
from functools import cache
from typing import Any

import cbor2
import pytest
from support import ROOT

from coapkb.agent.robot_state import PlannedState
from coapkb.agent.settling import SETTLE_DECIDING_TIMEOUTS
from coapkb.agent.task_assigner import RobotEnergy, TaskFacts, assign
from coapkb.config import CostModel
from coapkb.feeder import split_tasks
from coapkb.harness.record import TeamRecord
from coapkb.harness.team import Team, TeamSpec, draw_tasks, robot_starts
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.store import KnowledgeBase
from coapkb.transport import open_client
from coapkb.transport.messages import ContentFormat, Method, Request
from coapkb.world import DEPOT, layout_from_row, travel_distance

ONTOLOGIES = ROOT / "ontologies"

MISSING = ("Nonexistent_thing_1", "Nonexistent_thing_2")

#: Six robots, two clusters, five tasks each, one missing object per cluster.  Cluster 1's share
#: makes the payload limit bite: Robot1 (60.6 kg) is cheapest for the first two sacks and keeps
#: them (21.04 + 16.63 = 37.67 kg < 0.75 * 60.6), so 24.95 kg more would overload it and the
#: Danone sack must go to Robot3 although Robot1 can lift.  Then the seed's example object.
TASKS_6 = [
    "Barilla_rice_sack_786", "Bosch_rug_837", MISSING[0], "Danone_rice_sack_72", "Gucci_bag_14",
    "Heinz_rice_sack_414", "Nestle_canned_beans_435", "Levis_jeans_234", MISSING[1], "Canon_tv_995",
]
PAYLOAD_BOUND = {"object": "Danone_rice_sack_72", "overloaded": "Robot1", "winner": "Robot3"}

TASK_KEYS = {"object", "cluster", "seq", "skipped", "assigned_to", "decisions", "costs", "errors", "agreed",
             "coordination_s"}
COUNTER_KEYS = {"bytes_sent", "bytes_received", "messages_sent", "messages_received"}


# --------------------------------------------------------------------------- ground truth from the KBs


@cache
def kb(module: str) -> KnowledgeBase:
    return KnowledgeBase.load([ONTOLOGIES / f"{module}.owl"])


def rows(module: str, query: str, **params: str) -> list[dict[str, Any]]:
    return kb(module).query(NAMED_QUERIES[query].render(params)).as_dicts()  # type: ignore[union-attr]


@cache
def facts_of(name: str) -> TaskFacts | None:
    """The four queries, asked of the KB files directly (capable: every robot in the KB)."""
    if not rows("Object", "object-exists", name=name):
        return None
    where = rows("Location", "object-location", name=name)[0]
    features = rows("Object", "object-features", name=name)[0]
    grip = str(features["grip"]).rsplit("#", 1)[-1]
    capable = {str(r["robo_id"]): float(r["payload"]) for r in rows("Capability", "robots-for-grip", grip=grip)}
    return TaskFacts(0, name, int(where["aisle_no"]), int(where["rack_no"]), int(where["bin_no"]),
                     float(features["weight"]), grip, capable)


@cache
def payloads() -> dict[str, float]:
    return {str(r["robo_id"]): float(r["payload"]) for r in rows("Capability", "robot-specs")}


def expected_assignments(tasks: list[str], clusters: list[list[str]]) -> list[str | None]:
    """Offline replay of the Task Assigner, cluster by cluster, on the KBs' facts."""
    layout = layout_from_row(rows("Location", "warehouse-layout")[0])
    energy = {str(r["robo_id"]): RobotEnergy(float(r["e_empty"]), float(r["e_loaded"]), float(r["e_pick"]))
              for r in rows("Capability", "robot-specs")}
    starts = robot_starts(ONTOLOGIES)
    result: list[str | None] = []
    for cluster, share in zip(clusters, split_tasks(tasks, len(clusters))):
        states = {
            r: PlannedState(int(starts[r]["aisle"]), int(starts[r]["rack"]), float(starts[r]["battery_wh"]), 0.0,
                            float(starts[r]["payload_kg"]))
            for r in cluster
        }
        for seq, name in enumerate(share, start=1):
            facts = facts_of(name)
            if facts is None:
                result.append(None)
                continue
            facts = TaskFacts(seq, name, facts.aisle, facts.rack, facts.bin, facts.weight_kg, facts.grip,
                              {r: p for r, p in facts.capable.items() if r in cluster})
            outcome = assign(facts, states, {r: energy[r] for r in cluster},
                             lambda a, b: travel_distance(a, b, layout), DEPOT, CostModel())
            if outcome.plan is not None:
                states[outcome.plan.robot_id] = outcome.plan.after
            result.append(outcome.assigned_to)
    return result


def test_task_lists_are_what_the_tests_assume() -> None:
    for name in TASKS_6:
        assert (facts_of(name) is None) == (name in MISSING), name
    # Ground truth sanity: the grips' robot sets are proper subsets, so capability is a real constraint.
    assert all(len(facts_of(n).capable) < len(payloads()) for n in TASKS_6 if n not in MISSING)  # type: ignore[union-attr]


# --------------------------------------------------------------------------- checks on a record


def check_record(record: TeamRecord, spec: TeamSpec, tasks: list[str]) -> None:
    # The JSON form (what `coapkb team --record` writes) keeps its keys and reads back as the same record.
    data = json.loads(json.dumps(record.to_dict()))
    assert all(TASK_KEYS <= set(t) for t in data["tasks"]), data["tasks"]
    assert all(COUNTER_KEYS <= set(s[side]) for s in data["robot_stats"].values() for side in ("server", "client"))
    assert TeamRecord.from_dict(data).to_dict() == data
    assert record.mode == spec.mode
    assert record.transport == spec.transport
    assert record.strategy == spec.strategy
    assert record.robots == spec.robot_ids
    assert record.clusters == spec.clusters()
    assert [t.object for t in record.tasks] == tasks, "tasks in the order given"

    clusters = spec.clusters()
    executed: dict[str, int] = {r: 0 for r in spec.robot_ids}
    loads: dict[str, float] = {r: 0.0 for r in spec.robot_ids}
    for task in record.tasks:
        name = task.object
        assert task.coordination_s >= 0
        cluster = clusters[task.cluster - 1]
        # Every robot of the cluster decided, with no error, and all agree.
        assert set(task.decisions) == set(cluster), name
        assert task.errors == {}, (name, task.errors)
        assert len(set(task.decisions.values())) == 1, (name, task.decisions)
        assert task.agreed is True
        facts = facts_of(name)
        if facts is None:
            assert task.skipped is True, name
            assert task.assigned_to is None
            assert set(task.decisions.values()) == {None}
            continue
        assert task.skipped is False, name
        winner = task.assigned_to
        assert winner is not None, f"{name} not assigned: {task}"
        assert winner in cluster
        assert set(task.decisions.values()) == {winner}
        # Capability: the winner is among robots-for-grip of the object's grip (straight from the KBs).
        assert winner in facts.capable, f"{winner} cannot pick {name} by {facts.grip}"
        cost = task.costs[winner]
        assert cost is not None
        assert all(c is None or cost <= c for c in task.costs.values()), task.costs
        assert all(task.costs[r] is None for r in cluster if r not in facts.capable), task.costs
        # Payload: the object fits, and what the winner carries between unloads never exceeds its payload.
        payload = payloads()[winner]
        assert facts.weight_kg <= payload
        loads[winner] += facts.weight_kg
        assert loads[winner] <= payload + 1e-9, f"{winner} would carry {loads[winner]} kg > {payload} kg"
        if loads[winner] >= CostModel().unload_at_fraction * payload:
            loads[winner] = 0.0
        executed[winner] += 1

    # Determinism: the same assignments as an offline replay of the cost model.
    assert [t.assigned_to for t in record.tasks] == expected_assignments(tasks, clusters)

    stats = record.robot_stats
    assert set(stats) == set(spec.robot_ids)
    for robot_id, s in stats.items():
        assert s.server is not None, robot_id
        assert s.server.messages_received > 0 and s.server.bytes_received > 0
        assert s.server.messages_sent > 0 and s.server.bytes_sent > 0
        assert s.queries.failed == 0
        assert s.executed == executed[robot_id], (robot_id, s.executed, executed)
        assert s.idle is True
        computes = spec.strategy == "compute-by-all" or robot_id == min(
            next(c for c in clusters if robot_id in c), key=lambda r: int(r[5:])
        )
        if not computes:  # compute-and-communicate: only the leader queries
            assert s.queries.local == 0 and s.queries.remote == 0, (robot_id, s.queries)
            continue
        assert s.client.messages_sent > 0 and s.client.bytes_received > 0
        assert s.queries.remote + s.queries.pushed > 0  # facts from teammates: asked, or pushed
        if spec.mode == "central":
            assert s.queries.local == 0, (robot_id, s.queries)
        else:
            assert s.queries.local > 0, (robot_id, s.queries)
    total_local = sum(s.queries.local for s in stats.values())
    assert (total_local > 0) == (spec.mode == "distributed")


async def run_team(spec: TeamSpec, tasks: list[str], budget_s: float = 90.0) -> TeamRecord:
    async with asyncio.timeout(budget_s):
        async with Team.launch(spec) as team:
            expected = set(spec.robot_ids) | ({"central"} if spec.mode == "central" else set())
            assert set(team.processes) == expected
            record = await team.run(tasks)
            processes = dict(team.processes)
            workdir = team.workdir
    assert all(p.returncode is not None for p in processes.values()), "a process outlived Team.launch"
    assert not workdir.exists()
    return record


# --------------------------------------------------------------------------- the matrix


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["distributed", "central"])
@pytest.mark.parametrize("transport", ["coap", "zmq"])
async def test_six_robots(transport: str, mode: str) -> None:
    spec = TeamSpec(robots=6, mode=mode, transport=transport, query_timeout_s=5.0, task_timeout_s=30.0)
    record = await run_team(spec, TASKS_6)
    check_record(record, spec, TASKS_6)
    check_payload_bound(record)


def check_payload_bound(record: TeamRecord) -> None:
    """The capable but nearly full robot is refused (cost None) and the other lifter wins."""
    task = next(t for t in record.tasks if t.object == PAYLOAD_BOUND["object"])
    assert PAYLOAD_BOUND["overloaded"] in facts_of(PAYLOAD_BOUND["object"]).capable  # type: ignore[union-attr]
    assert task.costs[PAYLOAD_BOUND["overloaded"]] is None, task
    assert task.assigned_to == PAYLOAD_BOUND["winner"], task


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["coap", "zmq"])
async def test_compute_and_communicate(transport: str) -> None:
    spec = TeamSpec(robots=6, transport=transport, strategy="compute-and-communicate", query_timeout_s=5.0,
                    task_timeout_s=30.0)
    record = await run_team(spec, TASKS_6)
    check_record(record, spec, TASKS_6)
    check_payload_bound(record)


@pytest.mark.slow
async def test_nine_robots() -> None:
    tasks = draw_tasks(9, ONTOLOGIES, seed=5)
    tasks[1:1] = [MISSING[0]]
    tasks[7:7] = [MISSING[1]]
    spec = TeamSpec(robots=9, query_timeout_s=5.0, task_timeout_s=30.0)
    record = await run_team(spec, tasks)
    assert record.clusters == [["Robot1", "Robot2", "Robot3"], ["Robot4", "Robot5", "Robot6"],
                                  ["Robot7", "Robot8", "Robot9"]]
    check_record(record, spec, tasks)


# --------------------------------------------------------------------------- failures


async def _post_task(client, endpoint, seq: int, name: str) -> None:
    body = cbor2.dumps({"seq": seq, "object": name})
    response = await client.request(
        endpoint, Request(Method.POST, "/tasks", payload=body, content_format=ContentFormat.CBOR), timeout=5.0
    )
    assert response.status.is_success, response


async def _decisions(client, endpoint) -> list[dict[str, Any]]:
    response = await client.request(endpoint, Request(Method.GET, "/tasks", accept=ContentFormat.CBOR), timeout=5.0)
    assert response.status.is_success, response
    return cbor2.loads(response.payload)


@pytest.mark.slow
@pytest.mark.parametrize(
    "transport,mode,victim,names",
    [
        ("coap", "distributed", "Robot2", ("Object KB", "Robot2")),
        ("zmq", "distributed", "Robot2", ("Object KB", "Robot2")),
        ("coap", "central", "central", ("KB", "central server")),  # every KB is there: any query fails first
    ],
)
async def test_unreachable_kb_holder_makes_its_tasks_unavailable(transport: str, mode: str, victim: str,
                                                          names: tuple[str, ...]) -> None:
    """The only robot holding the Object KB (no replica) dies: its teammates report which
    query, KB and robot failed, within a bounded time, instead of hanging; and they keep
    taking tasks.  (With replicas they go on: tests/harness/test_faults.py.)"""
    timeout_s = 3.0
    spec = TeamSpec(robots=3, mode=mode, transport=transport, query_timeout_s=timeout_s, replication=1)
    async with asyncio.timeout(60):
        async with Team.launch(spec) as team:
            team.processes[victim].send_signal(signal.SIGKILL)
            await team.processes[victim].wait()
            survivors = [r for r in spec.robot_ids if r != victim]
            client = await open_client(transport, security=team.feeder_security())  # as the feeder (OSCORE)
            try:
                for seq, name in enumerate(["Gucci_bag_14", "Dell_monitor_986"], start=1):
                    fed = time.monotonic()
                    for r in survivors:
                        await _post_task(client, team.endpoints[r], seq, name)
                    decided: dict[str, dict[str, Any]] = {}
                    # The queries fail after query_timeout_s; the bound only tells a hang from a
                    # slow, loaded machine, so it is generous.
                    deadline = fed + timeout_s * 4 + 30
                    while len(decided) < len(survivors):
                        assert time.monotonic() < deadline, f"no decision on task {seq} from {survivors}: hanging"
                        for r in survivors:
                            log = await _decisions(client, team.endpoints[r])
                            if len(log) >= seq:
                                decided[r] = log[seq - 1]
                        await asyncio.sleep(0.1)
                    for r, decision in decided.items():
                        assert decision["seq"] == seq and decision["object"] == name
                        assert decision["assigned_to"] is None, (r, decision)
                        # No live holder: the task is unavailable, and why.
                        error = decision["unavailable"]
                        assert error and decision["error"] is None, (r, decision)
                        for needle in names:
                            assert needle in error, (r, needle, error)
                        # The Object and Location queries go out together: whichever
                        # fails first is named, or, once failed queries have declared
                        # the holder down, that.
                        assert any(q in error for q in ("pick-facts", "pick-place", f"{victim}: down")), error
                        # The query's timeout, then asking the teammates whether one had
                        # the knowledge: SETTLE_WAIT_TIMEOUTS query timeouts, stretched up to
                        # SETTLE_DECIDING_TIMEOUTS while a teammate answers that it is still
                        # deciding (on a loaded machine both survivors' queries do not fail
                        # at the same moment: 12.3 s was seen against the shorter bound).
                        bound = timeout_s * (1 + SETTLE_DECIDING_TIMEOUTS) + 2
                        assert decision["coordination_s"] <= bound, (r, decision)
                for r in survivors:
                    assert team.processes[r].returncode is None, f"{r} died"
            finally:
                await client.aclose()


# --------------------------------------------------------------------------- no process left behind


async def test_processes_stop_when_the_body_raises() -> None:
    class Boom(Exception):
        pass

    processes = {}
    with pytest.raises(Boom):
        async with asyncio.timeout(60):
            async with Team.launch(TeamSpec(robots=3)) as team:
                processes = dict(team.processes)
                workdir = team.workdir
                assert all(p.returncode is None for p in processes.values())
                raise Boom()
    assert set(processes) == {"Robot1", "Robot2", "Robot3"}
    assert all(p.returncode is not None for p in processes.values())
    assert not workdir.exists()
    for p in processes.values():
        assert not _alive(p.pid), p.pid


async def test_processes_stop_when_the_body_is_cancelled() -> None:
    processes = {}

    async def body() -> None:
        async with Team.launch(TeamSpec(robots=3, mode="central")) as team:
            processes.update(team.processes)
            await asyncio.sleep(3600)

    task = asyncio.create_task(body())
    async with asyncio.timeout(60):
        while len(processes) < 4:
            await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    assert all(p.returncode is not None for p in processes.values())


def _alive(pid: int) -> bool:
    """Running (not gone, not a zombie)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _children(pid: int) -> list[int]:
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(entry))
    return found


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _processes_mentioning(text: str) -> list[int]:
    return [int(e) for e in os.listdir("/proc") if e.isdigit() and text in _cmdline(int(e)) and _alive(int(e))]


@pytest.mark.slow
@pytest.mark.parametrize(
    "sig,to_group,exit_code",
    [(signal.SIGINT, True, 130), (signal.SIGTERM, False, 128 + signal.SIGTERM)],
    ids=["ctrl-c-to-group", "sigterm-to-parent"],
)
def test_cli_team_interrupted_leaves_no_process(sig: int, to_group: bool, exit_code: int) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "coapkb", "team", "--robots", "3", "--tasks", "50", "--time-scale", "5"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
    )
    agents: list[int] = []
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        first = proc.stdout.readline().decode() if ready else ""
        assert first.startswith("team up"), (first, proc.poll())
        agents = _children(proc.pid)
        configs = {c.split("--config ", 1)[1].split()[0] for c in map(_cmdline, agents) if "--config " in c}
        assert len(agents) == 3 and len(configs) == 3, [_cmdline(a) for a in agents]
        run_dir = os.path.dirname(next(iter(configs)))
        assert "coapkb-team-" in run_dir
        time.sleep(0.3)  # in the middle of the run
        if to_group:
            os.killpg(proc.pid, sig)
        else:
            os.kill(proc.pid, sig)
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"coapkb team did not exit within 60 s of {signal.Signals(sig).name}")
        assert proc.returncode == exit_code, (proc.returncode, err.decode()[-2000:])
        assert b"Traceback" not in err, err.decode()[-2000:]
        deadline = time.monotonic() + 30  # generous: the robots exit as soon as they are told
        while time.monotonic() < deadline and any(_alive(a) for a in agents):
            time.sleep(0.1)
        assert not [a for a in agents if _alive(a)], "robot agents outlived coapkb team"
        assert _processes_mentioning(run_dir) == []
        assert not os.path.exists(run_dir), "the team's temporary directory was left behind"
    finally:
        if proc.poll() is None:
            with_group = os.killpg
            try:
                with_group(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
        for a in agents:  # our grandchildren: never leave them running, even when the test fails
            if _alive(a) and "coapkb" in _cmdline(a):
                try:
                    os.kill(a, signal.SIGKILL)
                except ProcessLookupError:
                    pass
