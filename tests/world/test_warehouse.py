"""The warehouse model: deterministic generation, geometry, robot clusters, OWL output."""

from __future__ import annotations

import io
from decimal import Decimal
from pathlib import Path

import pytest
import rdflib
from hypothesis import given, settings
from hypothesis import strategies as st
from rdflib.namespace import OWL, RDF, RDFS
from support import ROOT

from coapkb.world import (
    CAPABILITY_NS,
    LOCATION_NS,
    OBJECT_NS,
    ONTOLOGIES,
    Layout,
    Position,
    layout_from_row,
    travel_distance,
)
from coapkb.world.generator import WarehouseSpec, cluster_grip_coverage, generate
from coapkb.world.ontologies import build_graphs, ontology_bytes, write_ontologies
from coapkb.world.vocabulary import GRIP_COMPONENT, GRIP_TYPES, PRODUCT_CLASSES

SMALL = WarehouseSpec(products=200, aisles=4, racks_per_aisle=6, bins_per_rack=3, seed=3)


def test_generation_is_byte_identical_for_equal_specs(tmp_path: Path) -> None:
    first = ontology_bytes(SMALL)
    assert first == ontology_bytes(WarehouseSpec(**SMALL.__dict__))
    written = write_ontologies(SMALL, tmp_path)
    assert {name: path.read_bytes() for name, path in written.items()} == first
    assert ontology_bytes(WarehouseSpec(**{**SMALL.__dict__, "seed": 4}))["Object"] != first["Object"]


def test_committed_ontologies_are_the_default_spec() -> None:
    """ontologies/ is what `tools/gen_warehouse.py` writes by default: regenerate after changing the generator."""
    expected = ontology_bytes(WarehouseSpec())
    for name, data in expected.items():
        assert (ROOT / "ontologies" / f"{name}.owl").read_bytes() == data, f"ontologies/{name}.owl is stale"


def test_rdfxml_and_graphs_hold_the_same_triples() -> None:
    graphs = build_graphs(SMALL)
    for name, data in ontology_bytes(SMALL).items():
        parsed = rdflib.Graph()
        parsed.parse(io.BytesIO(data), format="xml")
        assert set(parsed) == set(graphs[name]), name


def test_ontologies_are_owl2_with_declarations() -> None:
    for name, graph in build_graphs(SMALL).items():
        iri, ns, _ = ONTOLOGIES[name]
        assert (rdflib.URIRef(iri), RDF.type, OWL.Ontology) in graph
        declared_props = set(graph.subjects(RDF.type, OWL.ObjectProperty)) | set(
            graph.subjects(RDF.type, OWL.DatatypeProperty)
        )
        classes = set(graph.subjects(RDF.type, OWL.Class))
        for prop in declared_props:
            assert graph.value(prop, RDFS.domain) in classes, prop
            assert graph.value(prop, RDFS.range) is not None, prop
        individuals = set(graph.subjects(RDF.type, OWL.NamedIndividual))
        for s, p, o in graph:
            if s in individuals and p != RDF.type:
                assert p in declared_props, f"{name}: undeclared property {p}"
            if s in individuals and p == RDF.type and o != OWL.NamedIndividual:
                assert o in classes, f"{name}: undeclared class {o}"
            assert str(s).startswith(ns) or str(s) == iri, s
    obj = build_graphs(SMALL)["Object"]
    for cls in PRODUCT_CLASSES:
        assert (rdflib.URIRef(OBJECT_NS + cls), RDFS.subClassOf, rdflib.URIRef(OBJECT_NS + "Product")) in obj


def test_products() -> None:
    wh = generate(WarehouseSpec())
    names = [p.name for p in wh.products]
    assert len(names) == len(set(names)) == 1000
    assert {p.product_class for p in wh.products} == set(PRODUCT_CLASSES)
    bag = wh.product("Gucci_bag_14")
    assert bag.product_class == "PersonalItems" and bag.grip == "gripping"
    for p in wh.products:
        assert Decimal("0.1") <= p.weight_kg <= Decimal("25")
        assert wh.layout.contains(p.position) and 1 <= p.position.rack <= wh.spec.racks_per_aisle
        assert 1 <= p.bin_no <= wh.spec.bins_per_rack
        assert p.grip in GRIP_TYPES
        assert p.dimension_text.endswith(" cm")


@pytest.mark.parametrize("products", [1, 5, 13, 14, 15])
def test_gucci_bag_always_present(products: int) -> None:
    wh = generate(WarehouseSpec(products=products))
    assert len(wh.products) == products
    assert wh.product("Gucci_bag_14").grip == "gripping"


# -- geometry ---------------------------------------------------------------

LAYOUT = Layout(aisles=10, racks_per_aisle=25, rack_length_m=1.2, aisle_spacing_m=3.5, cross_aisle_margin_m=2.0)
positions = st.builds(Position, st.integers(1, LAYOUT.aisles), st.integers(0, LAYOUT.racks_per_aisle + 1))


