"""The names the three knowledge bases and the robot team share: the
ontologies' namespaces, product classes, grip types, robot components, and
how robots form clusters."""

from __future__ import annotations

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


#: Properties with one value per subject: a write replaces the value, and of
#: concurrent writes the latest (by hybrid logical clock) is the one seen.
SINGLE_VALUED: frozenset[str] = frozenset(
    {
        LOCATION_NS + "Robot_aisle_no",
        LOCATION_NS + "Robot_rack_no",
        LOCATION_NS + "Robot_updated_ms",
        CAPABILITY_NS + "Robot_battery",
        CAPABILITY_NS + "Robot_payload",
        CAPABILITY_NS + "Robot_load_kg",
        CAPABILITY_NS + "Robot_charge_wh",
        CAPABILITY_NS + "Robot_updated_ms",
    }
)
