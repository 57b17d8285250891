"""examples/three-robots as its README runs it: keys made with the documented
command, three ``coapkb agent`` processes started from the example's TOML
files, and ``coapkb feed`` as the team's feeder.

The example folder is copied as it is into a temporary directory that also
holds (a link to) the repository's ontologies, so its relative paths
resolve as in the repository and the keys never land in the source tree.
Its ports are fixed: every process started here is stopped at the end.
"""

from __future__ import annotations

import os
import re
import select
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from support import ROOT

from coapkb.feeder import read_tasks_file

EXAMPLE = ROOT / "examples" / "three-robots"
ROBOTS = ("Robot1", "Robot2", "Robot3")
KEYS_COMMAND = "coapkb keys --team-dir examples/three-robots/keys"
#: What ``coapkb demo`` assigns the same tasks to (its robots start at their homes in the KBs too).
DEMO_ASSIGNMENTS = ["Robot2", "Robot1", "Robot2", "Robot1", "Robot1"]
TASK_LINE = re.compile(r"^\[cluster 1\] task +(\d+) (\S+) +-> (Robot[123]) \(\d+ ms\)$")
SKIP_LINE = re.compile(r"^\[cluster 1\] task +(\d+) (\S+) +skipped: (.*) \(\d+ ms\)$")


