"""The seed paper's Query_1..Query_4, corrected, against the committed ontologies."""

from __future__ import annotations

from decimal import Decimal

import pytest
from rdflib import Literal, URIRef
from support import ROOT

from coapkb.kb.errors import KBError, UnexpectedResult
from coapkb.kb.named_queries import NAMED_QUERIES, SAFE_VALUE, NamedQuery, named_queries_for
from coapkb.kb.results import expect_ask, expect_select
from coapkb.kb.store import BACKENDS, KnowledgeBase, named_rows
from coapkb.model.results import AskResult, GraphResult, SelectResult
from coapkb.world import CAPABILITY_NS, LOCATION_NS, OBJECT_NS, Position, layout_from_row
from coapkb.world.generator import WarehouseSpec, generate
from coapkb.world.vocabulary import GRIP_TYPES

WAREHOUSE = generate(WarehouseSpec())  # what ontologies/ was generated from (checked in test_warehouse)
BAG = WAREHOUSE.product("Gucci_bag_14")


@pytest.fixture(scope="module", params=BACKENDS)
def team(request: pytest.FixtureRequest) -> dict[str, KnowledgeBase]:
    """One KB per module, as the paper's Robot1..3 each carry one."""
    return {
        name: KnowledgeBase.load([ROOT / "ontologies" / f"{name}.owl"], backend=request.param)
        for name in ("Object", "Location", "Capability")
    }


def ask(team: dict[str, KnowledgeBase], query_name: str, /, **params: str) -> list[dict]:
    return named_rows(team[NAMED_QUERIES[query_name].kb], query_name, params)


def test_query1_object_exists(team: dict[str, KnowledgeBase]) -> None:
    bag = URIRef(OBJECT_NS + "Gucci_bag_14")
    assert ask(team, "object-exists", name="Gucci_bag_14") == [
        {"object": bag, "class": URIRef(OBJECT_NS + "PersonalItems")}
    ]
    assert ask(team, "object-exists-in-class", name="Gucci_bag_14", cls="PersonalItems") == [{"object": bag}]
    assert ask(team, "object-exists-in-class", name="Gucci_bag_14", cls="Electronics") == []


def test_query2_object_location(team: dict[str, KnowledgeBase]) -> None:
    [row] = ask(team, "object-location", name="Gucci_bag_14")
    assert row["loc"] == URIRef(LOCATION_NS + "Warehouse_A")
    assert row["warehouse"] == Literal("Warehouse_A")
    placed = Position(row["aisle_no"].toPython(), row["rack_no"].toPython())
    assert placed == BAG.position
    assert row["bin_no"].toPython() == BAG.bin_no


def test_query3_object_features(team: dict[str, KnowledgeBase]) -> None:
    [row] = ask(team, "object-features", name="Gucci_bag_14")
    assert row["grip"] == URIRef(OBJECT_NS + "gripping")
    assert row["frag"].toPython() is BAG.fragile
    assert row["price"].toPython() == BAG.price
    assert row["weight"].toPython() == BAG.weight_kg
    assert row["color"] == Literal(BAG.colour)
    assert row["shape"] == URIRef(OBJECT_NS + "Shape_Gucci_bag_14")
    assert row["dim"] == Literal(BAG.dimension_text)


def test_the_pick_queries_answer_what_query_1_to_3_do_that_the_assigner_reads(team: dict[str, KnowledgeBase]) -> None:
    [exists] = ask(team, "object-exists", name="Gucci_bag_14")
    [features] = ask(team, "object-features", name="Gucci_bag_14")
    [where] = ask(team, "object-location", name="Gucci_bag_14")
    local = lambda iri: Literal(str(iri).rsplit("#", 1)[1])  # noqa: E731
    assert ask(team, "pick-facts", name="Gucci_bag_14") == [
        {"class": local(exists["class"]), "grip": local(features["grip"]), "weight": features["weight"]}
    ]
    assert ask(team, "pick-place", name="Gucci_bag_14") == [
        {k: where[k] for k in ("aisle_no", "rack_no", "bin_no")}
    ]


