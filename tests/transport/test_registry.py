"""The registry of transports: what each one registered, and what asks it."""

from __future__ import annotations

import pytest

from coapkb.security import SecurityError, mechanism_for
from coapkb.security.mechanisms import MECHANISMS
from coapkb.transport import Endpoint, check_table, open_client, reliability_for, serve
from coapkb.transport.registry import (
    REGISTERED,
    SCHEMES,
    UnknownTransport,
    find,
    parse_endpoint,
    secured_schemes,
    transport_for,
)


def test_every_registered_scheme_is_an_endpoint_scheme() -> None:
    for t in REGISTERED:
        assert parse_endpoint(f"{t.scheme}://127.0.0.1:{t.default_port}") == Endpoint(t.scheme, "127.0.0.1", t.default_port)
        for alias in t.aliases:
            assert parse_endpoint(f"{alias}://127.0.0.1:1").scheme == t.scheme
    assert parse_endpoint("tcp://127.0.0.1:1").scheme == "zmq"
    with pytest.raises(ValueError, match="unsupported scheme"):
        parse_endpoint("carrier-pigeon://127.0.0.1:1")


@pytest.mark.parametrize("uri", ["coap://127.0.0.1:5683", "zmq://[::1]:5555", "zenoh://robot-1.local:7447", "h:1"])
def test_an_endpoint_is_written_back_as_it_was_read(uri: str) -> None:
    endpoint = parse_endpoint(uri)
    assert parse_endpoint(str(endpoint)) == endpoint


#: Found by fuzzing the configuration: hosts that parsed, but whose str()
#: did not (a config written with dump_config could not be loaded again).
@pytest.mark.parametrize("uri", ["coap://[1:7=.0.0[::1]:5683.1]:5723", "coap://::1:5683", "coap://a]b:1",
                                 "coap://[::1]]:1", "coap://h:\u00b2"])
def test_a_host_str_could_not_write_back_is_refused(uri: str) -> None:
    with pytest.raises(ValueError, match="expected HOST:PORT"):
        parse_endpoint(uri)


def test_a_port_past_65535_is_said_out_of_range() -> None:
    with pytest.raises(ValueError, match=r"^port 99999 out of range \(0-65535\) in 'coap://127.0.0.1:99999'$"):
        parse_endpoint("coap://127.0.0.1:99999")
    assert parse_endpoint("127.0.0.1:65535").port == 65535


def test_lookups() -> None:
    assert SCHEMES == ("coap", "zmq", "zenoh", "zenoh+udp", "zenoh+quic", "dds")
    assert transport_for("tcp") is transport_for("zmq") is find("zmq")
    assert find("carrier-pigeon") is None
    with pytest.raises(UnknownTransport, match="choose from coap, zmq, zenoh, zenoh\\+udp, zenoh\\+quic, dds"):
        transport_for("carrier-pigeon")
    assert [t.scheme for t in REGISTERED if t.datagram] == ["coap", "zenoh+udp", "zenoh+quic", "dds"]
    assert [t.scheme for t in REGISTERED if t.resource_directory] == ["coap"]


def test_only_coap_shares_a_reliability_layer() -> None:
    assert reliability_for("zmq") is None
    assert reliability_for("zenoh+udp") is None
    # TCP, QUIC or RTPS below the others retransmits; CoAP's layer does it itself.
    assert {t.scheme: t.recovery for t in REGISTERED} == {
        "coap": None, "zmq": "tcp", "zenoh": "tcp", "zenoh+udp": "quic", "zenoh+quic": "quic", "dds": "rtps"}
    assert [t.scheme for t in REGISTERED if not t.retransmits_itself] == ["coap"]
    layer = reliability_for("coap", link_kbps=256)
    assert layer is not None and layer.as_dict()["profile"]["link_kbps"] == 256  # the layer itself


def test_each_secured_transport_has_its_mechanism() -> None:
    assert secured_schemes() == ("coap", "zmq", "zenoh", "zenoh+quic")
    assert {transport_for(s).security for s in secured_schemes()} == set(MECHANISMS)
    assert mechanism_for("zmq").needs_server_name and not mechanism_for("coap").needs_server_name
    with pytest.raises(SecurityError, match="the zenoh\\+udp transport cannot be secured: it is Zenoh's reliable UDP, "
                                            "QUIC without encryption or authentication"):
        mechanism_for("zenoh+udp")
    with pytest.raises(SecurityError, match="the dds transport cannot be secured: the cyclonedds wheel carries no "
                                            "DDS Security plugins"):
        mechanism_for("dds")


def test_every_transport_takes_a_table_of_tunables() -> None:
    """A robot's ``[transport.SCHEME]``: the CoAP layer's policy, or the options of a transport without a layer."""
    assert all(t.reliability is not None or t.options is not None for t in REGISTERED)
    for t in REGISTERED:
        check_table(t.scheme, {})
        with pytest.raises(ValueError, match="^no_such_field: unknown field"):
            check_table(t.scheme, {"no_such_field": 1})


async def test_a_table_reaches_the_transport_it_tunes() -> None:
    from coapkb.transport.router import Router
    from coapkb.transport.zmq.transport import ZmqClientTransport, ZmqServerTransport

    table = {"tcp_keepalive_idle_s": 45, "server_tcp_keepalive_idle_s": 90, "max_observations": 3}
    client = await open_client("zmq", options=table)
    server = await serve(Router(), Endpoint("zmq", "127.0.0.1", 0), options=table)
    try:
        assert isinstance(client, ZmqClientTransport) and isinstance(server, ZmqServerTransport)
        assert (client._options.tcp_keepalive_idle_s, server._observations._limit) == (45, 3)
    finally:
        await client.aclose()
        await server.aclose()
