"""Query Handler (the seed's Fig. 2): each query goes to the KB that can answer it.

A query for a KB module this robot holds runs on its own knowledge base; any
other goes, through the transport interface, to the teammate holding that
module (or to the central server in the centralised baseline).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping

from ..errors import CoapkbError
from ..kb.client import KBClient, QueryFailed
from ..config import RobotConfig
from ..kb.store import KBError, KnowledgeBase
from ..transport.messages import ContentFormat, Method
from ..kb.named_queries import NAMED_QUERIES
from ..kb.results import QueryResult
from ..transport.base import Endpoint, TransportError

#: How queries travel: "compact" = named query resources with CBOR answers
#: (a few bytes each way); "seed" = the whole SPARQL text in every request
#: with SPARQL-JSON answers, as the seed paper's system did.
QUERY_WIRES = ("compact", "seed")


class QueryError(CoapkbError):
    """A query could not be answered; the message says which, where and why."""


@dataclass
class QueryStats:
    local: int = 0
    remote: int = 0
    failed: int = 0
    #: Remote answers served from the client's cache (fresh, or revalidated by ETag).
    cached: int = 0
    #: Wall-clock latency of each remote query, in seconds.
    remote_latencies: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"local": self.local, "remote": self.remote, "failed": self.failed, "cached": self.cached}


class QueryHandler:
    def __init__(
        self,
        config: RobotConfig,
        kb: KnowledgeBase | None,
        client: KBClient,
        wire: str = "compact",
    ) -> None:
        if wire not in QUERY_WIRES:
            raise ValueError(f"query wire {wire!r} is not one of {', '.join(QUERY_WIRES)}")
        self.config = config
        self.kb = kb
        self.client = client
        self.wire = wire
        self.stats = QueryStats()

    def _remote_for(self, module: str) -> tuple[str, Endpoint] | None:
        """(who, where) for a remote query, or None if this robot answers itself."""
        if self.config.central is not None:
            return "central server", self.config.central
        holder = self.config.holder_of(module)
        if holder is None:
            raise QueryError(f"no teammate holds the {module} KB")
        if holder.robot_id == self.config.robot_id and self.kb is not None:
            return None
        return holder.robot_id, holder.endpoint

    async def run(self, name: str, params: Mapping[str, str]) -> QueryResult:
        """Run the named query ``name`` wherever its KB module lives."""
        query = NAMED_QUERIES[name]
        target = self._remote_for(query.kb)
        if target is None:
            self.stats.local += 1
            assert self.kb is not None
            try:
                return self.kb.query(query.render(params))
            except KBError as exc:
                self.stats.failed += 1
                raise QueryError(f"{name} on own {query.kb} KB: {exc}") from None
        who, peer = target
        started = time.monotonic()
        hits_before = self.client.cache_stats.hits
        try:
            if self.wire == "compact":
                result = await self.client.named(peer, name, params, timeout=self.config.query_timeout_s)
                if self.client.cache_stats.hits > hits_before:  # answered from the cache, no traffic
                    self.stats.cached += 1
                    return result
            else:
                result = await self.client.sparql(
                    peer,
                    query.render(params),
                    accept=ContentFormat.JSON,
                    method=Method.POST,
                    timeout=self.config.query_timeout_s,
                )
        except (QueryFailed, TransportError) as exc:
            self.stats.failed += 1
            raise QueryError(f"{name} to {who} ({peer}) for the {query.kb} KB failed: {exc}") from None
        self.stats.remote += 1
        self.stats.remote_latencies.append(time.monotonic() - started)
        return result
