"""What the Controller's decisions travel as between teammates: the task
as the feeder posts it, the leader's decision message ("compute and
communicate"), and the cluster's claims on objects (``/robot/claims``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import cbor2

from ..world import Position
from .job import Job
from .robot_state import Decision, PlannedState
from .task_assigner import ChargeStop

#: Where a robot serves its cluster's claims (:func:`encode_claims`).
CLAIMS_PATH = "/robot/claims"


@dataclass(frozen=True)
class Claim:
    """An object this robot's cluster assigned: to whom, at which task."""

    robot: str
    seq: int

    def __str__(self) -> str:
        return f"picked by {self.robot} at task {self.seq}"


@dataclass(frozen=True)
class Task:
    seq: int
    object: str
    #: Robots (restarted) that are members again from this task on.
    join: tuple[str, ...] = ()
    #: The process of each joiner that took this post (its boot), where the
    #: feeder names it: a teammate that finds another process of it there
    #: takes it for restarted again, not for the joiner.
    boots: Mapping[str, int] = field(default_factory=dict)
    #: The task this one does again: its robot went down before the pick.
    again: int | None = None
    #: The object was delivered back to its shelf since the cluster decided
    #: it (coapkb.feeder.restock): the claim remembered is void.
    restocked: bool = False


@dataclass(frozen=True)
class DecisionMessage:
    """What "compute and communicate" sends: the decision and the winner's plan."""

    decision: Decision
    after: PlannedState | None = None
    job: Job | None = None
    #: The sending leader's process (:attr:`RobotState.boot`; 0 = not said):
    #: a follower that never observed it can still tell a new process of it.
    boot: int = 0

    def to_dict(self) -> dict[str, object]:
        raw: dict[str, object] = {
            "decision": asdict(self.decision),
            "after": asdict(self.after) if self.after else None,
            "job": asdict(self.job) if self.job else None,
        }
        if self.boot:
            raw["boot"] = self.boot
        return raw

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> DecisionMessage:
        job = raw.get("job")
        return cls(
            decision=Decision(**raw["decision"]),
            after=PlannedState(**raw["after"]) if raw.get("after") else None,
            job=_job(job) if job else None,
            boot=int(raw.get("boot", 0)),
        )


def _job(raw: Mapping[str, Any]) -> Job:
    charge = raw.get("charge")
    if charge is not None:
        charge = ChargeStop(**{**charge, "dock": Position(**charge["dock"])})
    return Job(**{**raw, "depot": tuple(raw["depot"]), "charge": charge})


def encode_claims(claims: Mapping[str, Claim]) -> bytes:
    """``/robot/claims``: ``[[object, robot, seq], ...]`` in CBOR."""
    return cbor2.dumps([[obj, c.robot, c.seq] for obj, c in claims.items()])


def decode_claims(payload: bytes) -> dict[str, Claim]:
    """:func:`encode_claims`'s output; ``ValueError`` for anything else."""
    try:
        raw = cbor2.loads(payload)
    except (cbor2.CBORDecodeError, RecursionError) as exc:
        raise ValueError(f"not CBOR: {exc}") from None
    if not isinstance(raw, list):
        raise ValueError("claims are an array")
    claims = {}
    for item in raw:
        if not (isinstance(item, list) and len(item) == 3 and isinstance(item[0], str) and isinstance(item[1], str)
                and type(item[2]) is int and item[2] > 0):
            raise ValueError(f"a claim is [object, robot, seq], got {item!r}"[:200])
        claims[item[0]] = Claim(item[1], item[2])
    return claims
