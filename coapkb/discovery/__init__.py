"""Discovery without a static map: a Resource Directory (RFC
9176) where robots register their endpoint and KB modules, and look up their
cluster (docs/discovery.md).

* :mod:`.directory`: the directory (aiocoap's registry behind coapkb's
  transport, OSCORE and policy); ``coapkb team --discovery rd`` hosts it in
  the feeder's process.
* :mod:`.client`: a robot's registration, lookup and renewals.
"""

from .client import DirectoryClient, DiscoveryError, discover
from .directory import DirectoryPolicy, DirectoryService, ResourceDirectory

__all__ = ["DirectoryClient", "DirectoryPolicy", "DirectoryService", "DiscoveryError", "ResourceDirectory", "discover"]
