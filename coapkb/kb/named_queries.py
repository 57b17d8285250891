"""The seed paper's queries (Sec. III-D, Query_1..Query_4), corrected and named.

As printed, the paper's queries do not parse: the WHERE clauses lack
braces, local names are quoted (``ns_1:'Gucci_bag_14'``), Query_3 projects
``?price`` and ``?color`` without binding them, and Query_4 projects
``?robo_name`` but binds ``?robo_id``.  The versions here fix that and take
the object name or grip type as a parameter, so a robot can offer them as
resources (``/kb/q/<name>?name=...``) and a client sends a few bytes
instead of the query text.

Parameters are substituted textually, so they are validated strictly: a
value must be a plain local name (:data:`SAFE_VALUE`).  Nothing that could
close a literal, an IRI or a group pattern gets through.
"""

from __future__ import annotations

import re
import string
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

__all__ = ["NAMED_QUERIES", "SAFE_VALUE", "NamedQuery", "named_queries_for"]

#: A parameter value: a SPARQL/XML-safe local name, at most 128 characters,
#: not ending in "." (a prefixed name cannot end with a dot).
#: Most local names a list parameter takes: a cluster is three robots, and a
#: CoAP Uri-Query option holds at most 255 bytes.
MAX_LIST_ITEMS = 16
SAFE_VALUE = re.compile(r"[A-Za-z_](?:[A-Za-z0-9_.-]{0,126}[A-Za-z0-9_-])?")


class _Template(string.Template):
    # ``$name`` placeholders; templates must not use SPARQL's ``$var`` form.
    idpattern = r"[a-z][a-z0-9_]*"


@dataclass(frozen=True)
class NamedQuery:
    """A parameterised SPARQL query one KB module answers.

    ``kb`` is the module (file stem) that holds the data; ``params`` the
    parameter names, in the order they are documented; ``template`` the
    query with ``$param`` placeholders; ``rt`` the CoRE resource type
    advertised for it.
    """

    name: str
    kb: str
    params: tuple[str, ...]
    template: str
    description: str
    rt: str = "coapkb.q"
    #: Parameters (of ``params``) whose value is a comma-separated list of
    #: local names, rendered as a list of string literals (``"a", "b"``).
    lists: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        placeholders = set(_Template(self.template).get_identifiers())
        if placeholders != set(self.params) or len(set(self.params)) != len(self.params):
            raise ValueError(
                f"named query {self.name!r}: template placeholders {sorted(placeholders)} "
                f"do not match params {list(self.params)}"
            )
        if not set(self.lists) <= set(self.params):
            raise ValueError(f"named query {self.name!r}: list parameters {list(self.lists)} are not all params")

    def render(self, params: Mapping[str, str]) -> str:
        """The query text for these parameter values.

        Raises ``ValueError`` naming the problem for a missing, unexpected
        or unsafe parameter, so a server can answer 4.00 with the message.
        """
        missing = [p for p in self.params if p not in params]
        extra = sorted(k for k in params if k not in self.params)
        if missing or extra:
            problems = []
            if missing:
                problems.append("missing " + ", ".join(missing))
            if extra:
                problems.append("unexpected " + ", ".join(extra))
            expected = ", ".join(self.params) if self.params else "no parameters"
            raise ValueError(f"query {self.name!r} takes {expected}: {'; '.join(problems)}")
        values: dict[str, str] = {}
        for key in self.params:
            value = params[key]
            items = value.split(",") if key in self.lists and isinstance(value, str) else [value]
            if len(items) > MAX_LIST_ITEMS or not all(
                isinstance(item, str) and SAFE_VALUE.fullmatch(item) is not None for item in items
            ):
                what = (f"a comma-separated list of at most {MAX_LIST_ITEMS} local names" if key in self.lists
                        else "a local name")
                raise ValueError(
                    f"parameter {key!r} of query {self.name!r} must be {what} "
                    f"(letters, digits, '_', '-', '.', at most 128 characters), got {value!r}"
                )
            values[key] = ", ".join(f'"{item}"' for item in items) if key in self.lists else value
        return _Template(self.template).substitute(values)