def run(workdir: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """``python -m coapkb ARGS`` from ``workdir``, as the README's commands run from the repository's root."""
    return subprocess.run([sys.executable, "-m", "coapkb", *args], cwd=workdir, env=_env(),
                          capture_output=True, text=True, timeout=timeout)


def _env() -> dict[str, str]:
    # This checkout's coapkb, whatever the working directory.
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": str(ROOT) + (os.pathsep + path if path else ""), "PYTHONUNBUFFERED": "1"}


def one_error_line(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode != 0, result
    assert "Traceback" not in result.stdout + result.stderr, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("coapkb: "), result.stderr
    return lines[0]


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """A stand-in for the repository's root: the example folder, copied, and the ontologies."""
    shutil.copytree(EXAMPLE, tmp_path / "examples" / "three-robots", ignore=shutil.ignore_patterns("keys"))
    (tmp_path / "ontologies").symlink_to(ROOT / "ontologies", target_is_directory=True)
    return tmp_path


@pytest.fixture
def robots(workdir: Path) -> Iterator[dict[str, subprocess.Popen[str]]]:
    """The three robots, started as the README says (once their keys exist); always stopped."""
    processes: dict[str, subprocess.Popen[str]] = {}
    logs = {r: workdir / f"{r}.stderr" for r in ROBOTS}  # a file, not a pipe nobody reads
    try:
        for robot_id in ROBOTS:
            with logs[robot_id].open("w") as log:
                processes[robot_id] = subprocess.Popen(
                    [sys.executable, "-m", "coapkb", "agent", "--config", f"examples/three-robots/{robot_id}.toml"],
                    cwd=workdir, env=_env(), stdout=subprocess.PIPE, stderr=log, text=True,
                )
        for robot_id, proc in processes.items():
            assert proc.stdout is not None
            ready, _, _ = select.select([proc.stdout], [], [], 90)
            line = proc.stdout.readline() if ready else ""  # "robot RobotN ready on ...", or nothing if it failed
            if not line.startswith(f"robot {robot_id} ready"):
                pytest.fail(f"{robot_id} did not start: {line or logs[robot_id].read_text() or 'no ready line'}")
        yield processes
    finally:
        for proc in processes.values():
            if proc.poll() is None:
                proc.terminate()
        for proc in processes.values():
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def test_the_example_files_are_valid_and_ship_no_keys() -> None:
    assert sorted(p.name for p in EXAMPLE.glob("*.toml")) == [f"{r}.toml" for r in ROBOTS]
    assert len(read_tasks_file(EXAMPLE / "tasks.txt")) == 5
    tracked = subprocess.run(["git", "ls-files", str(EXAMPLE)], cwd=ROOT, capture_output=True, text=True).stdout
    assert "keys/" not in tracked
    assert KEYS_COMMAND in (EXAMPLE / "README.md").read_text(encoding="utf-8")


@pytest.mark.slow
def test_a_robot_without_its_keys_names_the_command(workdir: Path) -> None:
    line = one_error_line(run(workdir, "agent", "--config", "examples/three-robots/Robot1.toml", timeout=60))
    assert KEYS_COMMAND in line, line


@pytest.mark.slow
def test_three_robots_started_by_hand_are_fed_their_tasks(workdir: Path, request: pytest.FixtureRequest) -> None:
    made = run(workdir, *KEYS_COMMAND.split()[1:], timeout=60)
    assert made.returncode == 0, made.stderr
    feed = ("feed", "--team", "examples/three-robots", "--tasks-file", "examples/three-robots/tasks.txt")

    # Nobody started yet: one line naming every robot and how to start it.
    line = one_error_line(run(workdir, *feed, "--answer-timeout", "2", timeout=60))
    for robot_id in ROBOTS:
        assert f"{robot_id} does not answer at coap://127.0.0.1:" in line, line
        assert f"coapkb agent --config examples/three-robots/{robot_id}.toml" in line, line

    processes = request.getfixturevalue("robots")
    result = run(workdir, *feed, "--record", "feed.mcap")
    assert result.returncode == 0, result.stdout + result.stderr
    with (workdir / "feed.mcap").open("rb") as f:  # recorded for Foxglove: every task, the robots' poses
        topics = [channel.topic for _, channel, _ in make_reader(f).iter_messages()]
    assert topics.count("/tasks") == 5 and topics.count("/warehouse") == 1 and "/robots/poses" in topics
    assert "Traceback" not in result.stdout + result.stderr
    tasks = read_tasks_file(EXAMPLE / "tasks.txt")
    lines = [m for m in map(TASK_LINE.match, result.stdout.splitlines()) if m]
    assert [(int(m[1]), m[2]) for m in lines] == list(enumerate(tasks, 1)), result.stdout
    # The robots of `coapkb demo`, with the same homes and KBs: the same assignments.
    assert [m[3] for m in lines] == DEMO_ASSIGNMENTS, result.stdout
    n = len(tasks)
    assert (f"{n} tasks, {n} assigned, 0 skipped, 0 unassigned, 0 unavailable, 0 reassigned, 0 not found, "
            "0 with errors, 0 disagreements; coordination") in result.stdout

    # Fed again, the robots go on with tasks 6 to 10, from where the first
    # list left them, and skip every object: each was picked by then.
    again = run(workdir, *feed)
    assert again.returncode == 0, again.stdout + again.stderr
    lines = [m for m in map(SKIP_LINE.match, again.stdout.splitlines()) if m]
    assert [(int(m[1]), m[2]) for m in lines] == list(enumerate(tasks, 6)), again.stdout
    assert [m[3] for m in lines] == [f"picked by {robot} at task {i}"
                                     for i, robot in enumerate(DEMO_ASSIGNMENTS, 1)], again.stdout
    assert f"{n} tasks, 0 assigned, {n} skipped ({n} already picked)" in again.stdout

    # A delivery first: the bag is back on its shelf (in the KB, written with
    # the operator's key, and for every robot's claim) and picked again.
    restocked = workdir / "restock.txt"
    restocked.write_text(f"restock {tasks[0]}\n{tasks[0]}\n", encoding="utf-8")
    delivered = run(workdir, "feed", "--team", "examples/three-robots", "--tasks-file", str(restocked))
    assert delivered.returncode == 0, delivered.stdout + delivered.stderr
    assert [(int(m[1]), m[2]) for m in map(TASK_LINE.match, delivered.stdout.splitlines()) if m] == [
        (2 * n + 1, tasks[0])], delivered.stdout
    assert "1 tasks, 1 assigned, 0 skipped" in delivered.stdout and "; restocked 1" in delivered.stdout

    # Robot2 stopped and started again by hand: a new process, no task taken.
    # The next feed has it join its teammates at its first task.
    processes["Robot2"].terminate()
    processes["Robot2"].wait(10)
    with (workdir / "Robot2.again.stderr").open("w") as log:
        processes["Robot2"] = restarted = subprocess.Popen(
            [sys.executable, "-m", "coapkb", "agent", "--config", "examples/three-robots/Robot2.toml"],
            cwd=workdir, env=_env(), stdout=subprocess.PIPE, stderr=log, text=True)
    assert restarted.stdout is not None
    ready, _, _ = select.select([restarted.stdout], [], [], 90)
    assert ready and restarted.stdout.readline().startswith("robot Robot2 ready")
    rejoined = run(workdir, *feed)
    assert rejoined.returncode == 0, rejoined.stdout + rejoined.stderr
    lines = [m for m in map(SKIP_LINE.match, rejoined.stdout.splitlines()) if m]
    assert [int(m[1]) for m in lines] == list(range(2 * n + 2, 3 * n + 2)), rejoined.stdout
    assert f"{n} tasks, 0 assigned, {n} skipped ({n} already picked)" in rejoined.stdout
    assert "0 disagreements" in rejoined.stdout
