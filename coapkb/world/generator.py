"""A deterministic generator of the warehouse's products and robots.

The seed paper's scenario (Sec. III-B) is a warehouse whose objects sit in
racks along aisles; robots navigate the aisles to pick them.
:func:`generate` makes products and robots from a :class:`WarehouseSpec`
-- the same spec always yields the same warehouse, because all randomness
comes from one ``random.Random(spec.seed)``.  :mod:`.ontologies` writes the
result as the three knowledge bases the robots carry.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from decimal import Decimal

from .geometry import Layout, Position
from .vocabulary import (
    ARM_GRIPS,
    BASE_COMPONENTS,
    CLUSTER_ARCHETYPES,
    CLUSTER_SIZE,
    GRIP_COMPONENT,
    GRIP_TYPES,
    GUCCI_BAG_SERIAL,
    PRODUCT_CLASSES,
)


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
    #: Range the robots' battery capacities are drawn from, Wh.
    battery_wh: tuple[float, float] = (400.0, 900.0)

    def __post_init__(self) -> None:
        for name in ("products", "aisles", "racks_per_aisle", "bins_per_rack", "robots"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not 0 < self.battery_wh[0] <= self.battery_wh[1]:
            raise ValueError(f"battery_wh must be a range of positive capacities, got {self.battery_wh}")
        if not self.warehouse_name.isidentifier():
            raise ValueError(f"warehouse_name must be a plain identifier, got {self.warehouse_name!r}")
        _ = self.layout  # validates the geometry

    @property
    def docks(self) -> tuple[Position, ...]:
        """The charging docks: one per robot cluster (at most one per aisle),
        on the back cross-aisle -- the wall opposite the depot, out of the
        pick and unload traffic -- spread evenly along it.  Dock ``i`` of
        ``n`` is at the back end of aisle ``1 + (2i + 1) * aisles // 2n``
        (10 aisles, 3 docks: aisles 2, 6 and 9).  Derived from the spec
        alone, so adding them draws nothing from the seeded generator."""
        n = min(-(-self.robots // CLUSTER_SIZE), self.aisles)
        back = self.racks_per_aisle + 1
        return tuple(Position(1 + (2 * i + 1) * self.aisles // (2 * n), back) for i in range(n))

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
    battery = rng.uniform(*spec.battery_wh)
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


def cluster_grip_coverage(robots: Iterable[RobotSpec]) -> dict[int, dict[str, int]]:
    """Per cluster, how many of its robots can perform each grip type."""
    coverage: dict[int, dict[str, int]] = {}
    for r in robots:
        counts = coverage.setdefault(r.cluster, {g: 0 for g in GRIP_TYPES})
        for g in r.can_pick:
            counts[g] += 1
    return coverage
