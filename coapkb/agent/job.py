"""A task as the robot's plan hands it to the task executor (and the
knowledge writer records its pick and delivery)."""

from __future__ import annotations

from dataclasses import dataclass

from .task_assigner import ChargeStop


@dataclass(frozen=True)
class Job:
    """One task as this robot carries it out: what to pick where, the
    distances its plan drove, and what it expects to hold afterwards."""

    seq: int
    object: str
    aisle: int
    rack: int
    to_object_m: float
    to_depot_m: float
    depot: tuple[int, int]
    #: Drive to a dock and charge before the task (then ``to_object_m`` is from the dock).
    charge: ChargeStop | None = None
    #: The robot's battery charge (Wh) and carried load (kg) once the job is
    #: done, as planned: what it writes into the Capability KB then.
    battery_after_wh: float | None = None
    load_after_kg: float | None = None
