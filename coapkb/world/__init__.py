"""The warehouse the robot team works in.

What a running robot needs -- the KBs' namespaces (:mod:`.vocabulary`) and
the geometry of the aisle graph (:mod:`.geometry`) -- is importable from
here.  Making a warehouse is apart: :mod:`.generator` (products and robots
from a seed) and :mod:`.ontologies` (the three KB files), used by
``tools/gen_warehouse.py`` and the tests.
"""

from .geometry import DEPOT, Layout, Position, layout_from_row, travel_distance
from .vocabulary import CAPABILITY_NS, CLUSTER_SIZE, LOCATION_NS, OBJECT_NS, ONTOLOGIES

__all__ = [
    "CAPABILITY_NS",
    "CLUSTER_SIZE",
    "DEPOT",
    "LOCATION_NS",
    "OBJECT_NS",
    "ONTOLOGIES",
    "Layout",
    "Position",
    "layout_from_row",
    "travel_distance",
]
