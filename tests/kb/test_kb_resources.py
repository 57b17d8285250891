"""KBResources on its query threads: what a failed query leaves behind."""

from __future__ import annotations

import gc
import sys

import pytest
from support import KB_FILES

from coapkb.kb.limits import QueryLimits
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.messages import Method, Request, Status
from coapkb.transport.router import Router


@pytest.fixture(scope="module")
def kb() -> KnowledgeBase:
    return KnowledgeBase.load(KB_FILES)


#: Found by fuzzing: a query that failed on its thread (triple terms in a
#: CONSTRUCT) or ran out of time brought its exception, and with the
#: traceback pyoxigraph's result iterator, to the event loop; pyo3 refuses
#: to drop that on another thread, prints "unsendable ... dropped on another
#: thread" and leaks it, once per such query.
FAILING = {
    "triple-terms": "CONSTRUCT { ?s ?p ?o~ } WHERE { ?s ?p ?o } LIMIT 1",
    "select-timeout": "SELECT * WHERE { ?a ?b ?c . ?d ?e ?f . ?g ?h ?i }",
    "construct-timeout": "CONSTRUCT { ?a ?b ?i } WHERE { ?a ?b ?c . ?d ?e ?f . ?g ?h ?i }",
}


@pytest.mark.parametrize("text", FAILING.values(), ids=FAILING.keys())
async def test_a_failed_query_leaves_nothing_for_the_event_loop_to_drop(
    kb: KnowledgeBase, text: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    unraisable: list[str] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: unraisable.append(str(u.exc_value)))
    router = Router()
    KBResources(kb, QueryLimits(row_limit=10**9, time_budget_s=0.2, inline_below_s=0.0)).mount(router)
    answer = await router.handle(Request(Method.FETCH, "/kb/sparql", payload=text.encode()))
    assert answer.status in (Status.BAD_REQUEST, Status.SERVICE_UNAVAILABLE), answer
    del answer
    gc.collect()
    assert not unraisable
