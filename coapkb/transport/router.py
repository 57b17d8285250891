"""A transport-neutral resource table: the :class:`~coapkb.transport.base.Service`
every robot exposes, whatever carries its messages."""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable

from .base import ResourceInfo, Service
from .messages import Request, Response, Status

Handler = Callable[[Request], Awaitable[Response]]

log = logging.getLogger(__name__)


class Router(Service):
    """Routes requests by exact path (every resource is listed in discovery)."""

    def __init__(self) -> None:
        self._routes: dict[str, tuple[ResourceInfo, Handler]] = {}
        self._listeners: dict[str, list[Callable[[], None]]] = {}

    def add(self, info: ResourceInfo, handler: Handler) -> None:
        if info.path in self._routes:
            raise ValueError(f"resource {info.path} is already mounted")
        self._routes[info.path] = (info, handler)

    def resources(self) -> list[ResourceInfo]:
        return [info for info, _ in self._routes.values()]

    async def handle(self, request: Request) -> Response:
        route = self._routes.get(request.path)
        if route is None:
            return Response.error(Status.NOT_FOUND, self._not_found(request.path))
        info, handler = route
        if request.method not in info.methods:
            allowed = ", ".join(info.methods)
            return Response.error(
                Status.METHOD_NOT_ALLOWED, f"{request.method} not allowed on {info.path} (use {allowed})"
            )
        try:
            return await handler(request)
        except Exception:  # a bug must cost one request, never the server
            log.exception("handler for %s failed", request.path)
            return Response.error(Status.INTERNAL_SERVER_ERROR, "internal error while handling the request")

    def _not_found(self, path: str) -> str:
        """Why ``path`` has no answer, naming the resources beside it: a
        misspelled ``/kb/q/<name>`` learns the names of the named queries."""
        parent = path.rpartition("/")[0] + "/"
        siblings = sorted(
            p[len(parent) :] for p in self._routes if p.startswith(parent) and "/" not in p[len(parent) :]
        )
        known = f"; {parent} has: {', '.join(siblings)}" if siblings else ""
        return f"no resource at {path}{known}"

    def subscribe(self, path: str, on_change: Callable[[], None]) -> Callable[[], None]:
        listeners = self._listeners.setdefault(path, [])
        listeners.append(on_change)
        return lambda: listeners.remove(on_change) if on_change in listeners else None

    def notify(self, path: str) -> None:
        """Tell observers of ``path`` that its representation changed."""
        for listener in list(self._listeners.get(path, ())):
            listener()
