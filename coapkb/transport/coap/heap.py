"""Giving the memory a flood freed back to the system.

CPython hands objects larger than 512 bytes (a block of an answer, a
datagram) to the C library's malloc, and glibc returns freed memory to the
system only from the top of its heap: after a flood whose state has aged
out, the freed pages in the middle stay in the robot's RSS until
``malloc_trim`` gives them back (Dask's workers trim for the same reason).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from typing import Any


@functools.cache
def _libc() -> Any | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    libc = ctypes.CDLL(name)
    return libc if hasattr(libc, "malloc_trim") else None  # glibc only


def trim_heap() -> bool:
    """Return the C heap's free pages to the system; False where the C library cannot."""
    libc = _libc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True
