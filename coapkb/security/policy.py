"""Who may do what on a robot: the authorisation policy (pure, no I/O).

The peer is the team member whose EDHOC credential keyed the OSCORE
context the request arrived in (RFC 8613 section 3 binds a context to one
peer; EDHOC authenticated that peer's credential against the trust list).

=========================================  ==================================
request                                    allowed for
=========================================  ==================================
GET / FETCH on any resource, Observe       every team member
POST ``/kb/sparql`` (a query, read-only)   every team member
POST ``/tasks``                            the feeder
POST ``/decisions``                        the robot(s) deciding for this
                                           robot's cluster (its Controller's
                                           leader under compute-and-communicate)
anything else                              nobody (4.03)
=========================================  ==================================

No OSCORE (or a context of no team member) is 4.01 Unauthorized; a member
asking for something its role does not allow is 4.03 Forbidden (RFC 7252
section 5.9.2.1/.4: the client is known but not permitted).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Collection

from ..transport.messages import Status
from .keys import TeamMember

#: POSTs that only read (SPARQL by POST, RFC 8132's alternative to FETCH).
READ_ONLY_POSTS = frozenset({"/kb/sparql"})
READ_METHODS = frozenset({"GET", "FETCH"})


@dataclass(frozen=True)
class Verdict:
    allowed: bool
    status: Status | None = None
    reason: str = ""


ALLOW = Verdict(True)


@dataclass(frozen=True)
class AccessPolicy:
    #: The names of the members that may post decisions to this robot now
    #: (asked per request: the deciding robot may change with membership).
    deciders: Callable[[], Collection[str]] = field(default=lambda: ())

    def decide(self, member: TeamMember | None, method: str, path: str) -> Verdict:
        if member is None:
            return Verdict(False, Status.UNAUTHORIZED, "OSCORE with a team credential required")
        if method in READ_METHODS or (method == "POST" and path in READ_ONLY_POSTS):
            return ALLOW
        if method == "POST" and path == "/tasks":
            if member.role == "feeder":
                return ALLOW
            return Verdict(False, Status.FORBIDDEN, "only the feeder posts tasks")
        if method == "POST" and path == "/decisions":
            if member.role == "robot" and member.name in self.deciders():
                return ALLOW
            return Verdict(False, Status.FORBIDDEN, "only the cluster's deciding robot posts decisions")
        return Verdict(False, Status.FORBIDDEN, f"{method} {path} is not allowed to anyone")