def test_pick_facts_names_an_object_without_features_and_none_for_a_stranger(tmp_path) -> None:
    bare = tmp_path / "Object.ttl"
    bare.write_text(
        "@prefix ns_2: <http://www.tcs.org/2018/Object#> .\n"
        "@prefix rdfs: <http://www.w3.org/2000/01/rdf-schema#> .\n"
        "ns_2:PersonalItems rdfs:subClassOf ns_2:Product .\n"
        'ns_2:Plain_box_1 a ns_2:PersonalItems ; ns_2:Product_name "Plain_box_1" .\n',
        encoding="utf-8",
    )
    kb = KnowledgeBase.load([bare])
    query = NAMED_QUERIES["pick-facts"]
    assert kb.query(query.render({"name": "Plain_box_1"})).as_dicts() == [{"class": Literal("PersonalItems")}]
    assert kb.query(query.render({"name": "Gucci_bag_15000"})).as_dicts() == []


@pytest.mark.parametrize("grip", GRIP_TYPES)
def test_query4_robots_for_grip(team: dict[str, KnowledgeBase], grip: str) -> None:
    rows = ask(team, "robots-for-grip", grip=grip)
    expected = [r for r in WAREHOUSE.robots if grip in r.can_pick]
    assert [row["robo_id"] for row in rows] == sorted(Literal(r.robot_id) for r in expected)
    by_id = {str(row["robo_id"]): row for row in rows}
    for r in expected:
        assert by_id[r.robot_id]["robots"] == URIRef(CAPABILITY_NS + r.robot_id)
        assert by_id[r.robot_id]["payload"].toPython() == r.payload_kg


@pytest.mark.parametrize("grip", GRIP_TYPES)
def test_query4_among_a_team_answers_its_robots_only(team: dict[str, KnowledgeBase], grip: str) -> None:
    """What a robot's cost model needs: its own team, an answer that does not
    grow with the warehouse's fleet; the same rows as Query_4's for them."""
    cluster = ("Robot4", "Robot5", "Robot6")
    among = ask(team, "robots-for-grip-among", grip=grip, robots=",".join(cluster))
    every = ask(team, "robots-for-grip", grip=grip)
    assert among == [row for row in every if str(row["robo_id"]) in cluster]
    specs = ask(team, "robot-specs-among", robots=",".join(cluster))
    assert specs == [row for row in ask(team, "robot-specs") if str(row["robo_id"]) in cluster]


@pytest.mark.parametrize("robots", ["", "Robot1,", "Robot1, Robot2", "Robot1,$x", ",".join(["R"] * 17)])
def test_a_list_parameter_takes_local_names_only(robots: str) -> None:
    with pytest.raises(ValueError, match="comma-separated list"):
        NAMED_QUERIES["robot-specs-among"].render({"robots": robots})


def test_unknown_product_has_no_rows(team: dict[str, KnowledgeBase]) -> None:
    for query_name in ("object-exists", "object-location", "object-features", "pick-facts", "pick-place"):
        assert ask(team, query_name, name="Gucci_bag_15000") == []
    assert ask(team, "robots-for-grip", grip="telekinesis") == []


def test_robot_positions_and_specs(team: dict[str, KnowledgeBase]) -> None:
    positions = {
        str(r["robo_id"]): Position(r["aisle_no"].toPython(), r["rack_no"].toPython())
        for r in ask(team, "robot-positions")
    }
    assert positions == {r.robot_id: r.home for r in WAREHOUSE.robots}
    profiles = {str(r["robo_id"]): r for r in ask(team, "robot-specs")}
    for r in WAREHOUSE.robots:
        p = profiles[r.robot_id]
        assert (p["payload"].toPython(), p["battery"].toPython(), p["speed"].toPython()) == (
            r.payload_kg,
            r.battery_wh,
            r.speed_m_s,
        )
        assert p["e_loaded"].toPython() == r.energy_per_m_loaded_wh
        assert p["e_pick"].toPython() == r.energy_per_pick_wh


