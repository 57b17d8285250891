"""The warehouse the robot team works in, and its three knowledge bases.

The seed paper's scenario (Sec. III-B) is a warehouse whose objects sit in
racks along aisles; robots navigate the aisles to pick them.  This module
is the single source of truth for that world:

* the geometry the Task Assigner's cost function needs (:class:`Layout`,
  :class:`Position`, :func:`travel_distance`);
* a deterministic generator (:func:`generate`) of products and robots from a
  :class:`WarehouseSpec` -- the same spec always yields the same warehouse,
  because all randomness comes from one ``random.Random(spec.seed)``;
* the three OWL 2 ontologies the robots carry (``Object.owl``,
  ``Location.owl``, ``Capability.owl``), as rdflib graphs
  (:func:`build_graphs`) or as byte-stable RDF/XML (:func:`ontology_bytes`,
  :func:`write_ontologies`).

Geometry
--------
Aisles are parallel corridors running "north" (+y).  Aisle ``a`` (1-based)
has its centre line at ``x = (a - 1) * aisle_spacing_m``.  Each aisle is
lined with ``racks_per_aisle`` rack bays of ``rack_length_m`` each, numbered
1.. from the front.  A front cross-aisle runs along ``y = 0`` and a back
cross-aisle along ``y = aisle_length_m``; between a cross-aisle's centre line
and the first/last rack bay there are ``cross_aisle_margin_m`` metres.  The
pick point of rack ``r`` is the middle of its bay::

    y(r) = cross_aisle_margin_m + (r - 0.5) * rack_length_m      (1 <= r <= R)

and, so robots can park on the cross-aisles, rack ``0`` is the aisle's
junction with the front cross-aisle (``y = 0``) and rack ``R + 1`` its
junction with the back one (``y = aisle_length_m``).

Travel is restricted to that aisle graph: within one aisle a robot moves
along it; between aisles it leaves by the front or the back cross-aisle,
whichever is shorter (see :func:`travel_distance`).  The constants are
stored in ``Location.owl`` on the warehouse individual so that a robot that
only has the KB can rebuild the :class:`Layout` (see :func:`layout_from_row`).
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from collections.abc import Iterable, Iterator, Mapping
from xml.sax.saxutils import escape, quoteattr

import rdflib
from rdflib.namespace import OWL, RDF, RDFS, XSD

# --------------------------------------------------------------------------
# Vocabulary

OBJECT_NS = "http://www.tcs.org/2018/Object#"
LOCATION_NS = "http://www.tcs.org/2018/Location#"
CAPABILITY_NS = "http://www.tcs.org/2018/Capability#"

#: KB name -> (ontology IRI, namespace, conventional prefix).
ONTOLOGIES: dict[str, tuple[str, str, str]] = {
    "Object": ("http://www.tcs.org/2018/Object", OBJECT_NS, "obj"),
    "Location": ("http://www.tcs.org/2018/Location", LOCATION_NS, "loc"),
    "Capability": ("http://www.tcs.org/2018/Capability", CAPABILITY_NS, "cap"),
}

PRODUCT_CLASSES: tuple[str, ...] = ("PersonalItems", "Electronics", "Grocery", "Apparel", "HomeGoods")

#: How an object can be picked up (Object.owl ``can_be_picked_by``) and what a
#: robot can do (Capability.owl ``Can_Pick``): the same local names in both.
GRIP_TYPES: tuple[str, ...] = ("gripping", "grasping", "suction", "lifting")

#: The hardware component each grip type needs.
GRIP_COMPONENT: dict[str, str] = {
    "gripping": "gripper",  # parallel-jaw gripper closing on the object's body
    "grasping": "hand",  # multi-finger hand taking a handle or a delicate item
    "suction": "suction_cup",  # flat, sealed surfaces: boxes, cases
    "lifting": "fork",  # heavy or bulky items lifted from below
}

#: Every robot drives and localises; arm-based grips also need an arm.
BASE_COMPONENTS: tuple[str, ...] = ("wheels", "lidar", "camera")
ARM_GRIPS = frozenset({"gripping", "grasping", "suction"})

#: Grip sets of the three robots of a full cluster.  Each grip type appears
#: in exactly two of them, so every cluster of three robots can still pick
#: everything when one of its robots is busy or down.
CLUSTER_ARCHETYPES: tuple[tuple[str, ...], ...] = (
    ("gripping", "grasping"),
    ("gripping", "suction", "lifting"),
    ("grasping", "suction", "lifting"),
)
CLUSTER_SIZE = 3

#: The seed paper's example object (Sec. III-D): always generated.
GUCCI_BAG = "Gucci_bag_14"
GUCCI_BAG_SERIAL = 14


# --------------------------------------------------------------------------
# Geometry


@dataclass(frozen=True, order=True)
class Position:
    """A place on the aisle graph: an aisle and a rack bay along it.

    ``rack`` 0 and ``racks_per_aisle + 1`` are the aisle's junctions with
    the front and back cross-aisles.  Using the KB's own integers
    (``Inventory_aisle_no``/``Inventory_rack_no``, ``Robot_aisle_no``/
    ``Robot_rack_no``) means a cost function needs no conversion.
    """

    aisle: int
    rack: int


@dataclass(frozen=True)
class Layout:
    """The geometry of the aisle graph, in metres (see the module docstring)."""

    aisles: int
    racks_per_aisle: int
    rack_length_m: float = 1.2
    aisle_spacing_m: float = 3.5
    cross_aisle_margin_m: float = 2.0

    def __post_init__(self) -> None:
        if self.aisles < 1 or self.racks_per_aisle < 1:
            raise ValueError(f"need at least one aisle and one rack, got {self.aisles}x{self.racks_per_aisle}")
        for name in ("rack_length_m", "aisle_spacing_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.cross_aisle_margin_m < 0:
            raise ValueError(f"cross_aisle_margin_m must be >= 0, got {self.cross_aisle_margin_m}")

    @property
    def aisle_length_m(self) -> float:
        """Distance between the front and back cross-aisle centre lines."""
        return 2 * self.cross_aisle_margin_m + self.racks_per_aisle * self.rack_length_m

    def contains(self, p: Position) -> bool:
        return 1 <= p.aisle <= self.aisles and 0 <= p.rack <= self.racks_per_aisle + 1

    def xy(self, p: Position) -> tuple[float, float]:
        """Metric coordinates of a position (x across aisles, y along them)."""
        if not self.contains(p):
            raise ValueError(
                f"{p} is outside the warehouse (aisles 1..{self.aisles}, racks 0..{self.racks_per_aisle + 1})"
            )
        if p.rack == 0:
            y = 0.0
        elif p.rack == self.racks_per_aisle + 1:
            y = self.aisle_length_m
        else:
            y = self.cross_aisle_margin_m + (p.rack - 0.5) * self.rack_length_m
        return (p.aisle - 1) * self.aisle_spacing_m, y


def travel_distance(a: Position, b: Position, layout: Layout) -> float:
    """Shortest driving distance in metres between two positions.

    Same aisle: straight along it.  Different aisles: out to the front or
    the back cross-aisle, across, and back in -- whichever is shorter.  This
    is the geodesic of the aisle graph, hence a metric (symmetric, zero only
    on the same point, triangle inequality).
    """
    xa, ya = layout.xy(a)
    xb, yb = layout.xy(b)
    if a.aisle == b.aisle:
        return abs(ya - yb)
    across = abs(xa - xb)
    via_front = ya + yb
    via_back = 2 * layout.aisle_length_m - ya - yb
    return across + min(via_front, via_back)


def layout_from_row(row: Mapping[str, object]) -> Layout:
    """Rebuild a :class:`Layout` from one row of the ``warehouse-layout``
    named query (``SelectResult.as_dicts()[0]``): values may be rdflib
    literals or plain numbers.  Lets a robot without the generator's spec
    compute distances from the Location KB alone."""
    try:
        return Layout(
            aisles=int(str(row["aisles"])),
            racks_per_aisle=int(str(row["racks_per_aisle"])),
            rack_length_m=float(str(row["rack_length_m"])),
            aisle_spacing_m=float(str(row["aisle_spacing_m"])),
            cross_aisle_margin_m=float(str(row["cross_aisle_margin_m"])),
        )
    except KeyError as exc:
        raise ValueError(f"warehouse-layout row lacks {exc.args[0]!r}") from None


# --------------------------------------------------------------------------
# The warehouse model


@dataclass(frozen=True)
class WarehouseSpec:
    """Everything that determines a generated warehouse; same spec, same bytes.

    The defaults give the seed paper's three-KB team of three clusters of
    three robots and ~1,000 products in 10 aisles x 25 racks x 4 bins
    (1,000 bins; several products may share a bin).
    """

    products: int = 1000
    aisles: int = 10
    racks_per_aisle: int = 25
    bins_per_rack: int = 4
    robots: int = 9
    seed: int = 7
    rack_length_m: float = 1.2
    aisle_spacing_m: float = 3.5
    cross_aisle_margin_m: float = 2.0
    warehouse_name: str = "Warehouse_A"

    def __post_init__(self) -> None:
        for name in ("products", "aisles", "racks_per_aisle", "bins_per_rack", "robots"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not self.warehouse_name.isidentifier():
            raise ValueError(f"warehouse_name must be a plain identifier, got {self.warehouse_name!r}")
        _ = self.layout  # validates the geometry

    @property
    def layout(self) -> Layout:
        return Layout(
            aisles=self.aisles,
            racks_per_aisle=self.racks_per_aisle,
            rack_length_m=self.rack_length_m,
            aisle_spacing_m=self.aisle_spacing_m,
            cross_aisle_margin_m=self.cross_aisle_margin_m,
        )


@dataclass(frozen=True)
class Product:
    """One stored object, with its Object.owl features and its storage place."""

    name: str
    product_class: str
    fragile: bool
    price: Decimal  # currency units, 2 decimals
    colour: str
    weight_kg: Decimal
    dimensions_cm: tuple[int, int, int]  # length x width x height
    grip: str
    position: Position  # aisle and rack bay it is stored at
    bin_no: int  # shelf level within the rack, 1..bins_per_rack

    @property
    def dimension_text(self) -> str:
        length, width, height = self.dimensions_cm
        return f"{length}x{width}x{height} cm"


@dataclass(frozen=True)
class RobotSpec:
    """One robot of the team: capabilities (Capability.owl) and home (Location.owl).

    Energies are in Wh: ``energy_per_m_empty_wh`` per metre driven without
    load, ``energy_per_m_loaded_wh`` per metre carrying a full payload (linear
    in between), ``energy_per_pick_wh`` per pick-and-place.  The Task
    Assigner's battery-cost function is built from these.
    """

    robot_id: str
    can_pick: tuple[str, ...]
    components: tuple[str, ...]
    payload_kg: Decimal
    battery_wh: Decimal
    home: Position
    speed_m_s: Decimal
    energy_per_m_empty_wh: Decimal
    energy_per_m_loaded_wh: Decimal
    energy_per_pick_wh: Decimal

    @property
    def number(self) -> int:
        return int(self.robot_id.removeprefix("Robot"))

    @property
    def cluster(self) -> int:
        """0-based cluster index: Robot1-3 -> 0, Robot4-6 -> 1, ..."""
        return (self.number - 1) // CLUSTER_SIZE

    def travel_energy_wh(self, distance_m: float, load_kg: float = 0.0) -> float:
        """Battery energy to drive ``distance_m`` carrying ``load_kg``."""
        payload = float(self.payload_kg)
        if load_kg < 0 or load_kg > payload:
            raise ValueError(f"{self.robot_id} cannot carry {load_kg} kg (payload {self.payload_kg} kg)")
        empty, loaded = float(self.energy_per_m_empty_wh), float(self.energy_per_m_loaded_wh)
        return distance_m * (empty + (loaded - empty) * load_kg / payload)


@dataclass(frozen=True)
class Warehouse:
    """A generated warehouse: layout, products (by serial) and robots."""

    spec: WarehouseSpec
    products: tuple[Product, ...]
    robots: tuple[RobotSpec, ...]

    @property
    def layout(self) -> Layout:
        return self.spec.layout

    def product(self, name: str) -> Product:
        for p in self.products:
            if p.name == name:
                return p
        raise KeyError(name)

    def robot(self, robot_id: str) -> RobotSpec:
        for r in self.robots:
            if r.robot_id == robot_id:
                return r
        raise KeyError(robot_id)

    def grip_types_used(self) -> frozenset[str]:
        return frozenset(p.grip for p in self.products)


# Product catalogue: per item kind, the grip it needs and realistic ranges.
@dataclass(frozen=True)
class _ItemKind:
    item: str
    grip: str
    weight_kg: tuple[float, float]
    dims_cm: tuple[tuple[int, int], tuple[int, int], tuple[int, int]]
    price: tuple[float, float]
    fragile_p: float


_CATALOGUE: dict[str, tuple[tuple[str, ...], tuple[_ItemKind, ...]]] = {
    "PersonalItems": (
        ("Gucci", "Prada", "Fossil", "Armani", "Coach", "Tissot"),
        (
            _ItemKind("bag", "gripping", (0.5, 2.5), ((25, 45), (10, 20), (20, 35)), (80, 2500), 0.1),
            _ItemKind("backpack", "gripping", (0.6, 2.0), ((28, 35), (12, 20), (40, 50)), (40, 400), 0.0),
            _ItemKind("wallet", "suction", (0.1, 0.3), ((10, 20), (2, 3), (8, 11)), (30, 600), 0.0),
            _ItemKind("watch", "grasping", (0.1, 0.3), ((8, 12), (8, 12), (6, 9)), (90, 5000), 0.9),
            _ItemKind("sunglasses", "grasping", (0.1, 0.2), ((15, 17), (5, 7), (5, 6)), (60, 450), 0.8),
            _ItemKind("perfume", "grasping", (0.2, 0.6), ((8, 12), (5, 8), (12, 18)), (40, 250), 0.95),
        ),
    ),
    "Electronics": (
        ("Sony", "Samsung", "Dell", "Lenovo", "Philips", "Canon"),
        (
            _ItemKind("laptop", "suction", (1.2, 3.0), ((35, 45), (25, 32), (6, 10)), (400, 2800), 0.6),
            _ItemKind("phone", "suction", (0.3, 0.6), ((17, 20), (9, 11), (5, 7)), (150, 1400), 0.7),
            _ItemKind("monitor", "suction", (3.5, 9.0), ((55, 80), (12, 20), (40, 55)), (120, 900), 0.9),
            _ItemKind("tv", "lifting", (9.0, 24.0), ((100, 160), (15, 22), (65, 100)), (300, 2500), 0.95),
            _ItemKind("speaker", "gripping", (0.5, 4.0), ((10, 30), (10, 25), (15, 40)), (40, 500), 0.3),
            _ItemKind("printer", "lifting", (5.0, 15.0), ((40, 55), (35, 50), (20, 40)), (90, 700), 0.4),
            _ItemKind("camera", "grasping", (0.4, 1.5), ((12, 20), (10, 15), (8, 12)), (250, 3500), 0.85),
        ),
    ),
    "Grocery": (
        ("Nestle", "Barilla", "Heinz", "Kelloggs", "Lavazza", "Danone"),
        (
            _ItemKind("rice_sack", "lifting", (5.0, 25.0), ((40, 60), (25, 40), (10, 15)), (8, 60), 0.0),
            _ItemKind("water_pack", "lifting", (6.0, 12.0), ((30, 40), (20, 27), (25, 35)), (3, 12), 0.0),
            _ItemKind("cereal_box", "suction", (0.3, 1.0), ((20, 30), (6, 9), (28, 40)), (2, 9), 0.0),
            _ItemKind("pasta", "suction", (0.5, 1.0), ((18, 25), (6, 8), (8, 12)), (1, 5), 0.0),
            _ItemKind("olive_oil", "grasping", (0.5, 1.1), ((7, 9), (7, 9), (25, 32)), (6, 25), 0.9),
            _ItemKind("coffee_jar", "grasping", (0.2, 0.6), ((9, 12), (9, 12), (12, 18)), (4, 20), 0.8),
            _ItemKind("canned_beans", "gripping", (0.4, 2.5), ((8, 25), (8, 18), (10, 12)), (1, 10), 0.0),
        ),
    ),
    "Apparel": (
        ("Levis", "Zara", "Nike", "Adidas", "Uniqlo", "Puma"),
        (
            _ItemKind("jacket", "gripping", (0.6, 2.0), ((35, 45), (30, 40), (5, 12)), (40, 450), 0.0),
            _ItemKind("jeans", "gripping", (0.4, 0.9), ((30, 38), (25, 30), (3, 6)), (25, 150), 0.0),
            _ItemKind("tshirt", "gripping", (0.1, 0.3), ((25, 30), (20, 25), (2, 4)), (8, 60), 0.0),
            _ItemKind("dress", "gripping", (0.2, 0.8), ((30, 40), (25, 30), (3, 6)), (30, 400), 0.05),
            _ItemKind("sneakers", "suction", (0.8, 1.6), ((30, 36), (18, 22), (11, 14)), (50, 250), 0.0),
            _ItemKind("boots", "suction", (1.2, 2.5), ((32, 38), (20, 25), (15, 35)), (70, 400), 0.0),
        ),
    ),
    "HomeGoods": (
        ("Ikea", "Bosch", "Tefal", "Dyson", "Muji", "Villeroy"),
        (
            _ItemKind("lamp", "grasping", (0.8, 4.0), ((20, 40), (20, 40), (35, 70)), (20, 300), 0.8),
            _ItemKind("vase", "grasping", (0.5, 3.0), ((12, 25), (12, 25), (20, 45)), (15, 250), 0.95),
            _ItemKind("mirror", "suction", (2.0, 12.0), ((40, 80), (3, 5), (50, 120)), (30, 350), 0.95),
            _ItemKind("towel_set", "gripping", (0.8, 2.5), ((30, 40), (25, 30), (10, 20)), (15, 90), 0.0),
            _ItemKind("cookware_set", "lifting", (4.0, 12.0), ((45, 60), (30, 40), (25, 35)), (60, 500), 0.3),
            _ItemKind("chair", "lifting", (5.0, 15.0), ((45, 60), (45, 60), (80, 100)), (40, 400), 0.1),
            _ItemKind("rug", "lifting", (3.0, 20.0), ((120, 250), (25, 35), (25, 35)), (40, 900), 0.0),
        ),
    ),
}

_COLOURS = (
    "black", "white", "grey", "silver", "red", "blue", "navy", "green",
    "brown", "beige", "yellow", "orange", "pink", "purple", "gold",
)  # fmt: skip

_GUCCI_KIND = _CATALOGUE["PersonalItems"][1][0]
assert _GUCCI_KIND.item == "bag" and _GUCCI_KIND.grip == "gripping"


def _dec(value: float, places: int) -> Decimal:
    """Round to ``places`` decimals and normalise (no trailing zeros), so the
    RDF/XML lexical form is xsd:decimal's canonical one: Oxigraph canonicalises
    numeric literals on load, rdflib keeps them verbatim, and the two backends
    must return identical terms."""
    return Decimal(f"{value:.{places}f}").normalize() + Decimal(0)


def decimal_text(value: Decimal) -> str:
    """Canonical xsd:decimal lexical form (``12.5``, ``130``, ``0.05``)."""
    return format(value.normalize(), "f")


def generate(spec: WarehouseSpec) -> Warehouse:
    """Generate the warehouse a spec describes, deterministically.

    Products get serial numbers 1..N and names ``<Brand>_<item>_<serial>``;
    serial 14 is always the seed paper's ``Gucci_bag_14`` (a PersonalItems
    bag picked by gripping), substituted for the last serial when N < 14.
    Products are placed uniformly over all bins.  Robots come in clusters of
    three; a full cluster gets the :data:`CLUSTER_ARCHETYPES` grip sets in a
    seeded order, so each grip type is pickable by two robots of every
    cluster.  A trailing partial cluster (robots not a multiple of three)
    gets every grip type on every robot, which keeps that guarantee
    (``min(2, size)`` robots per grip type).
    """
    rng = random.Random(spec.seed)
    serials = list(range(1, spec.products + 1))
    if GUCCI_BAG_SERIAL not in serials:
        serials[-1] = GUCCI_BAG_SERIAL
    products = tuple(_make_product(rng, spec, serial) for serial in serials)
    robots = tuple(_make_robots(rng, spec))
    return Warehouse(spec=spec, products=products, robots=robots)


def _make_product(rng: random.Random, spec: WarehouseSpec, serial: int) -> Product:
    # Draw the same number of values for every product, so one product's
    # attributes never shift another's.
    cls = PRODUCT_CLASSES[rng.randrange(len(PRODUCT_CLASSES))]
    brands, kinds = _CATALOGUE[cls]
    brand = brands[rng.randrange(len(brands))]
    kind = kinds[rng.randrange(len(kinds))]
    if serial == GUCCI_BAG_SERIAL:
        cls, brand, kind = "PersonalItems", "Gucci", _GUCCI_KIND
    r_weight, r_price, r_fragile, r_colour = rng.random(), rng.random(), rng.random(), rng.randrange(len(_COLOURS))
    dims = tuple(rng.randint(lo, hi) for lo, hi in kind.dims_cm)
    aisle = rng.randint(1, spec.aisles)
    rack = rng.randint(1, spec.racks_per_aisle)
    bin_no = rng.randint(1, spec.bins_per_rack)
    w_lo, w_hi = kind.weight_kg
    p_lo, p_hi = kind.price
    return Product(
        name=f"{brand}_{kind.item}_{serial}",
        product_class=cls,
        fragile=r_fragile < kind.fragile_p,
        price=_dec(p_lo + (p_hi - p_lo) * r_price, 2),
        colour=_COLOURS[r_colour],
        weight_kg=_dec(w_lo + (w_hi - w_lo) * r_weight, 2),
        dimensions_cm=(dims[0], dims[1], dims[2]),
        grip=kind.grip,
        position=Position(aisle, rack),
        bin_no=bin_no,
    )


def _make_robots(rng: random.Random, spec: WarehouseSpec) -> Iterator[RobotSpec]:
    for first in range(1, spec.robots + 1, CLUSTER_SIZE):
        size = min(CLUSTER_SIZE, spec.robots - first + 1)
        if size == CLUSTER_SIZE:
            grip_sets = list(CLUSTER_ARCHETYPES)
            rng.shuffle(grip_sets)
        else:
            grip_sets = [GRIP_TYPES] * size
        for offset, grips in enumerate(grip_sets):
            yield _make_robot(rng, spec, first + offset, grips)


def _make_robot(rng: random.Random, spec: WarehouseSpec, number: int, grips: tuple[str, ...]) -> RobotSpec:
    can_pick = tuple(g for g in GRIP_TYPES if g in grips)
    components = tuple(GRIP_COMPONENT[g] for g in can_pick)
    if ARM_GRIPS & set(can_pick):
        components += ("arm",)
    components += BASE_COMPONENTS
    heavy = "lifting" in can_pick
    payload = rng.uniform(60, 120) if heavy else rng.uniform(25, 45)
    speed = rng.uniform(0.8, 1.2) if heavy else rng.uniform(1.2, 1.8)
    e_empty = rng.uniform(0.030, 0.050) if heavy else rng.uniform(0.015, 0.030)
    e_loaded = e_empty * rng.uniform(1.3, 1.8)
    e_pick = rng.uniform(1.0, 2.5) if heavy else rng.uniform(0.3, 1.0)
    battery = rng.uniform(400, 900)
    home = Position(rng.randint(1, spec.aisles), rng.randint(0, spec.racks_per_aisle + 1))
    return RobotSpec(
        robot_id=f"Robot{number}",
        can_pick=can_pick,
        components=components,
        payload_kg=_dec(payload, 1),
        battery_wh=_dec(battery, 0),
        home=home,
        speed_m_s=_dec(speed, 2),
        energy_per_m_empty_wh=_dec(e_empty, 4),
        energy_per_m_loaded_wh=_dec(e_loaded, 4),
        energy_per_pick_wh=_dec(e_pick, 2),
    )


# --------------------------------------------------------------------------
# Ontologies: a small neutral model, rendered as rdflib graphs or RDF/XML

# Object values: ("iri", local name in the ontology's namespace) or a literal
# (kind, lexical) with kind in _XSD ("string" is a plain literal).
_Value = tuple[str, str]
_Individual = tuple[str, tuple[str, ...], tuple[tuple[str, _Value], ...]]

_XSD = {
    "string": None,
    "boolean": str(XSD.boolean),
    "decimal": str(XSD.decimal),
    "integer": str(XSD.integer),
}


@dataclass(frozen=True)
class _Ontology:
    name: str
    comment: str
    version_info: str
    #: (local, superclass local or None, comment)
    classes: tuple[tuple[str, str | None, str], ...]
    #: (local, domain class local, range class local, comment)
    object_properties: tuple[tuple[str, str, str, str], ...]
    #: (local, domain class local, xsd kind, comment)
    datatype_properties: tuple[tuple[str, str, str, str], ...]
    individuals: tuple[_Individual, ...]

    @property
    def iri(self) -> str:
        return ONTOLOGIES[self.name][0]

    @property
    def ns(self) -> str:
        return ONTOLOGIES[self.name][1]

    @property
    def prefix(self) -> str:
        return ONTOLOGIES[self.name][2]


def _iri(local: str) -> _Value:
    return ("iri", local)


def _s(text: str) -> _Value:
    return ("string", text)


def _b(flag: bool) -> _Value:
    return ("boolean", "true" if flag else "false")


def _d(value: Decimal | float) -> _Value:
    return ("decimal", decimal_text(value if isinstance(value, Decimal) else Decimal(repr(value))))


def _i(value: int) -> _Value:
    return ("integer", str(int(value)))


def _version(spec: WarehouseSpec) -> str:
    return (
        f"generated by coapkb.warehouse: products={spec.products} aisles={spec.aisles} "
        f"racks_per_aisle={spec.racks_per_aisle} bins_per_rack={spec.bins_per_rack} "
        f"robots={spec.robots} seed={spec.seed}"
    )


def _object_ontology(wh: Warehouse) -> _Ontology:
    individuals: list[_Individual] = [(g, ("PickingMethod",), ()) for g in GRIP_TYPES]
    for p in wh.products:
        shape = f"Shape_{p.name}"
        individuals.append(
            (
                p.name,
                (p.product_class,),
                (
                    ("Product_name", _s(p.name)),
                    ("Item_fragility", _b(p.fragile)),
                    ("price", _d(p.price)),
                    ("colour", _s(p.colour)),
                    ("weight", _d(p.weight_kg)),
                    ("has_shape", _iri(shape)),
                    ("can_be_picked_by", _iri(p.grip)),
                ),
            )
        )
        individuals.append((shape, ("Shape",), (("Item_dimension", _s(p.dimension_text)),)))
    return _Ontology(
        name="Object",
        comment="Objects stored in the warehouse and their features (seed paper Sec. III-B).",
        version_info=_version(wh.spec),
        classes=(
            ("Product", None, "Anything stored in the warehouse."),
            *((c, "Product", f"{c} products.") for c in PRODUCT_CLASSES),
            ("Shape", None, "The shape and size of a product."),
            ("PickingMethod", None, "How a product can be picked up; matches Capability.owl's Can_Pick values."),
        ),
        object_properties=(
            ("has_shape", "Product", "Shape", "The product's shape node."),
            ("can_be_picked_by", "Product", "PickingMethod", "The grip a robot needs to pick the product."),
        ),
        datatype_properties=(
            ("Product_name", "Product", "string", "The product's name; equals its local name."),
            ("Item_fragility", "Product", "boolean", "True when the product is fragile."),
            ("price", "Product", "decimal", "Unit price."),
            ("colour", "Product", "string", "Main colour."),
            ("weight", "Product", "decimal", "Weight in kilograms."),
            ("Item_dimension", "Shape", "string", "Length x width x height, e.g. '30x12x25 cm'."),
        ),
        individuals=tuple(individuals),
    )


def _rack_local(aisle: int, rack: int) -> str:
    return f"Rack_{aisle:02d}_{rack:02d}"


def _location_ontology(wh: Warehouse) -> _Ontology:
    spec, layout = wh.spec, wh.layout
    wname = spec.warehouse_name
    individuals: list[_Individual] = [
        (
            wname,
            ("Warehouse",),
            (
                ("Location_name", _s(wname)),
                ("Aisle_count", _i(layout.aisles)),
                ("Racks_per_aisle", _i(layout.racks_per_aisle)),
                ("Bins_per_rack", _i(spec.bins_per_rack)),
                ("Rack_length_m", _d(layout.rack_length_m)),
                ("Aisle_spacing_m", _d(layout.aisle_spacing_m)),
                ("Cross_aisle_margin_m", _d(layout.cross_aisle_margin_m)),
                ("Aisle_length_m", _d(round(layout.aisle_length_m, 6))),
            ),
        )
    ]
    for a in range(1, layout.aisles + 1):
        aisle = f"Aisle_{a:02d}"
        individuals.append((aisle, ("Aisle",), (("Part_Of", _iri(wname)), ("Aisle_no", _i(a)))))
        for r in range(1, layout.racks_per_aisle + 1):
            rack = _rack_local(a, r)
            x, y = layout.xy(Position(a, r))
            individuals.append(
                (
                    rack,
                    ("Rack",),
                    (
                        ("Part_Of", _iri(aisle)),
                        ("Aisle_no", _i(a)),
                        ("Rack_no", _i(r)),
                        ("Position_x_m", _d(round(x, 6))),
                        ("Position_y_m", _d(round(y, 6))),
                    ),
                )
            )
            for b in range(1, spec.bins_per_rack + 1):
                individuals.append(
                    (
                        f"Bin_{a:02d}_{r:02d}_{b}",
                        ("Bin",),
                        (("Part_Of", _iri(rack)), ("Aisle_no", _i(a)), ("Rack_no", _i(r)), ("Bin_no", _i(b))),
                    )
                )
    for p in wh.products:
        a, r = p.position.aisle, p.position.rack
        individuals.append(
            (
                p.name,
                ("StoredItem",),
                (
                    ("Available_At", _iri(wname)),
                    ("Stored_In", _iri(f"Bin_{a:02d}_{r:02d}_{p.bin_no}")),
                    ("Inventory_aisle_no", _i(a)),
                    ("Inventory_rack_no", _i(r)),
                    ("Inventory_bin_no", _i(p.bin_no)),
                ),
            )
        )
    for robot in wh.robots:
        individuals.append(
            (
                robot.robot_id,
                ("Robot",),
                (
                    ("Robot_Id", _s(robot.robot_id)),
                    ("Robot_aisle_no", _i(robot.home.aisle)),
                    ("Robot_rack_no", _i(robot.home.rack)),
                ),
            )
        )
    return _Ontology(
        name="Location",
        comment=(
            "The warehouse map: aisles, racks, bins, where each product is stored and where each robot "
            "starts (seed paper Sec. III-B).  Geometry: aisle a's centre line is at x=(a-1)*Aisle_spacing_m; "
            "rack r's pick point at y=Cross_aisle_margin_m+(r-0.5)*Rack_length_m; the front cross-aisle is at "
            "y=0 and the back one at y=Aisle_length_m; rack 0 and rack Racks_per_aisle+1 denote an aisle's "
            "junctions with the front and back cross-aisles."
        ),
        version_info=_version(spec),
        classes=(
            ("Location", None, "A place in the warehouse."),
            ("Warehouse", "Location", "The whole warehouse; carries the geometry constants."),
            ("Aisle", "Location", "A corridor lined with racks."),
            ("Rack", "Location", "A rack bay along an aisle."),
            ("Bin", "Location", "A shelf level of a rack."),
            ("StoredItem", None, "A product as stored inventory (same local name as in Object.owl)."),
            ("Robot", None, "A robot of the team and its initial position."),
        ),
        object_properties=(
            ("Available_At", "StoredItem", "Location", "The warehouse an item is stored in."),
            ("Stored_In", "StoredItem", "Bin", "The bin an item is stored in."),
            ("Part_Of", "Location", "Location", "Containment: bin in rack, rack in aisle, aisle in warehouse."),
        ),
        datatype_properties=(
            ("Location_name", "Location", "string", "Name of a location."),
            ("Aisle_count", "Warehouse", "integer", "Number of aisles."),
            ("Racks_per_aisle", "Warehouse", "integer", "Rack bays along each aisle."),
            ("Bins_per_rack", "Warehouse", "integer", "Shelf levels per rack bay."),
            ("Rack_length_m", "Warehouse", "decimal", "Length of one rack bay along the aisle, metres."),
            ("Aisle_spacing_m", "Warehouse", "decimal", "Distance between neighbouring aisle centre lines, metres."),
            (
                "Cross_aisle_margin_m",
                "Warehouse",
                "decimal",
                "Distance from a cross-aisle centre line to the nearest rack bay, metres.",
            ),
            ("Aisle_length_m", "Warehouse", "decimal", "Front to back cross-aisle centre lines, metres."),
            ("Aisle_no", "Location", "integer", "Aisle number, 1-based."),
            ("Rack_no", "Location", "integer", "Rack bay number along the aisle, 1-based from the front."),
            ("Bin_no", "Bin", "integer", "Shelf level, 1-based from the floor."),
            ("Position_x_m", "Rack", "decimal", "x of the rack's pick point, metres."),
            ("Position_y_m", "Rack", "decimal", "y of the rack's pick point, metres."),
            ("Inventory_aisle_no", "StoredItem", "integer", "Aisle the item is stored in."),
            ("Inventory_rack_no", "StoredItem", "integer", "Rack bay the item is stored in."),
            ("Inventory_bin_no", "StoredItem", "integer", "Bin (shelf level) the item is stored in."),
            ("Robot_Id", "Robot", "string", "The robot's identifier, e.g. 'Robot1'."),
            ("Robot_aisle_no", "Robot", "integer", "Aisle of the robot's initial position."),
            ("Robot_rack_no", "Robot", "integer", "Rack of the robot's initial position (0/last+1: cross-aisles)."),
        ),
        individuals=tuple(individuals),
    )


def _capability_ontology(wh: Warehouse) -> _Ontology:
    components = sorted({c for r in wh.robots for c in r.components} | set(GRIP_COMPONENT.values()))
    individuals: list[_Individual] = [
        (g, ("Capability",), (("Requires_component", _iri(GRIP_COMPONENT[g])),)) for g in GRIP_TYPES
    ]
    individuals += [(c, ("Component",), ()) for c in components]
    for r in wh.robots:
        individuals.append(
            (
                r.robot_id,
                ("Robot",),
                (
                    ("Robot_Id", _s(r.robot_id)),
                    *(("Can_Pick", _iri(g)) for g in r.can_pick),
                    *(("has_component", _iri(c)) for c in r.components),
                    ("Robot_payload", _d(r.payload_kg)),
                    ("Robot_battery", _d(r.battery_wh)),
                    ("Robot_speed", _d(r.speed_m_s)),
                    ("Energy_per_metre_empty", _d(r.energy_per_m_empty_wh)),
                    ("Energy_per_metre_loaded", _d(r.energy_per_m_loaded_wh)),
                    ("Energy_per_pick", _d(r.energy_per_pick_wh)),
                ),
            )
        )
    return _Ontology(
        name="Capability",
        comment="Components and capabilities of every robot of the team (seed paper Sec. III-B).",
        version_info=_version(wh.spec),
        classes=(
            ("Robot", None, "A robot of the team."),
            ("Capability", None, "A way of picking objects; matches Object.owl's can_be_picked_by values."),
            ("Component", None, "A hardware component."),
        ),
        object_properties=(
            ("Can_Pick", "Robot", "Capability", "A grip type the robot can perform."),
            ("has_component", "Robot", "Component", "A hardware component the robot has."),
            ("Requires_component", "Capability", "Component", "The component a grip type needs."),
        ),
        datatype_properties=(
            ("Robot_Id", "Robot", "string", "The robot's identifier, e.g. 'Robot1'."),
            ("Robot_payload", "Robot", "decimal", "Maximum payload, kilograms."),
            ("Robot_battery", "Robot", "decimal", "Battery capacity, watt-hours."),
            ("Robot_speed", "Robot", "decimal", "Cruise speed, metres per second."),
            ("Energy_per_metre_empty", "Robot", "decimal", "Wh per metre driven without load."),
            ("Energy_per_metre_loaded", "Robot", "decimal", "Wh per metre driven with a full payload."),
            ("Energy_per_pick", "Robot", "decimal", "Wh per pick-and-place."),
        ),
        individuals=tuple(individuals),
    )


def _ontologies(spec: WarehouseSpec) -> dict[str, _Ontology]:
    wh = generate(spec)
    return {
        "Object": _object_ontology(wh),
        "Location": _location_ontology(wh),
        "Capability": _capability_ontology(wh),
    }


def _triples(ont: _Ontology) -> Iterator[tuple[rdflib.URIRef, rdflib.URIRef, rdflib.term.Node]]:
    ns = ont.ns
    ref = rdflib.URIRef
    yield ref(ont.iri), RDF.type, OWL.Ontology
    yield ref(ont.iri), RDFS.comment, rdflib.Literal(ont.comment)
    yield ref(ont.iri), OWL.versionInfo, rdflib.Literal(ont.version_info)
    for local, parent, comment in ont.classes:
        yield ref(ns + local), RDF.type, OWL.Class
        yield ref(ns + local), RDFS.comment, rdflib.Literal(comment)
        if parent is not None:
            yield ref(ns + local), RDFS.subClassOf, ref(ns + parent)
    for local, domain, range_, comment in ont.object_properties:
        yield ref(ns + local), RDF.type, OWL.ObjectProperty
        yield ref(ns + local), RDFS.domain, ref(ns + domain)
        yield ref(ns + local), RDFS.range, ref(ns + range_)
        yield ref(ns + local), RDFS.comment, rdflib.Literal(comment)
    for local, domain, kind, comment in ont.datatype_properties:
        yield ref(ns + local), RDF.type, OWL.DatatypeProperty
        yield ref(ns + local), RDFS.domain, ref(ns + domain)
        yield ref(ns + local), RDFS.range, XSD[kind]
        yield ref(ns + local), RDFS.comment, rdflib.Literal(comment)
    for local, types, props in ont.individuals:
        subject = ref(ns + local)
        yield subject, RDF.type, OWL.NamedIndividual
        for t in types:
            yield subject, RDF.type, ref(ns + t)
        for pred, (kind, value) in props:
            if kind == "iri":
                obj: rdflib.term.Node = ref(ns + value)
            else:
                dt = _XSD[kind]
                obj = rdflib.Literal(value, datatype=rdflib.URIRef(dt) if dt else None)
            yield subject, ref(ns + pred), obj


def build_graphs(spec: WarehouseSpec) -> dict[str, rdflib.Graph]:
    """The three KBs as rdflib graphs, keyed "Object", "Location", "Capability".

    Same triples as :func:`ontology_bytes` writes (tests check this); meant
    for tests and small specs -- rdflib needs ~1.4 KB per triple.
    """
    graphs: dict[str, rdflib.Graph] = {}
    for name, ont in _ontologies(spec).items():
        g = rdflib.Graph(bind_namespaces="core")
        g.bind(ont.prefix, ont.ns)
        for triple in _triples(ont):
            g.add(triple)
        graphs[name] = g
    return graphs


_XML_HEADER_NS = (
    ("owl", str(OWL)),
    ("rdf", str(RDF)),
    ("rdfs", str(RDFS)),
    ("xsd", str(XSD)),
)


def _rdfxml_lines(ont: _Ontology) -> Iterator[str]:
    """RDF/XML in Protege's layout: header, declarations, then individuals in
    generation order.  Written by hand rather than by rdflib's serializer,
    which is slow at 100k products and orders subjects by hash."""
    ns, pfx = ont.ns, ont.prefix
    decls = [f'xmlns:{pfx}="{ns}"', *(f'xmlns:{p}="{u}"' for p, u in _XML_HEADER_NS)]
    yield '<?xml version="1.0" encoding="utf-8"?>'
    yield "<rdf:RDF " + "\n     ".join(decls) + ">"
    yield f'    <owl:Ontology rdf:about="{ont.iri}">'
    yield f"        <rdfs:comment>{escape(ont.comment)}</rdfs:comment>"
    yield f"        <owl:versionInfo>{escape(ont.version_info)}</owl:versionInfo>"
    yield "    </owl:Ontology>"
    yield ""
    yield "    <!-- Classes -->"
    for local, parent, comment in ont.classes:
        yield f'    <owl:Class rdf:about="{ns}{local}">'
        if parent is not None:
            yield f'        <rdfs:subClassOf rdf:resource="{ns}{parent}"/>'
        yield f"        <rdfs:comment>{escape(comment)}</rdfs:comment>"
        yield "    </owl:Class>"
    yield ""
    yield "    <!-- Object properties -->"
    for local, domain, range_, comment in ont.object_properties:
        yield f'    <owl:ObjectProperty rdf:about="{ns}{local}">'
        yield f'        <rdfs:domain rdf:resource="{ns}{domain}"/>'
        yield f'        <rdfs:range rdf:resource="{ns}{range_}"/>'
        yield f"        <rdfs:comment>{escape(comment)}</rdfs:comment>"
        yield "    </owl:ObjectProperty>"
    yield ""
    yield "    <!-- Data properties -->"
    for local, domain, kind, comment in ont.datatype_properties:
        yield f'    <owl:DatatypeProperty rdf:about="{ns}{local}">'
        yield f'        <rdfs:domain rdf:resource="{ns}{domain}"/>'
        yield f'        <rdfs:range rdf:resource="{XSD}{kind}"/>'
        yield f"        <rdfs:comment>{escape(comment)}</rdfs:comment>"
        yield "    </owl:DatatypeProperty>"
    yield ""
    yield "    <!-- Individuals -->"
    for local, types, props in ont.individuals:
        yield f"    <owl:NamedIndividual rdf:about={quoteattr(ns + local)}>"
        for t in types:
            yield f"        <rdf:type rdf:resource={quoteattr(ns + t)}/>"
        for pred, (kind, value) in props:
            if kind == "iri":
                yield f"        <{pfx}:{pred} rdf:resource={quoteattr(ns + value)}/>"
            elif kind == "string":
                yield f"        <{pfx}:{pred}>{escape(value)}</{pfx}:{pred}>"
            else:
                yield f'        <{pfx}:{pred} rdf:datatype="{_XSD[kind]}">{value}</{pfx}:{pred}>'
        yield "    </owl:NamedIndividual>"
    yield "</rdf:RDF>"


def ontology_bytes(spec: WarehouseSpec) -> dict[str, bytes]:
    """The three KBs as OWL 2 RDF/XML documents, byte-identical for equal specs."""
    return {
        name: "".join(line + "\n" for line in _rdfxml_lines(ont)).encode("utf-8")
        for name, ont in _ontologies(spec).items()
    }


def write_ontologies(spec: WarehouseSpec, outdir: str | Path) -> dict[str, Path]:
    """Write ``Object.owl``, ``Location.owl`` and ``Capability.owl`` into ``outdir``."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    for name, ont in _ontologies(spec).items():
        path = out / f"{name}.owl"
        tmp = path.with_name(path.name + ".tmp")
        # Streamed line by line (same bytes as ontology_bytes): 100k products
        # make a ~100 MB Object.owl that need not sit in memory twice.
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            for line in _rdfxml_lines(ont):
                f.write(line)
                f.write("\n")
        tmp.replace(path)  # readers never see a half-written KB
        written[name] = path
    return written


def cluster_grip_coverage(robots: Iterable[RobotSpec]) -> dict[int, dict[str, int]]:
    """Per cluster, how many of its robots can perform each grip type."""
    coverage: dict[int, dict[str, int]] = {}
    for r in robots:
        counts = coverage.setdefault(r.cluster, {g: 0 for g in GRIP_TYPES})
        for g in r.can_pick:
            counts[g] += 1
    return coverage
