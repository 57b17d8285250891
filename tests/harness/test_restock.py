"""Deliveries during a shift, as a user runs them: ``restock OBJECT`` lines
in the task file of ``coapkb team`` (robots as processes, the world served
on its socket, the delivery written into the KB as the team's operator).
A picked object restocked is picked again; a misplaced one restocked is
found; without the delivery a repeat is skipped as before."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support import ROOT

#: Task 2 repeats task 1 (skipped: picked); then a delivery, and task 3 picks
#: the bag again.  Task 4's object is misplaced (not found); delivered anew,
#: task 5 finds it.
LIST = ["Gucci_bag_14", "Gucci_bag_14", "restock Gucci_bag_14", "Gucci_bag_14",
        "Barilla_pasta_1", "restock Barilla_pasta_1", "Barilla_pasta_1"]
TASKS = [line for line in LIST if not line.startswith("restock")]


def team(tmp_path: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], dict]:
    tasks_file = tmp_path / "tasks.txt"
    tasks_file.write_text("\n".join(LIST) + "\n", encoding="utf-8")
    out = tmp_path / "out.json"
    result = subprocess.run(
        [sys.executable, "-m", "coapkb", "team", "--robots", "3", "--tasks-file", str(tasks_file),
         "--misplace", "Barilla_pasta_1", "--quiet", "--record", str(out), *args],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    return result, json.loads(out.read_text(encoding="utf-8"))


def check(record: dict) -> None:
    tasks = record["tasks"]
    assert [(t["seq"], t["object"]) for t in tasks] == list(enumerate(TASKS, start=1))
    assert [t["fate"] for t in tasks] == ["assigned", "skipped", "assigned", "not-found", "assigned"], tasks
    assert tasks[1]["skip_reason"] == f"picked by {tasks[0]['assigned_to']} at task 1"
    assert all(t["agreed"] and not t["errors"] for t in tasks)
    assert set(tasks[2]["decisions"]) == {"Robot1", "Robot2", "Robot3"}  # every robot forgot its claim alike


@pytest.mark.slow
def test_a_writable_team_picks_a_restocked_object_again(tmp_path: Path) -> None:
    # Secure, as by default: the delivery is written with the operator's key.
    result, record = team(tmp_path)
    check(record)
    assert "restocked 2 objects (delivered back to their shelves in the KB and in the world)" in result.stdout


@pytest.mark.slow
def test_a_read_only_team_is_restocked_in_the_world_alone(tmp_path: Path) -> None:
    result, record = team(tmp_path, "--read-only", "--insecure")
    check(record)
    assert "restocked 2 objects (delivered back to their shelves in the world)" in result.stdout
