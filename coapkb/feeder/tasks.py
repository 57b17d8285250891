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
lists restarted robots that are members again from this task on;
``restocked`` (optional, true) says the object was delivered back to its
shelf since the cluster last decided it (:mod:`.restock`): no robot skips
it for the earlier pick it remembers.

A task list holds, besides objects to pick, deliveries: a ``restock
OBJECT`` line puts the object back on its shelf before the next task is fed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cbor2

from ..errors import CoapkbError
from ..transport.messages import ContentFormat, Method, Request

TASKS_PATH = "/tasks"


class FeederError(CoapkbError):
    """The feeder could not feed the team: a bad tasks file, a robot that
    refused a task or never decided it, a cluster with every robot down."""


@dataclass(frozen=True)
class Restock:
    """A delivery in a task list: ``object`` back on its shelf (returned or
    new stock) before the next task is fed."""

    object: str

    def __str__(self) -> str:
        return f"restock {self.object}"


#: What a task list holds: an object to pick, or a delivery.
Entry = str | Restock


def parse_entry(text: str) -> Entry:
    """``restock OBJECT`` or an object's name."""
    word, _, rest = text.partition(" ")
    if word == "restock":
        name = rest.strip()
        if not name or " " in name:
            raise FeederError(f"{text!r}: a delivery is 'restock OBJECT', one object's name")
        return Restock(name)
    return text


def read_tasks_file(path: str | Path) -> list[Entry]:
    """One product name per line, or ``restock NAME`` (a delivery); blank
    lines and ``#`` comments ignored."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise FeederError(f"cannot read tasks file {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise FeederError(f"tasks file {path} is not UTF-8 text") from None
    tasks = [line.split("#", 1)[0].strip() for line in lines]
    try:
        return [parse_entry(t) for t in tasks if t]
    except FeederError as exc:
        raise FeederError(f"tasks file {path}: {exc}") from None


def with_restocks(names: Sequence[str]) -> list[Entry]:
    """``names``, each object after its first preceded by a delivery of it:
    a shift longer than the stock finds each object back on its shelf when
    the list comes round to it again."""
    seen: set[str] = set()
    entries: list[Entry] = []
    for name in names:
        if name in seen:
            entries.append(Restock(name))
        seen.add(name)
        entries.append(name)
    return entries


def task_count(tasks: Sequence[Entry]) -> int:
    """The tasks of a list, its deliveries left out."""
    return sum(1 for t in tasks if isinstance(t, str))


def split_tasks(tasks: Sequence[Entry], clusters: int) -> list[list[Entry]]:
    """Contiguous, near-equal shares of the tasks, in order (the seed splits
    N tasks into equal sets); a delivery goes with the task after it (or
    with the last share, at the end of the list)."""
    total = task_count(tasks)
    bounds = [round(i * total / clusters) for i in range(clusters + 1)]
    shares: list[list[Entry]] = [[] for _ in range(clusters)]
    share, seen = 0, 0
    for entry in tasks:
        while share < clusters - 1 and seen >= bounds[share + 1]:
            share += 1
        seen += isinstance(entry, str)
        shares[share].append(entry)
    return shares


def task_post(seq: int, name: str, joining: Sequence[str] = (), again: int | None = None,
              restocked: bool = False, boots: Mapping[str, int] | None = None,
              missed: Sequence[str] = (), restarted: Sequence[str] = ()) -> Request:
    """The POST of task ``seq``.  The task stream orders joins: every robot
    admits the joiners at this task, each named with the process that took
    it where ``boots`` says (a teammate takes another process for a restart).  ``again``: the task this one does
    again (its robot went down before the pick), so no robot takes the
    object for already picked; ``restocked``: the object was delivered
    back since, so no robot does either; ``missed``: robots that were to
    join at this task and did not take it (a robot that took a post naming
    them counts them out); ``restarted``: members of the cluster that ran
    again as a new process while the task was posted, which did not take it
    (the process the others count on is gone; the new one joins later)."""
    boots = boots or {}
    join = [[r, boots[r]] if boots.get(r) else r for r in joining]
    body = cbor2.dumps({"seq": seq, "object": name, **({"join": join} if join else {}),
                        **({"missed": list(missed)} if missed else {}),
                        **({"restarted": list(restarted)} if restarted else {}),
                        **({"again": again} if again is not None else {}),
                        **({"restocked": True} if restocked else {})})
    return Request(Method.POST, TASKS_PATH, payload=body, content_format=ContentFormat.CBOR)
