"""The task stream: the list a feeder reads, how it is shared between
clusters, and the request that gives a robot one task.

``POST /tasks`` on a robot takes one task, in CBOR (content format 60) or
JSON (50)::

    {"seq": 1, "object": "Gucci_bag_14"}                  # task 1: pick this object
    {"seq": 7, "object": "Bosch_rug_837", "join": ["Robot2"]}

``seq`` numbers a cluster's tasks 1, 2, 3, ... and every robot of the
cluster takes them strictly in that order (4.09 for a gap; a repeated post
of a task already taken is answered 2.04 again and not taken twice);
``object`` is a product's local name in the Object KB; ``join`` (optional)
lists restarted robots that are members again from this task on.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cbor2

from ..errors import CoapkbError
from ..transport.messages import ContentFormat, Method, Request

TASKS_PATH = "/tasks"


class FeederError(CoapkbError):
    """The feeder could not feed the team: a bad tasks file, a robot that
    refused a task or never decided it, a cluster with every robot down."""


def read_tasks_file(path: str | Path) -> list[str]:
    """One product name per line; blank lines and ``#`` comments ignored."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise FeederError(f"cannot read tasks file {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise FeederError(f"tasks file {path} is not UTF-8 text") from None
    tasks = [line.split("#", 1)[0].strip() for line in lines]
    return [t for t in tasks if t]


def split_tasks(tasks: Sequence[str], clusters: int) -> list[list[str]]:
    """Contiguous, near-equal shares, in order (the seed splits N tasks into equal sets)."""
    bounds = [round(i * len(tasks) / clusters) for i in range(clusters + 1)]
    return [list(tasks[bounds[i] : bounds[i + 1]]) for i in range(clusters)]


def task_post(seq: int, name: str, joining: Sequence[str] = (), again: int | None = None) -> Request:
    """The POST of task ``seq``.  The task stream orders joins: every robot
    admits the joiners at this task.  ``again``: the task this one does
    again (its robot went down before the pick), so no robot takes the
    object for already picked."""
    body = cbor2.dumps({"seq": seq, "object": name, **({"join": list(joining)} if joining else {}),
                        **({"again": again} if again is not None else {})})
    return Request(Method.POST, TASKS_PATH, payload=body, content_format=ContentFormat.CBOR)
