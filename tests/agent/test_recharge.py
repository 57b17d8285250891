"""Robots recharge: a team whose batteries run down drives to the charging
docks and goes on picking.  Real processes on loopback (``coapkb team``) in a
generated warehouse whose batteries hold 40-60 Wh, so with the 20 Wh reserve
each robot has a few dozen Wh of work in it; time runs fast, so a charge
(about 5 simulated minutes) takes a fraction of a second."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cbor2
import pytest
from support import ROOT

from coapkb.agent.stats import Recharge, RobotStats
from coapkb.harness.record import TeamRecord
from coapkb.transport.base import TrafficCounters
from coapkb.world.generator import WarehouseSpec
from coapkb.world.ontologies import write_ontologies

SMALL_BATTERIES = WarehouseSpec(products=300, robots=3, battery_wh=(40.0, 60.0))
TASKS = 90


def test_recharges_keep_their_wire_form() -> None:
    stats = RobotStats("Robot1", "coap", "compute-by-all", "compact", None, None, None, TrafficCounters(),
                       recharges=[Recharge(12, (2, 26), 21.5, 48.0)])
    wire = stats.to_dict()
    assert wire["recharges"] == [{"seq": 12, "dock": [2, 26], "arrive_wh": 21.5, "full_wh": 48.0}]
    assert RobotStats.from_dict(cbor2.loads(cbor2.dumps(wire))) == stats
    assert RobotStats.from_dict(json.loads(json.dumps(wire))) == stats
    assert "recharges" not in RobotStats("Robot1", "coap", "compute-by-all", "compact", None, None, None,
                                         TrafficCounters()).to_dict()


@pytest.mark.slow
def test_a_team_with_small_batteries_recharges_and_leaves_no_task_unassigned(tmp_path: Path) -> None:
    write_ontologies(SMALL_BATTERIES, tmp_path / "kb")
    out = tmp_path / "record.json"
    result = subprocess.run(
        [sys.executable, "-m", "coapkb", "team", "--robots", "3", "--tasks", str(TASKS), "--seed", "3",
         "--ontologies", str(tmp_path / "kb"), "--time-scale", "5000", "--insecure", "--quiet",
         "--record", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    record = TeamRecord.from_dict(json.loads(out.read_text(encoding="utf-8")))

    # Every task found a robot: none refused for its battery, none disputed.
    assert [t.seq for t in record.tasks if t.fate != "assigned"] == []
    assert not record.disputed

    # Batteries went down to near the reserve, and up again at a dock.
    recharges = [(robot_id, r) for robot_id, s in record.robot_stats.items() for r in s.recharges]
    assert recharges, result.stdout
    docks = {(d.aisle, d.rack) for d in SMALL_BATTERIES.docks}
    for robot_id, charge in recharges:
        assert charge.dock in docks
        # It arrives at the dock above the 20 Wh reserve but below what it could
        # carry on with, and leaves full (the capacity, 40-60 Wh).
        assert 20.0 <= charge.arrive_wh < charge.full_wh and 40.0 <= charge.full_wh <= 60.0
        # The charge came before the task it was planned for, which that robot won.
        assert record.tasks[charge.seq - 1].assigned_to == robot_id
    # The winner's cost of a task with a charge holds the time at the dock: dearer than any other pick.
    charged_seqs = {charge.seq for _, charge in recharges}
    winners_cost = {t.seq: t.costs[t.assigned_to] for t in record.tasks if t.assigned_to}
    plain = max(cost for seq, cost in winners_cost.items() if seq not in charged_seqs)
    assert all(winners_cost[seq] > plain for seq in charged_seqs)
    assert "recharged at a dock: " in result.stdout
