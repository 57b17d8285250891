"""Who may do what on a robot: the team's one access table (pure, no I/O).

The peer is the team member whose credential its transport's security
authenticated (OSCORE: the EDHOC credential that keyed the context the
request arrived in, RFC 8613 section 3; CurveZMQ: the client's Curve key;
mTLS: the certificate of the querier's session).

=========================================  ==================================
request                                    allowed for
=========================================  ==================================
GET / FETCH on any resource, Observe       every team member
POST ``/kb/sparql`` (a query, read-only)   every team member
POST ``/tasks``                            the feeder
POST ``/decisions``                        the robot(s) deciding for this
                                           robot's cluster (its Controller's
                                           leader under compute-and-communicate)
PATCH / iPATCH ``/kb`` (a write)           operators (role client) and robots
POST ``/kb/sync`` (replication)            robots
POST ``/robot/plan`` (compare notes)       robots (of the cluster: the
                                           resource checks)
anything else                              nobody (4.03)
=========================================  ==================================

The rows that admit by role (:data:`ROLE_RULES`) are also what Zenoh's own
access control enforces by certificate (:mod:`.zenoh_tls`).

No credential (or one of no team member) is 4.01 Unauthorized; a member
asking for something its role does not allow is 4.03 Forbidden (RFC 7252
section 5.9.2.1/.4: the client is known but not permitted).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, field

from ..transport.messages import Response, Status
from .keys import TeamMember, TeamTrust

#: POSTs that only read (SPARQL by POST, RFC 8132's alternative to FETCH).
READ_ONLY_POSTS = frozenset({"/kb/sparql"})
READ_METHODS = frozenset({"GET", "FETCH"})


@dataclass(frozen=True)
class RoleRule:
    """``method`` on ``path`` only for members of ``roles`` (and, with
    ``deciders_only``, only for the ones deciding for this robot now)."""

    method: str
    path: str
    roles: frozenset[str]
    refusal: str
    deciders_only: bool = False
    #: Whether Zenoh's access control can enforce it by key expression:
    #: not where the same key is also read by everyone (``/kb``).
    by_key: bool = True


#: The writes a role may make; every other write is nobody's.
ROLE_RULES: tuple[RoleRule, ...] = (
    RoleRule("POST", "/tasks", frozenset({"feeder"}), "only the feeder posts tasks"),
    RoleRule("POST", "/decisions", frozenset({"robot"}), "only the cluster's deciding robot posts decisions",
             deciders_only=True),
    RoleRule("PATCH", "/kb", frozenset({"client", "robot"}), "only operators (role client) and robots write the KB",
             by_key=False),
    RoleRule("iPATCH", "/kb", frozenset({"client", "robot"}), "only operators (role client) and robots write the KB",
             by_key=False),
    RoleRule("POST", "/kb/sync", frozenset({"robot"}), "only a module's holders replicate it"),
    RoleRule("POST", "/robot/plan", frozenset({"robot"}), "only the cluster's robots compare notes on a plan",
             by_key=False),
)


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
        for rule in ROLE_RULES:
            if rule.method == method and rule.path == path:
                if member.role in rule.roles and (not rule.deciders_only or member.name in self.deciders()):
                    return ALLOW
                return Verdict(False, Status.FORBIDDEN, rule.refusal)
        return Verdict(False, Status.FORBIDDEN, f"{method} {path} is not allowed to anyone")


@dataclass(frozen=True)
class TeamRules:
    """The transport's :class:`~coapkb.transport.security.AccessRules`: a
    sender's name to its member in ``trust``, held to ``policy``."""

    trust: TeamTrust
    policy: AccessPolicy
    #: Why a request with no member's credential is refused, if the
    #: transport's mechanism says it better than the policy.
    unauthenticated: str | None = None

    def refusal(self, sender: str | None, method: str, path: str) -> Response | None:
        member = None if sender is None else self.trust.by_name(sender)
        verdict = self.policy.decide(member, method, path)
        if verdict.allowed:
            return None
        assert verdict.status is not None
        reason = self.unauthenticated if member is None and self.unauthenticated else verdict.reason
        return Response.error(verdict.status, reason)