def test_distance_examples() -> None:
    # Same aisle: along it, one rack bay per 1.2 m.
    assert travel_distance(Position(3, 5), Position(3, 8), LAYOUT) == pytest.approx(3.6)
    # Rack 1 is 2.0 + 0.6 = 2.6 m from the front cross-aisle; aisles 1 and 3 are 7 m apart.
    assert travel_distance(Position(1, 1), Position(3, 1), LAYOUT) == pytest.approx(2.6 + 7.0 + 2.6)
    # Near the back, going round the back is shorter: rack 25 is 2.6 m from it.
    assert travel_distance(Position(1, 25), Position(2, 25), LAYOUT) == pytest.approx(2.6 + 3.5 + 2.6)
    # Cross-aisle junctions.
    assert travel_distance(Position(1, 0), Position(4, 0), LAYOUT) == pytest.approx(10.5)
    assert travel_distance(Position(2, 0), Position(2, 26), LAYOUT) == pytest.approx(LAYOUT.aisle_length_m)
    assert LAYOUT.aisle_length_m == pytest.approx(34.0)


@settings(max_examples=300, deadline=None)
@given(positions, positions, positions)
def test_distance_is_a_metric(a: Position, b: Position, c: Position) -> None:
    d = travel_distance
    assert d(a, a, LAYOUT) == 0
    assert d(a, b, LAYOUT) == pytest.approx(d(b, a, LAYOUT))
    assert d(a, b, LAYOUT) > 0 if a != b else True
    assert d(a, c, LAYOUT) <= d(a, b, LAYOUT) + d(b, c, LAYOUT) + 1e-9
    (xa, ya), (xb, yb) = LAYOUT.xy(a), LAYOUT.xy(b)
    straight = abs(xa - xb) + abs(ya - yb)
    assert d(a, b, LAYOUT) >= straight - 1e-9  # never shorter than Manhattan
    if a.aisle == b.aisle:
        assert d(a, b, LAYOUT) == pytest.approx(abs(ya - yb))
    else:  # leaving the aisle costs at least the way to the nearer cross-aisle and back
        assert d(a, b, LAYOUT) <= abs(xa - xb) + ya + yb + 1e-9


def test_distance_rejects_positions_off_the_map() -> None:
    with pytest.raises(ValueError):
        travel_distance(Position(0, 1), Position(1, 1), LAYOUT)
    with pytest.raises(ValueError):
        travel_distance(Position(1, 1), Position(1, LAYOUT.racks_per_aisle + 2), LAYOUT)


def test_layout_from_kb_row() -> None:
    row = {
        "aisles": rdflib.Literal(10),
        "racks_per_aisle": rdflib.Literal(25),
        "rack_length_m": rdflib.Literal(Decimal("1.2")),
        "aisle_spacing_m": rdflib.Literal(Decimal("3.5")),
        "cross_aisle_margin_m": rdflib.Literal(Decimal("2")),
    }
    assert layout_from_row(row) == WarehouseSpec().layout
    with pytest.raises(ValueError, match="aisles"):
        layout_from_row({})


# -- robots -----------------------------------------------------------------


@pytest.mark.parametrize("robots", [1, 2, 3, 4, 5, 9, 12])
def test_every_grip_is_covered_twice_per_cluster(robots: int) -> None:
    wh = generate(WarehouseSpec(products=300, robots=robots))
    assert [r.robot_id for r in wh.robots] == [f"Robot{i}" for i in range(1, robots + 1)]
    for cluster, counts in cluster_grip_coverage(wh.robots).items():
        size = sum(1 for r in wh.robots if r.cluster == cluster)
        for grip in wh.grip_types_used():
            assert counts[grip] >= min(2, size), (cluster, grip, counts)
    for r in wh.robots:
        for grip in r.can_pick:
            assert GRIP_COMPONENT[grip] in r.components
        assert wh.layout.contains(r.home)
        assert r.payload_kg >= 25  # any single product fits


def test_default_team() -> None:
    wh = generate(WarehouseSpec())
    assert len(wh.robots) == 9 and wh.grip_types_used() == set(GRIP_TYPES)
    assert any("gripping" in r.can_pick for r in wh.robots if r.cluster == 0)
    r = wh.robots[0]
    assert r.travel_energy_wh(100.0) == pytest.approx(100 * float(r.energy_per_m_empty_wh))
    assert r.travel_energy_wh(100.0, float(r.payload_kg)) == pytest.approx(100 * float(r.energy_per_m_loaded_wh))
    with pytest.raises(ValueError):
        r.travel_energy_wh(1.0, float(r.payload_kg) + 1)


def test_capability_and_location_graphs_describe_the_robots() -> None:
    wh = generate(SMALL)
    graphs = build_graphs(SMALL)
    cap, loc = graphs["Capability"], graphs["Location"]
    for r in wh.robots:
        node = rdflib.URIRef(CAPABILITY_NS + r.robot_id)
        grips = cap.objects(node, rdflib.URIRef(CAPABILITY_NS + "Can_Pick"))
        assert {str(o).removeprefix(CAPABILITY_NS) for o in grips} == set(r.can_pick)
        assert cap.value(node, rdflib.URIRef(CAPABILITY_NS + "Robot_payload")).toPython() == r.payload_kg
        lnode = rdflib.URIRef(LOCATION_NS + r.robot_id)
        assert loc.value(lnode, rdflib.URIRef(LOCATION_NS + "Robot_aisle_no")).toPython() == r.home.aisle
        assert loc.value(lnode, rdflib.URIRef(LOCATION_NS + "Robot_rack_no")).toPython() == r.home.rack


def test_spec_validation() -> None:
    with pytest.raises(ValueError):
        WarehouseSpec(products=0)
    with pytest.raises(ValueError):
        WarehouseSpec(rack_length_m=0)
    with pytest.raises(ValueError):
        WarehouseSpec(warehouse_name="Warehouse A")
