"""The inline fast path of KBResources: a named query known to be cheap runs
on the event loop (no thread); its first run, free SPARQL text and a query
that once ran out of time run on a thread with the time budget."""

from __future__ import annotations

import math
import threading

import pytest
from support import KB_FILES

from coapkb.kb.limits import QueryLimits
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.messages import ContentFormat, Method, Request, Status


def named(name: str) -> Request:
    return Request(Method.GET, "/kb/q/object-exists", {"name": name}, accept=ContentFormat.CBOR)


class ThreadCount:
    """Counts the query threads started while it is active."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.started = 0
        original = threading.Thread.start

        def start(thread: threading.Thread) -> None:
            if thread.name == "sparql-query":
                self.started += 1
            original(thread)

        monkeypatch.setattr(threading.Thread, "start", start)


@pytest.fixture(scope="module")
def kb() -> KnowledgeBase:
    return KnowledgeBase.load(KB_FILES)


#: A threshold no run of these queries reaches, even on a loaded machine: the tests check
#: the switch between thread and inline, not the speed (experiments/kb_load.py reports the
#: first run's time against the default threshold).
CHEAP = QueryLimits(inline_below_s=1.0)


async def test_cheap_named_query_runs_inline_after_its_first_run(kb: KnowledgeBase, monkeypatch: pytest.MonkeyPatch) -> None:
    resources = KBResources(kb, CHEAP)
    threads = ThreadCount(monkeypatch)
    first = await resources.named_query(named("Gucci_bag_14"))
    assert first.status == Status.CONTENT and threads.started == 1
    assert "object-exists" in resources.slowest_run
    names = ["Gucci_bag_1", "Gucci_bag_2", "Gucci_bag_3", "no_such_thing"]
    answers = [await resources.named_query(named(n)) for n in names]
    assert threads.started == 1  # every later (different) question ran inline
    # the same answers as the thread path gives
    fresh = KBResources(kb, QueryLimits(inline_below_s=0))
    assert [a.payload for a in answers] == [(await fresh.named_query(named(n))).payload for n in names]


async def test_free_sparql_and_slow_or_timed_out_queries_keep_their_thread(
    kb: KnowledgeBase, monkeypatch: pytest.MonkeyPatch
) -> None:
    resources = KBResources(kb, CHEAP)
    threads = ThreadCount(monkeypatch)
    text = "ASK { ?s ?p ?o }"
    for accept in (ContentFormat.CBOR, ContentFormat.JSON):
        request = Request(Method.FETCH, "/kb/sparql", payload=text.encode(), content_format=0, accept=accept)
        assert (await resources.sparql(request)).status == Status.CONTENT
    assert threads.started == 2
    resources.slowest_run["object-exists"] = math.inf  # as after a run that ran out of time
    await resources.named_query(named("Gucci_bag_14"))
    await resources.named_query(named("Gucci_bag_1"))
    assert threads.started == 4


def test_inline_threshold_must_stay_under_the_time_budget() -> None:
    with pytest.raises(ValueError, match="inline_below_s"):
        QueryLimits(time_budget_s=0.5, inline_below_s=0.5)
