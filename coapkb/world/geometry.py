"""The warehouse's geometry: positions on the aisle graph and the distances
between them, which the Task Assigner's cost function needs.

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

from collections.abc import Mapping
from dataclasses import dataclass


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


#: The depot, where robots unload and start when no [start] is given: the
#: front end of the first aisle.
DEPOT = Position(1, 0)


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