_OBJ = "PREFIX ns_2: <http://www.tcs.org/2018/Object#>\n"
_LOC = "PREFIX ns_1: <http://www.tcs.org/2018/Location#>\n"
_CAP = "PREFIX ns_3: <http://www.tcs.org/2018/Capability#>\n"
_RDF = "PREFIX rdf: <http://www.w3.org/1999/02/22-rdf-syntax-ns#>\n"
_RDFS = "PREFIX rdfs: <http://www.w3.org/2000/01/rdf-schema#>\n"

# The Capability KB's robots, as two queries and their team-scoped forms ask them.
_ROBOTS_FOR_GRIP = """SELECT ?robots ?robo_id ?payload
WHERE {
  ?robots ns_3:Can_Pick ns_3:$grip .
  ?robots ns_3:Robot_Id ?robo_id .
  ?robots ns_3:Robot_payload ?payload .
"""
_ROBOT_SPECS = """SELECT ?robot ?robo_id ?payload ?battery ?speed ?e_empty ?e_loaded ?e_pick
WHERE {
  ?robot ns_3:Robot_Id ?robo_id .
  ?robot ns_3:Robot_payload ?payload .
  ?robot ns_3:Robot_battery ?battery .
  ?robot ns_3:Robot_speed ?speed .
  ?robot ns_3:Energy_per_metre_empty ?e_empty .
  ?robot ns_3:Energy_per_metre_loaded ?e_loaded .
  ?robot ns_3:Energy_per_pick ?e_pick .
"""
#: Only these robots (the asking robot's team): a comma-separated list parameter.
_AMONG = """  FILTER (STR(?robo_id) IN ($robots))
"""

