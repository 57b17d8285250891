"""Team records and robot statistics: typed in the process, the same JSON/CBOR on the wire and on disk."""

from __future__ import annotations

import json
from dataclasses import replace

import cbor2

from coapkb.agent.query_handler import QueryStats
from coapkb.agent.stats import RobotStats
from coapkb.feeder import FateCounts, TaskRecord
from coapkb.harness.record import FaultEvent, TeamRecord, summarise
from coapkb.transport.base import TrafficCounters


def _stats(robot_id: str, *, sent: int, spurious: int = 0) -> RobotStats:
    return RobotStats(
        robot_id=robot_id, transport="coap", strategy="compute-by-all", query_wire="compact",
        retransmission={"profile": {"name": "robust"}, "peers": {"10.0.0.2:5683": {"spurious_retransmissions": spurious}}},
        server_retransmission=None,
        server=TrafficCounters(bytes_sent=sent, bytes_received=10, messages_sent=2, messages_received=1),
        client=TrafficCounters(bytes_sent=sent, bytes_received=20, messages_sent=3, messages_received=3,
                               retransmissions=1),
        queries=QueryStats(local=1, remote=2, failed=0, cached=1, remote_latencies=[0.012345, 0.5]),
        executed=1, idle=True,
    )


def _record() -> TeamRecord:
    tasks = [
        TaskRecord("Gucci_bag_14", 1, 1, assigned_to="Robot2", decisions={"Robot1": "Robot2", "Robot2": "Robot2"},
                   costs={"Robot1": 3.5, "Robot2": 1.25}, reasons={}, coordination_s=0.1234567),
        TaskRecord("Nonexistent_thing_1", 1, 2, skipped=True, decisions={"Robot1": None, "Robot2": None}),
        TaskRecord("Canon_tv_995", 1, 3, decisions={"Robot1": "Robot1", "Robot2": None},
                   errors={"Robot2": "query timed out"}),
    ]
    return TeamRecord(
        mode="distributed", transport="coap", strategy="compute-by-all",
        query_wire="compact", robots=["Robot1", "Robot2"], clusters=[["Robot1", "Robot2"]], tasks=tasks,
        coordination_s=1.5, completion_s=2.25,
        robot_stats={"Robot1": _stats("Robot1", sent=100, spurious=2), "Robot2": _stats("Robot2", sent=50)},
        feeder_traffic=TrafficCounters(bytes_sent=7, retransmissions=1),
    )


def test_robot_stats_keep_their_wire_form() -> None:
    stats = _stats("Robot1", sent=100, spurious=2)
    wire = stats.to_dict()
    assert list(wire) == ["robot_id", "transport", "strategy", "query_wire", "retransmission",
                          "server_retransmission", "server", "client", "queries", "remote_latencies_s",
                          "executed", "idle"]
    assert wire["queries"] == {"local": 1, "remote": 2, "failed": 0, "cached": 1, "failovers": 0, "hedged": 0,
                               "pushed": 0}
    assert RobotStats.from_dict(cbor2.loads(cbor2.dumps(wire))) == stats
    assert RobotStats.from_dict(json.loads(json.dumps(wire))) == stats
    assert stats.traffic.bytes_sent == 200 and stats.traffic.retransmissions == 1
    assert stats.spurious_retransmissions == 2
    # A ZeroMQ robot: no reliability description; a record from before 'cached' existed.
    old = {**wire, "retransmission": None, "queries": {"local": 1, "remote": 2, "failed": 0}}
    back = RobotStats.from_dict(old)
    assert back.spurious_retransmissions == 0 and back.queries.cached == 0


def test_team_record_round_trips_through_its_json_file() -> None:
    record = _record()
    data = json.loads(json.dumps(record.to_dict()))
    assert list(data) == ["mode", "transport", "strategy", "query_wire", "robots", "clusters",
                          "tasks", "coordination_s", "completion_s", "robot_stats", "feeder_traffic",
                          "faults", "down", "fates"]
    assert data["tasks"][0]["coordination_s"] == 0.123457 and data["tasks"][0]["agreed"] is True
    assert [t["agreed"] for t in data["tasks"]] == [True, True, False]
    back = TeamRecord.from_dict(data)
    assert back.to_dict() == data
    assert back.robot_stats == record.robot_stats and back.feeder_traffic == record.feeder_traffic
    assert [t.object for t in back.disputed] == ["Canon_tv_995"]
    # A record from before fault injection: no faults, nobody down, fates still derived.
    old = {**data, "tasks": [{k: v for k, v in t.items() if k in OLD_TASK_KEYS} for t in data["tasks"]]}
    del old["faults"], old["down"], old["fates"]
    back = TeamRecord.from_dict(old)
    assert (back.faults, back.down) == ([], {})
    assert [t.fate for t in back.tasks] == ["assigned", "skipped", "failed"]
    # A record from when it named the reliability profile: the name is ignored.
    assert TeamRecord.from_dict({**data, "retransmission": "robust"}).to_dict() == data


