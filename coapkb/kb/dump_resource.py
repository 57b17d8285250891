"""``GET /kb/dump``: a robot's whole knowledge base, or one module of it,
as sorted N-Triples, so that two replicas compare with ``diff``."""

from __future__ import annotations

import asyncio
import hashlib
from typing import TYPE_CHECKING

from ..transport.messages import ContentFormat, Request, Response, Status
from .errors import KBError
from .live import module_namespaces

if TYPE_CHECKING:
    from .store import QueryableKB

#: Dumps kept rendered, by module and KB version: the blocks of one transfer
#: (and a second reader's) are cut from one rendering.
DUMPS_KEPT = 2


class DumpResource:
    """Renders ``kb`` once per version and module asked, in a thread
    unless ``threads`` is False (the simulator's one thread)."""

    def __init__(self, kb: QueryableKB, retry_after_s: int, max_age_s: int, *, threads: bool = True) -> None:
        self.kb = kb
        self.retry_after_s = retry_after_s
        self.max_age_s = max_age_s
        self.threads = threads
        self._dumps: dict[tuple[str | None, bytes], bytes] = {}

    async def dump(self, request: Request) -> Response:
        """GET ``/kb/dump[?module=NAME]``: every triple this robot's queries
        see (of one module: those whose subject is in its namespace, and its
        ontology's header), as N-Triples (text/plain, content-format 0:
        N-Triples has no CoAP number), one line each, sorted, so two
        replicas' dumps compare with ``diff``.  No row limit: a long answer
        goes block-wise, each block cut from one rendering per KB version."""
        if request.accept not in (None, ContentFormat.TEXT):
            return Response.error(Status.NOT_ACCEPTABLE, "a dump is N-Triples, text/plain (content-format 0)")
        module = request.query.get("module")
        prefixes = module_namespaces(self.kb.names)
        if module is not None and module not in prefixes:
            return Response.error(Status.BAD_REQUEST, f"no module {module!r} here; this robot holds "
                                  + ", ".join(self.kb.names))
        etag = self.kb.etag
        key = (module, etag)
        body = self._dumps.get(key)
        if body is None:
            wanted = None if module is None else prefixes[module]
            try:
                body = await asyncio.to_thread(self._render_dump, wanted) if self.threads else self._render_dump(wanted)
            except KBError as exc:
                return Response.error(Status.SERVICE_UNAVAILABLE, f"no dump: {exc}", max_age=self.retry_after_s)
            self._dumps[key] = body
            while len(self._dumps) > DUMPS_KEPT:
                del self._dumps[next(iter(self._dumps))]
        return Response(Status.CONTENT, body, ContentFormat.TEXT, max_age=self.max_age_s,
                        etag=hashlib.blake2s(etag + (module or "").encode(), digest_size=8).digest())

    def _render_dump(self, prefixes: tuple[str, ...] | None) -> bytes:
        result = self.kb.query("CONSTRUCT WHERE { ?s ?p ?o }", row_limit=1 << 40, time_budget_s=600.0)
        lines = sorted(
            f"{s.n3()} {p.n3()} {o.n3()} .\n" for s, p, o in result.triples  # type: ignore[union-attr]  # a CONSTRUCT
            if prefixes is None or str(s).startswith(prefixes))
        return "".join(lines).encode("utf-8")
