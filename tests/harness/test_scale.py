"""Teams past the nine robots the shipped KBs know: KBs generated for the
team, every task's fate counted, and server ports that never collide."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from support import ROOT

from coapkb.feeder import FateCounts, TaskRecord
from coapkb.harness.kbs import KnowledgeGap, generator_spec, kbs_for_team, known_robots
from coapkb.harness.team import DEFAULT_ONTOLOGIES, Placement, PortReservation, TeamSpec, _ephemeral_range
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.store import KnowledgeBase
from coapkb.world.generator import WarehouseSpec


def _rows(owl: Path, query: str) -> dict[str, dict[str, str]]:
    kb = KnowledgeBase.load([owl])
    return {str(r["robo_id"]): {k: str(v) for k, v in r.items()}
            for r in kb.query(NAMED_QUERIES[query].render({})).as_dicts()}  # type: ignore[union-attr]


def test_the_shipped_kbs_are_the_generators_for_nine_robots() -> None:
    assert generator_spec(DEFAULT_ONTOLOGIES) == WarehouseSpec()
    assert known_robots(DEFAULT_ONTOLOGIES) == {f"Robot{i}" for i in range(1, 10)}


def test_a_team_the_kbs_know_runs_on_them_as_they_are(tmp_path: Path) -> None:
    kbs = kbs_for_team(DEFAULT_ONTOLOGIES, [f"Robot{i}" for i in range(1, 10)], tmp_path / "kbs")
    assert (kbs.ontologies, kbs.generated) == (DEFAULT_ONTOLOGIES, None)
    assert not (tmp_path / "kbs").exists()


def test_a_larger_team_gets_kbs_that_add_its_robots_and_keep_the_rest(tmp_path: Path) -> None:
    team = [f"Robot{i}" for i in range(1, 13)]
    kbs = kbs_for_team(DEFAULT_ONTOLOGIES, team, tmp_path / "kbs")
    assert kbs.ontologies == tmp_path / "kbs"
    assert kbs.generated is not None and "does not know Robot10-Robot12 (3 robots)" in kbs.generated
    assert known_robots(kbs.ontologies) == set(team)
    # The same products, and the first nine robots as the shipped KBs have them.
    shipped, grown = DEFAULT_ONTOLOGIES / "Object.owl", kbs.ontologies / "Object.owl"
    drop = re.compile(r"<owl:versionInfo>.*</owl:versionInfo>")
    assert drop.sub("", shipped.read_text(encoding="utf-8")) == drop.sub("", grown.read_text(encoding="utf-8"))
    for owl, query in (("Capability.owl", "robot-specs"), ("Location.owl", "robot-positions")):
        before = _rows(DEFAULT_ONTOLOGIES / owl, query)
        after = _rows(kbs.ontologies / owl, query)
        assert set(after) == set(team)
        assert {r: after[r] for r in before} == before
    # The spec takes the generated KBs as they are.
    spec = TeamSpec(robots=12, ontologies=kbs.ontologies)
    assert kbs_for_team(spec.ontologies, spec.robot_ids, tmp_path / "again").generated is None


def test_kbs_not_made_by_the_generator_are_not_guessed_at(tmp_path: Path) -> None:
    for name in ("Object", "Location", "Capability"):
        text = (DEFAULT_ONTOLOGIES / f"{name}.owl").read_text(encoding="utf-8")
        (tmp_path / f"{name}.owl").write_text(re.sub(r"<owl:versionInfo>.*</owl:versionInfo>", "", text),
                                              encoding="utf-8")
    with pytest.raises(KnowledgeGap, match="does not know Robot10-Robot12.*--robots 12"):
        kbs_for_team(tmp_path, [f"Robot{i}" for i in range(1, 13)], tmp_path / "kbs")


def test_ports_for_a_hundred_robots_are_distinct_held_and_outside_the_ephemeral_range() -> None:
    low, _ = _ephemeral_range()
    ports = PortReservation("127.0.0.1")
    names = [f"Robot{i}" for i in range(1, 100)]
    try:
        taken = {name: ports.take(name, socket.SOCK_DGRAM) for name in names}
        assert len(set(taken.values())) == len(names)
        assert all(PortReservation.LOWEST <= p < low for p in taken.values())
        # Held: nobody else can bind one until its robot starts.
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other, pytest.raises(OSError):
            other.bind(("127.0.0.1", taken["Robot47"]))
        ports.release("Robot47")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as robot:
            robot.bind(("127.0.0.1", taken["Robot47"]))
    finally:
        ports.close()


def test_two_teams_placed_at_once_get_different_ports() -> None:
    first, second = Placement(), Placement()
    spec = TeamSpec(robots=3, transport="coap")
    try:
        a = {first.endpoint(f"Robot{i}", spec).port for i in range(1, 100)}
        b = {second.endpoint(f"Robot{i}", spec).port for i in range(1, 100)}
        assert len(a) == len(b) == 99 and not a & b
    finally:
        first.close()
        second.close()


def test_fate_counts_of_no_tasks() -> None:
    assert FateCounts.of([]).line() == ("0 tasks, 0 assigned, 0 skipped, 0 unassigned, 0 unavailable, "
                                         "0 reassigned, 0 not found, 0 with errors, 0 disagreements")
    one = TaskRecord("Gucci_bag_14", 1, 1, assigned_to="Robot1", decisions={"Robot1": "Robot1"})
    assert FateCounts.of([one]).counted == 1


@pytest.mark.slow
def test_a_team_of_twelve_on_the_default_command_assigns_every_task(tmp_path: Path) -> None:
    """Robots 10-12 are not in the shipped KBs: the team runs on KBs generated
    for it, says so, and no task goes unassigned for want of them."""
    out = tmp_path / "record.json"
    result = subprocess.run(
        [sys.executable, "-m", "coapkb", "team", "--robots", "12", "--tasks", "16", "--quiet", "--record", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=150,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    stdout = result.stdout
    assert re.search(r"^the Capability KB in .* does not know Robot10-Robot12 \(3 robots\): "
                     r"generated KBs for 12 robots .* in .*ontologies, removed when the run ends$", stdout, re.M), stdout
    line = re.search(r"^12 robots, distributed, coap, compute-by-all: (.*)$", stdout, re.M)
    assert line, stdout
    counts = {word: int(n) for n, word in re.findall(
        r"(\d+) (tasks|assigned|skipped|unassigned|unavailable|reassigned|with errors|disagreements)", line[1])}
    assert counts["tasks"] == 16 == sum(n for word, n in counts.items() if word != "tasks")
    assert counts["assigned"] + counts["skipped"] == 16, line[0]
    record = json.loads(out.read_text(encoding="utf-8"))
    assert {t["fate"] for t in record["tasks"]} <= {"assigned", "skipped"}
    assert record["fates"]["tasks"] == 16 and record["fates"]["unassigned"] == 0
    # Clusters 1 to 4 all got tasks, robots 10-12's cluster too.
    assert {t["cluster"] for t in record["tasks"]} == {1, 2, 3, 4}
    assert any(t["assigned_to"] in ("Robot10", "Robot11", "Robot12") for t in record["tasks"]), record["tasks"]
