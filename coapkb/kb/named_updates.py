"""Named updates: a robot's usual writes as a name and its arguments.

What a robot's work changes in the team's knowledge is always one of a few
SPARQL Updates (a pick, an object missing, a delivery, a restock, where the
robot is, its load and charge: :mod:`coapkb.agent.knowledge_writer` says
when each is written).  Sent as text a write costs 152-316 bytes on a 35
kbit/s radio; sent by name, as the named queries are asked, 41-57.  The
holder renders the same SPARQL Update from the name and the arguments, so
a named update writes exactly what its text would.

On the wire (docs/knowledge.md): the body of a PATCH ``/kb`` with
content-format 60, ``[+ [name, * argument]]`` (docs/named-updates.cddl),
every update of one module.  Arguments are checked as strictly as a named
query's parameters: a local name must be :data:`~.named_queries.SAFE_VALUE`,
a number an integer or a finite float, a robot id any text (it is written
as an escaped literal).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cbor2

from ..wire.codec import CodecError, load_cbor
from ..world.vocabulary import CAPABILITY_NS, LOCATION_NS
from .named_queries import SAFE_VALUE

__all__ = ["NAMED_UPDATES", "NamedUpdate", "decode_named_updates", "encode_named_updates",
           "is_named_updates", "named_updates_sparql"]

#: Each module's namespace as the empty prefix: what an update of it starts with.
PROLOGUE = {"Location": f"PREFIX : <{LOCATION_NS}>\n", "Capability": f"PREFIX : <{CAPABILITY_NS}>\n"}

_PLACE = ("Inventory_aisle_no", "Inventory_rack_no", "Inventory_bin_no")
#: What a pick, a delivery and a missing report leave on an object: a restock removes them.
_AFTER_PICK = ("Picked_by", "Picked_at_task", "Delivered_at_task", "Missing_since_task", "Reported_missing_by")


def _iri(name: str) -> str:
    """A name of the module the update is for: its namespace is the empty
    prefix (:data:`PROLOGUE`), so a name costs its own length."""
    return f":{name}"


def _literal(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _number(value: float) -> str:
    """A decimal literal (``Robot_payload``'s datatype; SPARQL's ``1.5``): never an exponent."""
    return f"{value:.3f}"


def _leaves_shelf(obj: str) -> str:
    pattern = " ; ".join(f"{_iri(p)} ?v{i}" for i, p in enumerate(_PLACE))
    return f"DELETE WHERE {{ {_iri(obj)} {pattern} }}"


def pick_update(obj: str, robot: str, seq: int) -> str:
    """The SPARQL Update of a pick: off the shelf, picked by ``robot`` at task ``seq``."""
    return (f"{_leaves_shelf(obj)} ;\nINSERT DATA {{ {_iri(obj)} {_iri('Picked_by')} {_literal(robot)} ; "
            f"{_iri('Picked_at_task')} {seq} }}")


def missing_update(obj: str, robot: str, seq: int) -> str:
    """The SPARQL Update of an object not at its shelf at task ``seq``."""
    return (f"{_leaves_shelf(obj)} ;\nINSERT DATA {{ {_iri(obj)} {_iri('Missing_since_task')} {seq} ; "
            f"{_iri('Reported_missing_by')} {_literal(robot)} }}")


def restock_update(obj: str, aisle: int, rack: int, bin_no: int) -> str:
    """The SPARQL Update of a delivery (the feeder's, :mod:`coapkb.feeder.restock`):
    ``obj`` back on its shelf, its pick, delivery and missing report gone."""
    deletes = " ;\n".join(f"DELETE WHERE {{ {_iri(obj)} {_iri(p)} ?v }}" for p in (*_AFTER_PICK, *_PLACE))
    values = " ; ".join(f"{_iri(p)} {v}" for p, v in zip(_PLACE, (aisle, rack, bin_no)))
    return f"{deletes} ;\nINSERT DATA {{ {_iri(obj)} {values} }}"


def delivered_update(obj: str, seq: int) -> str:
    """The SPARQL Update of ``obj``, picked at task ``seq``, delivered at the depot."""
    return f"INSERT DATA {{ {_iri(obj)} {_iri('Delivered_at_task')} {seq} }}"


def robot_at_update(robot: str, aisle: int, rack: int, at_ms: int) -> str:
    """The SPARQL Update of where a robot is (Location) at ``at_ms``: single-valued."""
    return (f"INSERT DATA {{ {_iri(robot)} {_iri('Robot_aisle_no')} {aisle} ; {_iri('Robot_rack_no')} {rack} ; "
            f"{_iri('Robot_updated_ms')} {at_ms} }}")


def load_update(robot: str, load_kg: float, charge_wh: float, at_ms: int) -> str:
    """The SPARQL Update of a robot's carried load and battery charge (Capability)."""
    return (f"INSERT DATA {{ {_iri(robot)} {_iri('Robot_load_kg')} {_number(load_kg)} ; "
            f"{_iri('Robot_charge_wh')} {_number(charge_wh)} ; {_iri('Robot_updated_ms')} {at_ms} }}")


Argument = str | int | float


def _name(value: object) -> bool:
    return isinstance(value, str) and SAFE_VALUE.fullmatch(value) is not None


def _text(value: object) -> bool:
    return isinstance(value, str) and len(value) <= 128


def _uint(value: object) -> bool:
    return type(value) is int and 0 <= value < 2**63


def _decimal(value: object) -> bool:
    return isinstance(value, (int, float)) and type(value) is not bool and math.isfinite(value) and abs(value) < 1e12


@dataclass(frozen=True)
class _Form:
    module: str
    #: One check per argument, in order (its name for error messages).
    args: tuple[tuple[str, Callable[[object], bool]], ...]
    render: Callable[..., str]


#: Every named update: name -> its module, its arguments and its SPARQL Update.
NAMED_UPDATES: dict[str, _Form] = {
    "pick": _Form("Location", (("object", _name), ("robot", _text), ("task", _uint)), pick_update),
    "missing": _Form("Location", (("object", _name), ("robot", _text), ("task", _uint)), missing_update),
    "delivered": _Form("Location", (("object", _name), ("task", _uint)), delivered_update),
    "restock": _Form("Location", (("object", _name), ("aisle", _uint), ("rack", _uint), ("bin", _uint)),
                     restock_update),
    "robot-at": _Form("Location", (("robot", _name), ("aisle", _uint), ("rack", _uint), ("ms", _uint)),
                      robot_at_update),
    "load": _Form("Capability", (("robot", _name), ("load_kg", _decimal), ("charge_wh", _decimal), ("ms", _uint)),
                  load_update),
}


@dataclass(frozen=True)
class NamedUpdate:
    """One named update and its arguments (checked: ValueError)."""

    name: str
    args: tuple[Argument, ...]

    def __post_init__(self) -> None:
        form = NAMED_UPDATES.get(self.name)
        if form is None:
            raise ValueError(f"no named update {self.name!r} (known: {', '.join(NAMED_UPDATES)})")
        if len(self.args) != len(form.args):
            raise ValueError(f"{self.name} takes {len(form.args)} arguments "
                             f"({', '.join(n for n, _ in form.args)}), not {len(self.args)}")
        for value, (arg, check) in zip(self.args, form.args):
            if not check(value):
                raise ValueError(f"{self.name}: {arg} {value!r} is not allowed")

    @property
    def module(self) -> str:
        return NAMED_UPDATES[self.name].module

    def text(self) -> str:
        """Its SPARQL Update, without the prologue (:func:`named_updates_sparql`)."""
        return NAMED_UPDATES[self.name].render(*self.args)


def named_updates_sparql(updates: Sequence[NamedUpdate]) -> str:
    """What ``updates`` (of one module) write, as one SPARQL Update with its prologue."""
    modules = {u.module for u in updates}
    if len(modules) != 1:
        raise ValueError("named updates of one write must be of one module, and there must be one at least")
    return PROLOGUE[modules.pop()] + " ;\n".join(u.text() for u in updates)


def encode_named_updates(updates: Sequence[NamedUpdate]) -> bytes:
    """The body of a PATCH ``/kb`` (content-format 60) that writes ``updates``."""
    named_updates_sparql(updates)  # one module
    return cbor2.dumps([[u.name, *u.args] for u in updates])


def is_named_updates(item: object) -> bool:
    """Is this decoded CBOR body named updates (not a compact patch, whose items are tags)?"""
    return isinstance(item, list) and bool(item) and all(isinstance(u, list) for u in item)


def decode_named_updates(item: object) -> tuple[NamedUpdate, ...]:
    """The named updates of a decoded body; raises :class:`CodecError`."""
    if not is_named_updates(item):
        raise CodecError("named updates are [+ [name, * argument]]")
    assert isinstance(item, list)
    updates = []
    try:
        for update in item:
            if not update or not isinstance(update[0], str):
                raise CodecError("each named update starts with its name")
            updates.append(NamedUpdate(update[0], tuple(update[1:])))
        named_updates_sparql(updates)
    except ValueError as exc:  # CodecError is one too
        raise CodecError(str(exc)) from None
    return tuple(updates)


def decode_named_updates_bytes(data: bytes) -> tuple[NamedUpdate, ...]:
    """:func:`decode_named_updates` of an encoded body."""
    return decode_named_updates(load_cbor(data))
