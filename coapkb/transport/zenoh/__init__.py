"""Zenoh transport (``zenoh://`` over TCP, ``zenoh+udp://`` reliable UDP, ``zenoh+quic://``): see :mod:`.transport`."""

from .transport import ZenohClientTransport, ZenohOptions, ZenohServerTransport

__all__ = ["ZenohClientTransport", "ZenohOptions", "ZenohServerTransport"]
