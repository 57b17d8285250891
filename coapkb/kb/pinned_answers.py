"""Answers pinned to a task: a question asked again for the same task is
answered as it was first.

A decision must read the same knowledge on every robot of a cluster,
though a write may land between two robots' questions: the holder they
all ask answers each question of one task alike (docs/knowledge.md, "The
world in the KB"; :meth:`~coapkb.kb.live.LiveKB.query_at`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

from ..model.results import QueryResult

__all__ = ["PINNED_ANSWERS", "PinnedAnswers"]

#: Answers kept as first given for a task: a few questions per task, and
#: no robot asks about a task hundreds of tasks old.
PINNED_ANSWERS = 1024


class PinnedAnswers:
    """The last ``kept`` answers, by task and question."""

    def __init__(self, kept: int = PINNED_ANSWERS) -> None:
        self.kept = kept
        #: (task, query) -> the answer first given for that task.
        self._answers: OrderedDict[tuple[int, str], QueryResult] = OrderedDict()

    def answer(self, task: int, sparql: str, ask: Callable[[str], QueryResult]) -> QueryResult:
        """The answer first given to ``sparql`` for ``task``; ``ask``-ed now if none is kept."""
        key = (task, sparql)
        kept = self._answers.get(key)
        if kept is not None:
            self._answers.move_to_end(key)
            return kept
        answer = ask(sparql)
        self._answers[key] = answer
        while len(self._answers) > self.kept:
            self._answers.popitem(last=False)
        return answer
