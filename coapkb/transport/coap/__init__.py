"""CoAP over UDP (RFC 7252) with aiocoap: the primary transport.

``client`` and ``server`` implement the one transport interface;
``reliability/`` decides how requests are retried on lossy links;
``blockwise`` and ``mapping`` are the wire details; ``aiocoap_adapter`` is
the only module that touches aiocoap's private names.
"""

from .client import CoapClientTransport
from .server import CoapServerTransport

__all__ = ["CoapClientTransport", "CoapServerTransport"]
