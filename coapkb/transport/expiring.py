"""A map bounded in entries, bytes and age: the shape of every piece of state
a stranger's requests can make a server keep (docs/flood.md): CoAP's
block-wise transfers, the KB's answer cache.

aiocoap keeps block-wise state in a ``TimeoutDict``: unbounded in size, and
an entry lives up to twice its timeout.  This map evicts the least recently
used entry first, so its three bounds hold at every insertion, and drops
entries unused for ``ttl_s`` whenever it is touched or :meth:`purge` runs.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from ..clock import monotonic as loop_clock

K = TypeVar("K")
V = TypeVar("V")


class ExpiringMap(Generic[K, V]):
    """Least recently used out first: at most ``max_entries`` entries, at most
    ``max_bytes`` by ``size(value)``, none unused for longer than ``ttl_s``.

    Reading an entry counts as a use.  A value larger than ``max_bytes`` is
    not kept at all."""

    def __init__(
        self,
        ttl_s: float,
        max_entries: int,
        max_bytes: int,
        size: Callable[[V], int],
        clock: Callable[[], float] = loop_clock,
    ) -> None:
        if ttl_s <= 0 or max_entries < 1 or max_bytes < 1:
            raise ValueError(f"bounds must be positive: ttl_s={ttl_s}, max_entries={max_entries}, max_bytes={max_bytes}")
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._size = size
        self._clock = clock
        #: key -> (value, its size, last use); in order of last use, oldest first.
        self._items: OrderedDict[K, tuple[V, int, float]] = OrderedDict()
        self.bytes = 0
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        self._purge()
        return key in self._items

    def __iter__(self) -> Iterator[K]:
        self._purge()
        return iter(list(self._items))

    def __getitem__(self, key: K) -> V:
        now = self._purge()
        value, size, _ = self._items[key]
        self._items[key] = (value, size, now)
        self._items.move_to_end(key)
        return value

    def get(self, key: K, default: V | None = None) -> V | None:
        try:
            return self[key]
        except KeyError:
            return default

    def __setitem__(self, key: K, value: V) -> None:
        now = self._purge()
        self._drop(key)
        size = self._size(value)
        if size > self.max_bytes:
            self.evicted += 1
            return
        self._items[key] = (value, size, now)
        self.bytes += size
        while len(self._items) > self.max_entries or self.bytes > self.max_bytes:
            self._evict()

    def pop(self, key: K) -> V:
        value, size, _ = self._items.pop(key)
        self.bytes -= size
        return value

    def purge(self) -> int:
        """Drop every entry unused for ``ttl_s``; returns the bytes dropped."""
        before = self.bytes
        self._purge()
        return before - self.bytes

    def _purge(self) -> float:
        now = self._clock()
        horizon = now - self.ttl_s
        while self._items:
            _, (_, _, used) = next(iter(self._items.items()))
            if used > horizon:
                break
            self._evict()
        return now

    def _drop(self, key: K) -> None:
        old = self._items.pop(key, None)
        if old is not None:
            self.bytes -= old[1]

    def _evict(self) -> None:
        _, (_, size, _) = self._items.popitem(last=False)
        self.bytes -= size
        self.evicted += 1
