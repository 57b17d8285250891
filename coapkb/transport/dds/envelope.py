"""The one DDS type coapkb uses (no ``from __future__ import annotations``:
Cyclone's IDL layer resolves the field types from the live annotations)."""

from dataclasses import dataclass

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.annotations import key
from cyclonedds.idl.types import sequence, uint8, uint64

__all__ = ["Envelope", "KEY_BYTES"]

#: Bytes of a sample besides the envelope: its key.
KEY_BYTES = 8


@dataclass
class Envelope(IdlStruct, typename="coapkb::Envelope"):
    """Every coapkb sample: a 64-bit key and a CBOR envelope
    (:mod:`coapkb.transport.envelope`) as an octet sequence."""

    id: uint64
    key("id")
    body: sequence[uint8]
