"""The world in the team's knowledge, as a user runs it: ``coapkb team
--writable --misplace`` (repeats skipped as picked, by the robot the first
task went to; a misplaced object not found, and its repeat skipped as
missing) and ``coapkb world`` serving the
shelves to robots run by hand.  Subprocesses, exit codes, output, record."""

from __future__ import annotations

import asyncio
import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from support import ROOT

from coapkb.world.service import WorldClient, WorldUnavailable

MISPLACED = "not where the KB says it is (misplaced)"
#: Tasks 3 and 5 repeat tasks 1 and 2; task 4's object is not at its shelf, and task 6 repeats it.
TASKS = ["Gucci_bag_14", "Canon_tv_538", "Gucci_bag_14", "Barilla_pasta_1", "Canon_tv_538", "Barilla_pasta_1"]


def coapkb(*args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "coapkb", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.slow
def test_a_writable_team_skips_repeats_and_finds_a_misplaced_object_missing(tmp_path: Path) -> None:
    tasks_file = tmp_path / "tasks.txt"
    tasks_file.write_text("\n".join(TASKS) + "\n", encoding="utf-8")
    out = tmp_path / "out.json"
    result = coapkb("team", "--robots", "3", "--tasks-file", str(tasks_file), "--writable",
                    "--misplace", "Barilla_pasta_1", "--insecure", "--quiet", "--record", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    stdout = result.stdout

    record = json.loads(out.read_text(encoding="utf-8"))
    tasks = record["tasks"]
    assert [(t["seq"], t["object"]) for t in tasks] == list(enumerate(TASKS, start=1))
    first, second = tasks[0]["assigned_to"], tasks[1]["assigned_to"]
    assert first in record["robots"] and second in record["robots"], tasks
    assert [t["fate"] for t in tasks] == ["assigned", "assigned", "skipped", "not-found", "skipped", "skipped"], tasks
    # Every robot skipped each repeat alike, naming the robot the first task went to.
    assert tasks[2]["skip_reason"] == f"picked by {first} at task 1"
    assert tasks[4]["skip_reason"] == f"picked by {second} at task 2"
    # The robots skipped task 6 on the claim of task 4 too, but nobody picked
    # it: the record says the object is missing since task 4.
    assert tasks[5]["skip_reason"] == "missing from its place since task 4"
    for task in (tasks[2], tasks[4], tasks[5]):
        assert task["skipped"] and task["assigned_to"] is None and task["agreed"]
        assert set(task["decisions"]) == {"Robot1", "Robot2", "Robot3"}
    # Task 4 went to a robot, which found the shelf empty.
    four = tasks[3]
    assert four["assigned_to"] in record["robots"] and four["agreed"] and not four["skipped"]
    assert four["not_found"] == f"{four['assigned_to']} did not find it: {MISPLACED}"
    assert all(t["agreed"] and not t["errors"] for t in tasks)
    fates = record["fates"]
    assert (fates["assigned"], fates["skipped"], fates["not_found"], fates["disagreements"], fates["errors"]) == (
        2, 3, 1, 0, 0)
    assert fates["skip_kinds"] == {"already picked": 2, "missing": 1}

    # The summary.
    assert "[cluster" not in stdout  # --quiet
    assert re.search(
        r"^3 robots, distributed, coap, compute-by-all: 6 tasks, 2 assigned, 3 skipped \(2 already picked, 1 missing\), "
        r"0 unassigned, 0 unavailable, 0 reassigned, 1 not found, 0 with errors, 0 disagreements$",
        stdout, re.M), stdout
    assert (f"\nnot found: task 4 Barilla_pasta_1 (cluster 1): {four['assigned_to']} did not find it: {MISPLACED}\n"
            in stdout), stdout
    assert f"record written to {out}" in stdout
    # Where the robots wrote they are: the one task 4 went to, at that shelf (aisle 1, rack 3).
    [positions] = [line for line in stdout.splitlines() if line.startswith("positions in the Location KB")]
    moved = dict(re.findall(r"(Robot\d) \(\d+, \d+\) -> (\(\d+, \d+\))", positions))
    assert set(moved) == {"Robot1", "Robot2", "Robot3"}, positions
    assert moved[four["assigned_to"]] == "(1, 3)", positions


async def _world_process(*args: str) -> tuple[asyncio.subprocess.Process, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "coapkb", "world", *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
    )
    assert proc.stdout is not None
    line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
    return proc, line


@pytest.mark.slow
async def test_coapkb_world_serves_the_shelves_until_sigterm(tmp_path: Path) -> None:
    path = tmp_path / "world.sock"
    proc, line = await _world_process(str(path), "--misplace", "Barilla_pasta_1", "--misplace", "Lego_set_1")
    try:
        assert line == f"world serving on {path}; misplaced: Barilla_pasta_1, Lego_set_1\n", line
        robot1, robot2 = WorldClient(path), WorldClient(path)
        try:
            assert await robot1.take("Barilla_pasta_1", "Robot1", 1) == MISPLACED
            assert await robot1.take("Gucci_bag_14", "Robot1", 2) is None
            assert await robot2.take("Gucci_bag_14", "Robot2", 3) == "gone: picked by Robot1 at task 2"
        finally:
            await robot1.aclose()
            await robot2.aclose()
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = await asyncio.wait_for(proc.communicate(), 30)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    # (Whether stderr is clean depends on the world having seen the robots
    # hang up before SIGTERM: see the test below.)
    assert proc.returncode == 0, stderr.decode()[-3000:]
    assert stdout.decode() == "\n1 objects taken\n  Gucci_bag_14: picked by Robot1 at task 2\n"
    assert not path.exists()
    with pytest.raises(WorldUnavailable):
        await WorldClient(path, timeout_s=1.0).take("Gucci_bag_14", "Robot3", 4)


@pytest.mark.slow
async def test_coapkb_world_stops_cleanly_while_robots_are_connected(tmp_path: Path) -> None:
    """Robots run by hand keep their connection to the world between
    questions: SIGTERM ends it all the same, at once and without a traceback."""
    path = tmp_path / "world.sock"
    proc, line = await _world_process(str(path))
    robot = WorldClient(path)
    try:
        assert line == f"world serving on {path}\n", line
        assert await robot.take("Gucci_bag_14", "Robot1", 1) is None
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = await asyncio.wait_for(proc.communicate(), 10)
    finally:
        await robot.aclose()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0
    assert stdout.decode() == "\n1 objects taken\n  Gucci_bag_14: picked by Robot1 at task 1\n"
    assert "Traceback" not in stderr.decode(), stderr.decode()[-3000:]


@pytest.mark.slow
async def test_a_robot_of_a_killed_world_raises_world_unavailable(tmp_path: Path) -> None:
    path = tmp_path / "world.sock"
    proc, line = await _world_process(str(path))
    client = WorldClient(path, timeout_s=2.0)
    try:
        assert line == f"world serving on {path}\n"
        assert await client.take("Gucci_bag_14", "Robot1", 1) is None
        proc.kill()
        await proc.wait()
        loop = asyncio.get_running_loop()
        started = loop.time()
        with pytest.raises(WorldUnavailable):
            await client.take("Canon_tv_538", "Robot1", 2)
        assert loop.time() - started < 2.5
    finally:
        await client.aclose()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


@pytest.mark.parametrize("where, needle", [
    ("missing-dir/world.sock", "is not a directory"),
    ("a-file", "exists and is not a socket"),
])
def test_coapkb_world_refuses_a_path_it_cannot_serve_on(tmp_path: Path, where: str, needle: str) -> None:
    (tmp_path / "a-file").write_text("keep me", encoding="utf-8")
    result = coapkb("world", str(tmp_path / where), timeout=30)
    assert result.returncode == 2 and needle in result.stderr, result.stderr
    assert (tmp_path / "a-file").read_text(encoding="utf-8") == "keep me"
