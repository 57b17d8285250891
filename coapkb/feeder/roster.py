"""The team as the feeder knows it: who is on it, where each robot
listens, and which robots share a task stream."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ..transport.base import Endpoint


@dataclass(frozen=True)
class Roster:
    """Who is on the team and where: every robot's endpoint, and the
    clusters (robots that share a task stream) in feeding order."""

    endpoints: Mapping[str, Endpoint]
    clusters: Sequence[Sequence[str]]

    @property
    def robot_ids(self) -> list[str]:
        return [r for cluster in self.clusters for r in cluster]

    def cluster_of(self, robot_id: str) -> Sequence[str]:
        """The robots of ``robot_id``'s cluster (its own included)."""
        return next((c for c in self.clusters if robot_id in c), ())
