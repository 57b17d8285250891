"""The one root of the errors coapkb raises on purpose.

Every error class of the package derives from :class:`CoapkbError`, so a
caller that means "anything coapkb reports" catches one class, not a tuple:

=============================  ====================================================================  ================
class                          raised by                                                             also a
=============================  ====================================================================  ================
``ConfigError``                :mod:`coapkb.config` (a robot's TOML)                                 ``ValueError``
``KBError`` and subclasses     :mod:`coapkb.kb.store` (load, query), :mod:`coapkb.kb.live` (writes)
``QueryFailed``                :mod:`coapkb.kb.client` (a 4.xx/5.xx answer)
``DataDirError``               :mod:`coapkb.kb.journal` (a data folder corrupt, in use, another's)
``QueryError``                 :mod:`coapkb.agent.query_handler`
``TransportError``             :mod:`coapkb.transport` (``PeerUnreachable``)
``UnknownTransport``           :mod:`coapkb.transport.registry`                                      ``ValueError``
``UnsupportedAiocoapVersion``  :mod:`coapkb.transport.coap.aiocoap_adapter`                          ``RuntimeError``
``MappingError``               :mod:`coapkb.transport.zenoh.mapping`                                 ``ValueError``
``SecurityError``              :mod:`coapkb.security` (keys, EDHOC, policy)
``DiscoveryError``             :mod:`coapkb.discovery.client`
``CodecError``                 :mod:`coapkb.wire.codec`                                              ``ValueError``
``WireError``                  :mod:`coapkb.transport.envelope`                                       ``ValueError``
``FeederError``                :mod:`coapkb.feeder` (tasks file, feeding)
``TeamError``                  :mod:`coapkb.harness.team`                                            ``FeederError``
``KnowledgeGap``               :mod:`coapkb.harness.kbs`                                             ``FeederError``
``RecordingError``             :mod:`coapkb.harness.recording`
``WorldUnavailable``           :mod:`coapkb.world.service`
``LinkEmulationError``         :mod:`coapkb.bench.linkemu`                                           ``RuntimeError``
``FaultSpecError``             :mod:`coapkb.sim.faults`                                              ``ValueError``
``SimulationError``            :mod:`coapkb.sim.loop`
``CaseFileError``              :mod:`coapkb.sim.case` (a ``--replay`` file)                          ``ValueError``
``UserError``                  :mod:`coapkb.cli`
=============================  ====================================================================  ================

The ``also a`` column keeps existing ``except ValueError`` callers working.
A bad argument to a function or constructor (a programming mistake, such as
a negative row limit) stays a plain ``ValueError``, as Python code expects;
the command line turns the ones it passes through from the user into one
error line.
"""

from __future__ import annotations


class CoapkbError(Exception):
    """Base of every error coapkb raises on purpose; ``str()`` is fit for a user."""
