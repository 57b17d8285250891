"""KnowledgeBase: loading, both backends agreeing, limits, and errors."""

from __future__ import annotations

import gc
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from rdflib import BNode, Literal, URIRef
from rdflib import namespace as rdfns
from support import ROOT

from coapkb.kb.errors import (
    FeatureRefused,
    KBError,
    KBLoadError,
    QueryRefused,
    QuerySyntaxError,
    QueryTimeout,
    UpdateRefused,
)
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.store import BACKENDS, KnowledgeBase
from coapkb.model.results import AskResult, GraphResult, SelectResult
from coapkb.world import OBJECT_NS
from coapkb.world.generator import WarehouseSpec
from coapkb.world.ontologies import build_graphs

KB_FILES = [ROOT / "ontologies" / f"{n}.owl" for n in ("Object", "Location", "Capability")]
PARAMS = {"name": "Gucci_bag_14", "grip": "gripping", "cls": "PersonalItems", "robots": "Robot1,Robot2,Robot3"}


@pytest.fixture(scope="module")
def kbs() -> dict[str, KnowledgeBase]:
    """The three committed modules in one KB, per backend."""
    return {backend: KnowledgeBase.load(KB_FILES, backend=backend) for backend in BACKENDS}


@pytest.fixture(scope="module")
def small_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The Capability module of a small warehouse as RDF/XML, Turtle and N-Triples."""
    out = tmp_path_factory.mktemp("kb")
    graph = build_graphs(WarehouseSpec(products=20))["Capability"]
    files = {"owl": out / "Capability.owl", "ttl": out / "Capability.ttl", "nt": out / "Capability.nt"}
    graph.serialize(files["owl"], format="xml")
    graph.serialize(files["ttl"], format="turtle")
    graph.serialize(files["nt"], format="nt", encoding="utf-8")
    return files


def test_kb_attributes(kbs: dict[str, KnowledgeBase]) -> None:
    ox, rl = kbs["oxigraph"], kbs["rdflib"]
    for kb in (ox, rl):
        assert kb.names == ("Object", "Location", "Capability")
        assert kb.triple_count > 20_000
        assert len(kb.etag) == 8
        assert kb.prefixes["obj"] == "http://www.tcs.org/2018/Object#"
        assert kb.prefixes["loc"] == "http://www.tcs.org/2018/Location#"
        assert kb.prefixes["cap"] == "http://www.tcs.org/2018/Capability#"
        assert "" not in kb.prefixes
    assert ox.triple_count == rl.triple_count
    assert ox.prefixes == rl.prefixes
    assert ox.etag != rl.etag  # same files, different backend: answers may differ in form


@pytest.mark.parametrize("suffix", ["owl", "ttl", "nt"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_loads_each_format(small_files: dict[str, Path], suffix: str, backend: str) -> None:
    kb = KnowledgeBase.load([small_files[suffix]], backend=backend)
    reference = KnowledgeBase.load([small_files["owl"]], backend="oxigraph")
    assert kb.names == ("Capability",)
    assert kb.triple_count == reference.triple_count
    query = NAMED_QUERIES["robots-for-grip"].render({"grip": "lifting"})
    assert kb.query(query) == reference.query(query)
    if suffix == "ttl":
        assert kb.prefixes["cap"] == "http://www.tcs.org/2018/Capability#"


def test_etag_follows_content(tmp_path: Path, small_files: dict[str, Path]) -> None:
    path = tmp_path / "Capability.ttl"
    path.write_bytes(small_files["ttl"].read_bytes())
    first = KnowledgeBase.load([path]).etag
    assert KnowledgeBase.load([path]).etag == first
    path.write_bytes(small_files["ttl"].read_bytes() + b"\n<urn:a> <urn:b> <urn:c> .\n")
    assert KnowledgeBase.load([path]).etag != first


@pytest.mark.parametrize("name", sorted(NAMED_QUERIES))
def test_backends_agree_on_named_queries(kbs: dict[str, KnowledgeBase], name: str) -> None:
    query = NAMED_QUERIES[name]
    text = query.render({p: PARAMS[p] for p in query.params})
    ox, rl = kbs["oxigraph"].query(text), kbs["rdflib"].query(text)
    assert isinstance(ox, SelectResult) and ox.rows
    assert ox.variables == rl.variables
    assert sorted(ox.rows) == sorted(rl.rows)  # only ordered queries need equal order
    if "ORDER BY" in text:
        assert ox.rows == rl.rows


def test_backends_agree_on_other_forms(kbs: dict[str, KnowledgeBase]) -> None:
    ox, rl = kbs["oxigraph"], kbs["rdflib"]
    star = (
        "PREFIX cap: <http://www.tcs.org/2018/Capability#>\n"
        "SELECT * WHERE { ?r cap:Robot_Id ?id . OPTIONAL { ?r cap:Nothing ?none } ?r cap:Robot_payload ?kg }"
    )
    a, b = ox.query(star), rl.query(star)
    assert a.variables == b.variables == ("id", "kg", "none", "r")  # SELECT *: sorted by name
    assert sorted(a.rows, key=str) == sorted(b.rows, key=str)
    assert all(row[2] is None for row in a.rows)  # unbound -> None
    ask = "PREFIX obj: <http://www.tcs.org/2018/Object#>\nASK { obj:Gucci_bag_14 obj:can_be_picked_by obj:gripping }"
    assert ox.query(ask) == rl.query(ask) == AskResult(True)
    construct = (
        "PREFIX obj: <http://www.tcs.org/2018/Object#>\n"
        "CONSTRUCT { ?p obj:grip ?g } WHERE { ?p obj:can_be_picked_by ?g }"
    )
    c1, c2 = ox.query(construct, row_limit=5000), rl.query(construct, row_limit=5000)
    assert isinstance(c1, GraphResult) and len(c1.triples) == 1000
    assert set(c1.triples) == set(c2.triples)
    describe = "DESCRIBE <http://www.tcs.org/2018/Object#Gucci_bag_14>"
    assert set(ox.query(describe).triples) == set(rl.query(describe).triples)


def test_terms_keep_datatype_and_language(kbs: dict[str, KnowledgeBase], tmp_path: Path) -> None:
    text = NAMED_QUERIES["object-features"].render({"name": "Gucci_bag_14"})
    for kb in kbs.values():
        row = kb.query(text).as_dicts()[0]
        assert row["frag"].datatype == rdfns.XSD.boolean and row["frag"].toPython() is False
        assert row["price"].datatype == rdfns.XSD.decimal
        assert row["color"] == Literal(str(row["color"]))  # plain (xsd:string) literal
        assert isinstance(row["grip"], URIRef) and row["grip"] == URIRef(OBJECT_NS + "gripping")
    path = tmp_path / "mixed.ttl"
    path.write_text(
        '<urn:s> <urn:label> "Kiste"@de , "box" , "7"^^<http://www.w3.org/2001/XMLSchema#integer> ; '
        "<urn:blank> [ <urn:p> 1 ] .\n"
    )
    rows = {}
    for backend in BACKENDS:
        result = KnowledgeBase.load([path], backend=backend).query("SELECT ?o WHERE { <urn:s> <urn:label> ?o }")
        rows[backend] = set(result.rows)
        blank = KnowledgeBase.load([path], backend=backend).query("SELECT ?b WHERE { <urn:s> <urn:blank> ?b }")
        assert isinstance(blank.rows[0][0], BNode)
    assert (
        rows["oxigraph"]
        == rows["rdflib"]
        == {
            (Literal("Kiste", lang="de"),),
            (Literal("box"),),
            (Literal("7", datatype=rdfns.XSD.integer),),
        }
    )


@pytest.mark.parametrize("backend", BACKENDS)
def test_row_limit_sets_truncated(kbs: dict[str, KnowledgeBase], backend: str) -> None:
    kb = kbs[backend]
    text = "PREFIX cap: <http://www.tcs.org/2018/Capability#>\nSELECT ?r WHERE { ?r cap:Robot_Id ?id }"
    assert len(kb.query(text).rows) == 9
    five = kb.query(text, row_limit=5)
    assert len(five.rows) == 5 and five.truncated
    nine = kb.query(text, row_limit=9)
    assert len(nine.rows) == 9 and not nine.truncated
    construct = "CONSTRUCT { ?s ?p ?o } WHERE { ?s ?p ?o }"
    graph = kb.query(construct, row_limit=10)
    assert len(graph.triples) == 10 and graph.truncated


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.timeout(60)  # unbudgeted, the query runs for days
def test_time_budget_stops_an_expensive_query(kbs: dict[str, KnowledgeBase], backend: str) -> None:
    cross_join = "SELECT * WHERE { ?a ?b ?c . ?d ?e ?f . ?g ?h ?i }"  # ~2e13 rows
    with pytest.raises(QueryTimeout) as info:
        kbs[backend].query(cross_join, row_limit=10**12, time_budget_s=0.05)
    assert info.value.budget_s == 0.05 and info.value.rows > 0
    assert "time budget" in str(info.value)


def test_a_query_stopped_on_a_worker_thread_leaves_no_result_to_another(kbs: dict[str, KnowledgeBase]) -> None:
    """Oxigraph's results may be freed only on the thread that made them: a
    query stopped by its budget on a worker thread (as the server runs
    SPARQL text) drops them there, not in a cycle through its exception
    that the collector frees on another thread ("PyQuerySolutions is
    unsendable", printed by a benchmark's robots)."""
    unraisable: list[BaseException | None] = []
    hook, sys.unraisablehook = sys.unraisablehook, lambda u: unraisable.append(u.exc_value)
    try:
        errors = []
        with ThreadPoolExecutor(1) as pool:
            for _ in range(5):
                job = pool.submit(kbs["oxigraph"].query, "SELECT * WHERE { ?a ?b ?c . ?d ?e ?f }",
                                  row_limit=10**9, time_budget_s=1e-4)
                errors.append(job.exception())
        assert all(isinstance(e, QueryTimeout) for e in errors)
        errors.clear()
        gc.collect()
    finally:
        sys.unraisablehook = hook
    assert unraisable == []


@pytest.mark.parametrize("backend", BACKENDS)
def test_syntax_error_has_position(kbs: dict[str, KnowledgeBase], backend: str) -> None:
    text = "PREFIX a: <http://a#>\nSELECT ?x\nWHERE ?x a:b ?y"  # braces missing, as in the paper
    with pytest.raises(QuerySyntaxError) as info:
        kbs[backend].query(text)
    err = info.value
    assert (err.line, err.column) == (3, 7)
    assert str(err).startswith("line 3, column 7: ")
    # The paper's quoted local name is rejected too.
    with pytest.raises(QuerySyntaxError):
        kbs[backend].query("PREFIX ns_1: <http://x#>\nSELECT ?a WHERE { ns_1:'Gucci_bag_14' ns_1:b ?a }")


@pytest.mark.parametrize("backend", BACKENDS)
def test_undeclared_prefix_is_named(kbs: dict[str, KnowledgeBase], backend: str) -> None:
    with pytest.raises(QuerySyntaxError) as info:
        kbs[backend].query("SELECT ?x WHERE {\n  ?x foo:bar ?y }")
    assert "foo" in str(info.value) and info.value.line == 2


UPDATES = {
    "INSERT DATA": "PREFIX a: <http://a#>\nINSERT DATA { a:s a:p a:o }",
    "DELETE WHERE": "DELETE WHERE { ?s ?p ?o }",
    "DELETE/INSERT": "# rename\nDELETE { ?s ?p ?o } INSERT { ?s ?p 1 } WHERE { ?s ?p ?o }",
    "LOAD": "LOAD <http://example.org/evil.ttl>",
    "CLEAR": "CLEAR ALL",
    "DROP": "DROP DEFAULT",
    "CREATE": "CREATE GRAPH <urn:g>",
    "INSERT": "INSERT DATA { <urn:a> <urn:b> }",  # malformed, but clearly an update
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("operation", sorted(UPDATES))
def test_update_refused(kbs: dict[str, KnowledgeBase], backend: str, operation: str) -> None:
    kb = kbs[backend]
    before = kb.triple_count
    with pytest.raises(UpdateRefused) as info:
        kb.query(UPDATES[operation])
    assert operation in str(info.value) and "read-only" in str(info.value)
    assert isinstance(info.value, QueryRefused) and isinstance(info.value, KBError)
    assert kb.query("ASK { ?s ?p ?o }") == AskResult(True)
    assert kb.triple_count == before


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(
    "text, feature",
    [
        ("SELECT * WHERE { SERVICE <http://127.0.0.1:1/sparql> { ?s ?p ?o } }", "SERVICE"),
        ("select * where { service silent <http://127.0.0.1:1/sparql> { ?s ?p ?o } }", "SERVICE"),
        ("SELECT * FROM <http://127.0.0.1:1/data.ttl> WHERE { ?s ?p ?o }", "FROM"),
        ("SELECT * FROM NAMED <http://127.0.0.1:1/g> WHERE { GRAPH ?g { ?s ?p ?o } }", "FROM"),
    ],
)
def test_remote_fetches_refused(kbs: dict[str, KnowledgeBase], backend: str, text: str, feature: str) -> None:
    """Both engines would fetch these IRIs over HTTP on a network client's behalf."""
    with pytest.raises(FeatureRefused) as info:
        kbs[backend].query(text)
    assert info.value.feature == feature and isinstance(info.value, QueryRefused)


@pytest.mark.parametrize("backend", BACKENDS)
def test_keywords_inside_names_and_strings_are_fine(kbs: dict[str, KnowledgeBase], backend: str) -> None:
    text = (
        "PREFIX service: <http://www.tcs.org/2018/Capability#>\n"
        "# FROM here on, no SERVICE\n"
        'SELECT ?from WHERE { ?from service:Robot_Id ?id FILTER(?id != "SERVICE FROM") }'
    )
    assert len(kbs[backend].query(text).rows) == 9


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_files(tmp_path: Path, backend: str) -> None:
    broken = tmp_path / "Broken.owl"
    broken.write_text('<?xml version="1.0"?>\n<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n<oops')
    with pytest.raises(KBLoadError) as info:
        KnowledgeBase.load([broken], backend=backend)
    assert info.value.path == str(broken) and str(broken) in str(info.value) and info.value.message
    bad_ttl = tmp_path / "Bad.ttl"
    bad_ttl.write_text("<urn:a> <urn:b> .\n")
    with pytest.raises(KBLoadError, match=r"Bad\.ttl"):
        KnowledgeBase.load([bad_ttl], backend=backend)
    with pytest.raises(KBLoadError, match=r"Missing\.owl"):
        KnowledgeBase.load([tmp_path / "Missing.owl"], backend=backend)
    odd = tmp_path / "data.xyz"
    odd.write_text("")
    with pytest.raises(KBLoadError, match="unknown RDF format"):
        KnowledgeBase.load([odd], backend=backend)


def test_load_arguments() -> None:
    with pytest.raises(ValueError, match="backend"):
        KnowledgeBase.load(KB_FILES, backend="sqlite")
    with pytest.raises(ValueError):
        KnowledgeBase.load([])


def test_rdflib_reuses_prepared_queries(kbs: dict[str, KnowledgeBase], monkeypatch: pytest.MonkeyPatch) -> None:
    """Parsing costs rdflib ~3 ms a query; a repeated query must not pay it again."""
    from rdflib.plugins.sparql import parser

    calls = []
    real = parser.parseQuery
    monkeypatch.setattr(parser, "parseQuery", lambda text: calls.append(text) or real(text))
    kb = kbs["rdflib"]
    text = NAMED_QUERIES["object-location"].render({"name": "Puma_tshirt_999"})
    results = [kb.query(text) for _ in range(5)]
    assert calls == [text]
    assert all(r == results[0] for r in results)
