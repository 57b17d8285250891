"""What a robot asks of its teammates beyond their observed plans: the
leader's decision sent to the followers ("compute and communicate"), a
teammate's decision on a task (:mod:`.settling`), and the cluster's claims
for a restarted robot (:mod:`.decisions`)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable

import cbor2

from ..config import RobotConfig
from ..transport.base import ClientTransport, TransportError
from ..transport.messages import ContentFormat, Method, Request, Status
from .decisions import CLAIMS_PATH, Claim, DecisionMessage, decode_claims
from .team_view import TeamView

#: Tries to deliver the leader's decision to a follower ("compute and communicate"),
#: each within the query timeout: together under the follower's patience (4 of them).
DECISION_SENDS = 3


class TeammateCalls:
    """One robot's requests to its teammates, over its client."""

    def __init__(self, client: ClientTransport, config: RobotConfig, team: TeamView) -> None:
        self.client = client
        self.config = config
        self.team = team

    async def send_decision(self, message: DecisionMessage) -> None:
        """The leader's decision, to the members it counts as up: each one
        known down would hold the decision up by a timeout."""
        team = self.team
        members = [r for r in team.membership.members if r != self.config.robot_id and team.is_up(r)]
        await broadcast_decision(self.client, self.config, message, members, team.is_up)

    async def ask_decision(self, robot_id: str, seq: int) -> DecisionMessage | None:
        """``robot_id``'s decision on task ``seq``; None if it has none (yet)."""
        request = Request(Method.GET, "/decisions", {"seq": str(seq)}, accept=ContentFormat.CBOR)
        response = await self.client.request(self.config.team[robot_id].endpoint, request,
                                             timeout=self.team.request_timeout_s)
        if response.status != Status.CONTENT:
            return None
        try:
            return DecisionMessage.from_dict(cbor2.loads(response.payload))
        except (ValueError, KeyError, TypeError, cbor2.CBORDecodeError):
            return None

    async def ask_claims(self, robot_id: str) -> dict[str, Claim]:
        """The cluster's claims as ``robot_id`` hands them over."""
        request = Request(Method.GET, CLAIMS_PATH, accept=ContentFormat.CBOR)
        response = await self.client.request(self.config.team[robot_id].endpoint, request,
                                             timeout=self.config.query_timeout_s)
        if response.status != Status.CONTENT:
            raise TransportError(f"{robot_id} answered {response.status.dotted} for its claims")
        try:
            return decode_claims(response.payload)
        except ValueError as exc:
            raise TransportError(f"{robot_id}'s claims: {exc}") from None


async def broadcast_decision(
    client: ClientTransport, config: RobotConfig, message: DecisionMessage, recipients: Iterable[str],
    still_up: Callable[[str], bool] = lambda _: True,
) -> None:
    """Send the leader's decision to ``recipients`` (teammates), concurrently;
    a teammate it did not reach is sent it again, up to
    :data:`DECISION_SENDS` times while ``still_up`` says it is up: a
    follower that never gets it waits out its patience and decides nothing
    (found in the simulator, a burst of loss on a radio link)."""
    payload = cbor2.dumps(message.to_dict())
    request = Request(Method.POST, "/decisions", payload=payload, content_format=ContentFormat.CBOR)
    pending = list(recipients)
    for _ in range(DECISION_SENDS):
        peers = [config.team[r].endpoint for r in pending]
        results = await asyncio.gather(
            *(client.request(p, request, timeout=config.query_timeout_s) for p in peers), return_exceptions=True
        )
        pending = [r for r, result in zip(pending, results)
                   if (isinstance(result, BaseException) or not result.status.is_success) and still_up(r)]
        if not pending:
            return
    failed = ", ".join(str(config.team[r].endpoint) for r in pending)
    raise TransportError(f"decision for task {message.decision.seq} not delivered to {failed}")