_QUERIES = (
    # Query_1, generalised: the paper fixes the class (PersonalItems); an
    # object of any product class exists if its name matches.
    NamedQuery(
        name="object-exists",
        kb="Object",
        params=("name",),
        template=_OBJ + _RDF + _RDFS + """SELECT ?object ?class
WHERE {
  ?object ns_2:Product_name "$name" .
  ?object rdf:type ?class .
  ?class rdfs:subClassOf ns_2:Product .
}""",
        description="Query_1: does a product with this name exist, and of which class",
    ),
    # Query_1 exactly as the paper means it (class given).
    NamedQuery(
        name="object-exists-in-class",
        kb="Object",
        params=("name", "cls"),
        template=_OBJ + _RDF + """SELECT ?object
WHERE {
  ?object rdf:type ns_2:$cls .
  ?object ns_2:Product_name "$name" .
}""",
        description="Query_1 (paper form): a product with this name in this class",
    ),
    # What the task assigner uses of Query_1 and Query_3, in one exchange
    # with the Object KB's holder instead of two: a row if the product
    # exists (its class), with the grip it is picked by and its weight when
    # the KB has them.  Query_3's other features (price, colour, shape) are
    # for people; the cost model never reads them.  Class and grip come as
    # their local names (the vocabulary is the Object KB's own), so the
    # answer carries no namespace.  The OPTIONAL names the product again:
    # Oxigraph evaluates it on its own before the left join, and without
    # the name it reads every product's grip and weight (3.4 ms, not 0.17).
    NamedQuery(
        name="pick-facts",
        kb="Object",
        params=("name",),
        template=_OBJ + _RDF + _RDFS + """SELECT ?class ?grip ?weight
WHERE {
  ?object ns_2:Product_name "$name" .
  ?object rdf:type ?type .
  ?type rdfs:subClassOf ns_2:Product .
  BIND (STRAFTER(STR(?type), "#") AS ?class)
  OPTIONAL {
    ?object ns_2:Product_name "$name" .
    ?object ns_2:can_be_picked_by ?by .
    ?object ns_2:weight ?weight .
    BIND (STRAFTER(STR(?by), "#") AS ?grip)
  }
}""",
        description="Query_1 and the grip and weight of Query_3: what assigning a pick needs from the Object KB",
    ),
    NamedQuery(
        name="object-location",
        kb="Location",
        params=("name",),
        template=_LOC + """SELECT ?loc ?warehouse ?aisle_no ?bin_no ?rack_no
WHERE {
  ns_1:$name ns_1:Available_At ?loc .
  ?loc ns_1:Location_name ?warehouse .
  ns_1:$name ns_1:Inventory_aisle_no ?aisle_no .
  ns_1:$name ns_1:Inventory_bin_no ?bin_no .
  ns_1:$name ns_1:Inventory_rack_no ?rack_no .
}""",
        description="Query_2: warehouse, aisle, rack and bin of a product",
    ),
    # Query_2 as the task assigner uses it: the place on the aisle graph,
    # without the warehouse's IRI and name (for people; one warehouse here).
    NamedQuery(
        name="pick-place",
        kb="Location",
        params=("name",),
        template=_LOC + """SELECT ?aisle_no ?rack_no ?bin_no ?picked_by ?picked_task ?missing_task
WHERE {
  OPTIONAL {
    ns_1:$name ns_1:Inventory_aisle_no ?aisle_no .
    ns_1:$name ns_1:Inventory_rack_no ?rack_no .
    ns_1:$name ns_1:Inventory_bin_no ?bin_no .
  }
  OPTIONAL { ns_1:$name ns_1:Picked_by ?picked_by . ns_1:$name ns_1:Picked_at_task ?picked_task . }
  OPTIONAL { ns_1:$name ns_1:Missing_since_task ?missing_task . }
  FILTER (BOUND(?aisle_no) || BOUND(?picked_by) || BOUND(?missing_task))
}""",
        description=("Query_2 as assigning a pick needs it: aisle, rack and bin of a product, "
                     "or who picked it at which task, or since which task it is missing"),
    ),
    # Query_3 plus the bindings for ?price and ?color the paper forgot, and
    # ?weight, which the battery cost of carrying the object depends on.
    NamedQuery(
        name="object-features",
        kb="Object",
        params=("name",),
        template=_OBJ + """SELECT ?frag ?price ?color ?shape ?dim ?grip ?weight
WHERE {
  ns_2:$name ns_2:Item_fragility ?frag .
  ns_2:$name ns_2:price ?price .
  ns_2:$name ns_2:colour ?color .
  ns_2:$name ns_2:has_shape ?shape .
  ?shape ns_2:Item_dimension ?dim .
  ns_2:$name ns_2:can_be_picked_by ?grip .
  ns_2:$name ns_2:weight ?weight .
}""",
        description="Query_3: fragility, price, colour, shape, size, grip and weight of a product",
    ),
    # Query_4 with ?robo_id projected (the paper projects the unbound
    # ?robo_name); ordered so every robot sees the same row order.
    NamedQuery(
        name="robots-for-grip",
        kb="Capability",
        params=("grip",),
        template=_CAP + _ROBOTS_FOR_GRIP + """}
ORDER BY ?robo_id""",
        description="Query_4: robots that can pick with this grip, and their payloads",
    ),
    # Query_4 for the asking robot's own team: a robot's cost model needs
    # its teammates only, and this answer does not grow with the whole team.
    NamedQuery(
        name="robots-for-grip-among",
        kb="Capability",
        params=("grip", "robots"),
        lists=("robots",),
        template=_CAP + _ROBOTS_FOR_GRIP + _AMONG + """}
ORDER BY ?robo_id""",
        description="Query_4 among these robots (comma-separated ids): those that can pick with this grip",
    ),
    NamedQuery(
        name="robot-specs",
        kb="Capability",
        params=(),
        template=_CAP + _ROBOT_SPECS + """}
ORDER BY ?robo_id""",
        description="Every robot's payload (kg), battery (Wh), speed (m/s) and energy use (Wh/m, Wh/pick)",
    ),
    NamedQuery(
        name="robot-specs-among",
        kb="Capability",
        params=("robots",),
        lists=("robots",),
        template=_CAP + _ROBOT_SPECS + _AMONG + """}
ORDER BY ?robo_id""",
        description="robot-specs among these robots (comma-separated ids)",
    ),
    NamedQuery(
        name="robot-positions",
        kb="Location",
        params=(),
        template=_LOC + """SELECT ?robot ?robo_id ?aisle_no ?rack_no ?updated_ms
WHERE {
  ?robot ns_1:Robot_Id ?robo_id .
  ?robot ns_1:Robot_aisle_no ?aisle_no .
  ?robot ns_1:Robot_rack_no ?rack_no .
  OPTIONAL { ?robot ns_1:Robot_updated_ms ?updated_ms . }
}
ORDER BY ?robo_id""",
        description=("Aisle and rack of every robot: where it started, or where it last reported "
                     "(updated_ms: when, Unix milliseconds) on a writable team"),
    ),
    NamedQuery(
        name="robot-loads",
        kb="Capability",
        params=(),
        template=_CAP + """SELECT ?robo_id ?payload ?load_kg ?charge_wh ?updated_ms
WHERE {
  ?robot ns_3:Robot_Id ?robo_id .
  ?robot ns_3:Robot_payload ?payload .
  OPTIONAL { ?robot ns_3:Robot_load_kg ?load_kg . }
  OPTIONAL { ?robot ns_3:Robot_charge_wh ?charge_wh . }
  OPTIONAL { ?robot ns_3:Robot_updated_ms ?updated_ms . }
}
ORDER BY ?robo_id""",
        description=("Every robot's payload capacity (kg) and, as it last reported on a writable team, "
                     "the load it carries (kg), its battery's charge (Wh) and when (Unix milliseconds)"),
    ),
    NamedQuery(
        name="warehouse-layout",
        kb="Location",
        params=(),
        template=_LOC + """SELECT ?warehouse ?name ?aisles ?racks_per_aisle ?bins_per_rack
       ?rack_length_m ?aisle_spacing_m ?cross_aisle_margin_m ?aisle_length_m
WHERE {
  ?warehouse ns_1:Location_name ?name .
  ?warehouse ns_1:Aisle_count ?aisles .
  ?warehouse ns_1:Racks_per_aisle ?racks_per_aisle .
  ?warehouse ns_1:Bins_per_rack ?bins_per_rack .
  ?warehouse ns_1:Rack_length_m ?rack_length_m .
  ?warehouse ns_1:Aisle_spacing_m ?aisle_spacing_m .
  ?warehouse ns_1:Cross_aisle_margin_m ?cross_aisle_margin_m .
  ?warehouse ns_1:Aisle_length_m ?aisle_length_m .
}""",
        description="Warehouse geometry constants (metres) for travel-distance costs",
    ),
    NamedQuery(
        name="charging-docks",
        kb="Location",
        params=(),
        template=_LOC + """SELECT ?dock ?name ?aisle_no ?rack_no
WHERE {
  ?dock a ns_1:ChargingDock .
  ?dock ns_1:Location_name ?name .
  ?dock ns_1:Aisle_no ?aisle_no .
  ?dock ns_1:Rack_no ?rack_no .
}
ORDER BY ?name""",
        description="The charging docks and their places on the aisle graph (aisle, rack 0 or last+1)",
    ),
)

#: Every named query, by name.  Read-only by convention: build your own dict
#: to add queries.
NAMED_QUERIES: dict[str, NamedQuery] = {q.name: q for q in _QUERIES}


def named_queries_for(kb_names: Iterable[str]) -> list[NamedQuery]:
    """The named queries a KB made of these modules (file stems) can answer,
    sorted by name."""
    names = set(kb_names)
    return sorted((q for q in NAMED_QUERIES.values() if q.kb in names), key=lambda q: q.name)