OLD_TASK_KEYS = {"object", "cluster", "seq", "skipped", "assigned_to", "decisions", "costs", "reasons", "errors",
                 "agreed", "coordination_s"}


def test_a_killed_robot_shows_in_the_record_and_summary() -> None:
    record = _record()
    orphan = record.tasks[0]
    orphan.orphaned = "Robot2 went down before executing it"
    rerun = TaskRecord(object=orphan.object, cluster=1, seq=4, assigned_to="Robot1",
                       decisions={"Robot1": "Robot1"}, epochs={"Robot1": 1}, members=["Robot1"],
                       absent={"Robot2": "2 requests failed"}, reassigned_from=orphan.seq)
    record = replace(record, tasks=[*record.tasks, rerun], faults=[FaultEvent("kill", "Robot2", 3.0, 1.25)],
                     down={"Robot2": "2 requests failed"})
    assert [t.fate for t in record.tasks] == ["reassigned", "skipped", "failed", "assigned"]
    data = json.loads(json.dumps(record.to_dict()))
    assert TeamRecord.from_dict(data).to_dict() == data
    lines = summarise(record).splitlines()
    assert lines[0].endswith("0 unassigned, 0 unavailable, 1 reassigned, 0 not found, 1 with errors, 0 disagreements")
    assert lines[1] == "assigned: Robot1 1"
    assert lines[-1] == "kill Robot2 at 3.0 s, declared down 1.2 s later"


def test_summary_counts_tasks_traffic_and_queries() -> None:
    lines = summarise(_record()).splitlines()
    assert lines[0] == ("2 robots, distributed, coap, compute-by-all: 3 tasks, 1 assigned, 1 skipped (1 no such object), "
                        "0 unassigned, 0 unavailable, 0 reassigned, 0 not found, 1 with errors, 0 disagreements")
    assert lines[1] == "assigned: Robot2 1"
    assert lines[2] == "coordination 1.50 s, completion 2.25 s"
    assert lines[3] == ("robots sent 300 B in 10 messages, received 60 B; "
                        "queries: 2 local, 4 remote, 2 answered from the cache")


def test_the_summary_counts_every_fate_once() -> None:
    """One task of each fate: every count is 1, the counts add up to the
    tasks, and the unassigned ones carry the robots' commonest reason."""
    decided = {"Robot1": "Robot1", "Robot2": "Robot1"}
    nobody = {"Robot1": None, "Robot2": None}
    tasks = [
        TaskRecord("Gucci_bag_14", 1, 1, assigned_to="Robot1", decisions=decided),
        TaskRecord("Nonexistent_thing_1", 1, 2, skipped=True, decisions=nobody),
        TaskRecord("Canon_tv_995", 1, 3, decisions=nobody, reasons={"Robot1": "cannot pick by suction",
                                                                   "Robot2": "cannot pick by suction"}),
        TaskRecord("Canon_tv_996", 1, 4, decisions=nobody, reasons={"Robot1": "cannot pick by suction",
                                                                   "Robot2": "battery low"}),
        TaskRecord("Canon_tv_997", 1, 5, decisions=nobody, reasons={"Robot1": "battery low",
                                                                   "Robot2": "battery low"}),
        TaskRecord("Sony_tv_1", 1, 6, decisions=nobody, unavailable="no live holder of the Object KB"),
        TaskRecord("Sony_tv_2", 1, 7, assigned_to="Robot2", decisions={"Robot2": "Robot2"},
                   orphaned="Robot2 went down before executing it"),
        TaskRecord("Sony_tv_3", 1, 8, decisions={"Robot1": "Robot1", "Robot2": None}, errors={"Robot2": "timeout"}),
        TaskRecord("Sony_tv_4", 1, 9, decisions={"Robot1": "Robot1", "Robot2": "Robot2"}),
        TaskRecord("Sony_tv_5", 1, 10, assigned_to="Robot1", decisions=decided,
                   not_found="Robot1 did not find it: gone: picked by Robot7 at task 3"),
    ]
    counts = FateCounts.of(tasks)
    assert (counts.assigned, counts.skipped, counts.unassigned, counts.unavailable, counts.reassigned,
            counts.not_found, counts.errors, counts.disagreements) == (1, 1, 3, 1, 1, 1, 1, 1)
    assert counts.counted == counts.tasks == len(tasks)
    assert (counts.unassigned_reason, counts.unassigned_reason_tasks) == ("cannot pick by suction", 2)
    record = replace(_record(), tasks=tasks)
    assert summarise(record).splitlines()[0] == (
        "2 robots, distributed, coap, compute-by-all: 10 tasks, 1 assigned, 1 skipped (1 no such object), 3 unassigned, "
        "1 unavailable, 1 reassigned, 1 not found, 1 with errors, 1 disagreements; "
        "unassigned mostly as 'cannot pick by suction' (2 of 3 tasks)")
    assert record.to_dict()["fates"]["unassigned"] == 3