def test_a_result_of_another_kind_than_the_caller_reads_is_a_kb_error(team: dict[str, KnowledgeBase]) -> None:
    rows = SelectResult(("x",), ((None,),))
    assert expect_select(rows, "q") is rows
    assert expect_ask(AskResult(True), "q").value is True
    with pytest.raises(UnexpectedResult, match="robot-specs: expected SELECT rows, got AskResult") as info:
        expect_select(AskResult(False), "robot-specs")
    assert isinstance(info.value, KBError)
    with pytest.raises(UnexpectedResult, match="q: expected an ASK answer, got GraphResult"):
        expect_ask(GraphResult(), "q")
    answer = team["Location"].query("ASK { ?s ?p ?o }")
    with pytest.raises(UnexpectedResult, match="ASK"):
        expect_select(answer, "ASK { ?s ?p ?o }")


def test_layout_from_the_kb(team: dict[str, KnowledgeBase]) -> None:
    [row] = ask(team, "warehouse-layout")
    layout = layout_from_row(row)
    assert layout == WAREHOUSE.layout
    assert row["aisle_length_m"].toPython() == Decimal(str(layout.aisle_length_m)).normalize()


def test_charging_docks_from_the_kb(team: dict[str, KnowledgeBase]) -> None:
    docks = ask(team, "charging-docks")
    assert [(int(r["aisle_no"]), int(r["rack_no"])) for r in docks] == [
        (d.aisle, d.rack) for d in WAREHOUSE.spec.docks
    ]
    # One per cluster of three robots, on the back cross-aisle.
    assert len(docks) == 3 and {int(r["rack_no"]) for r in docks} == {WAREHOUSE.layout.racks_per_aisle + 1}


INJECTIONS = [
    'Gucci_bag_14" } ; DROP ALL #',
    "Gucci_bag_14> <x",
    "Gucci_bag_14 . ?s ?p ?o",
    "Gucci_bag_14}",
    "a:b",
    "<http://evil/>",
    "",
    " Gucci_bag_14",
    "Gucci_bag_14\n",
    "x.",
    "1abc",
    "Gücci",
    "$name",
    "a" * 129,
]


@pytest.mark.parametrize("value", INJECTIONS)
def test_injection_rejected(value: str) -> None:
    for name in ("object-exists", "object-location", "object-features"):
        with pytest.raises(ValueError, match="local name"):
            NAMED_QUERIES[name].render({"name": value})
    with pytest.raises(ValueError):
        NAMED_QUERIES["robots-for-grip"].render({"grip": value})


def test_safe_values_accepted() -> None:
    for value in ("Gucci_bag_14", "a", "_x", "Ray-Ban_sunglasses_7", "v1.2_x", "a" * 128):
        assert SAFE_VALUE.fullmatch(value)
        assert f'"{value}"' in NAMED_QUERIES["object-exists"].render({"name": value})


def test_parameters_checked() -> None:
    q = NAMED_QUERIES["object-location"]
    with pytest.raises(ValueError, match="missing name"):
        q.render({})
    with pytest.raises(ValueError, match="unexpected grip"):
        q.render({"name": "Gucci_bag_14", "grip": "gripping"})
    with pytest.raises(ValueError, match="no parameters"):
        NAMED_QUERIES["robot-positions"].render({"name": "x"})
    with pytest.raises(ValueError):
        q.render({"name": 14})  # type: ignore[dict-item]
    assert "ns_1:Gucci_bag_14 ns_1:Available_At ?loc" in q.render({"name": "Gucci_bag_14"})


def test_registry() -> None:
    assert {
        "object-exists",
        "object-location",
        "object-features",
        "robots-for-grip",
        "robot-positions",
        "warehouse-layout",
        "charging-docks",
    } <= set(NAMED_QUERIES)
    assert {q.kb for q in NAMED_QUERIES.values()} == {"Object", "Location", "Capability"}
    obj = named_queries_for(["Object"])
    assert [q.name for q in obj] == sorted(q.name for q in NAMED_QUERIES.values() if q.kb == "Object")
    assert len(named_queries_for(["Object", "Location", "Capability"])) == len(NAMED_QUERIES)
    assert named_queries_for(["Unrelated"]) == []
    for q in NAMED_QUERIES.values():
        assert q.description and q.rt
    with pytest.raises(ValueError, match="placeholders"):
        NamedQuery("bad", "Object", ("name",), 'SELECT ?x WHERE { ?x ?p "$nmae" }', "typo")
