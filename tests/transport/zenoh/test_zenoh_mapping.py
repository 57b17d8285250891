"""The pure mapping of coapkb messages onto Zenoh queries, replies and samples."""

from __future__ import annotations

import cbor2
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coapkb.transport.base import Endpoint
from coapkb.transport.messages import ContentFormat, Method, Request, Response, Status
from coapkb.transport.registry import parse_endpoint
from coapkb.transport.zenoh.mapping import (
    KEY_ROOT,
    MappingError,
    Observe,
    RequestHeader,
    ResponseHeader,
    content_format_of,
    decode_request_header,
    decode_response_header,
    encode_request_header,
    encode_response_header,
    encoding_for,
    key_for_path,
    locator,
    parameters_text,
    path_for_key,
    query_from_parameters,
    request_from_query,
    response_from_reply,
)

texts = st.text(min_size=1, max_size=20)
segments = st.text(min_size=1, max_size=12).filter(lambda s: "/" not in s)
paths = st.lists(segments, min_size=0, max_size=4).map(lambda parts: "/" + "/".join(parts))
formats = st.one_of(st.none(), st.sampled_from(list(ContentFormat)), st.integers(0, 65535))
etags = st.lists(st.binary(min_size=1, max_size=8), max_size=3).map(tuple)


def test_locators() -> None:
    assert locator(Endpoint("zenoh", "10.0.0.2", 7447)) == "tcp/10.0.0.2:7447"
    # Zenoh's reliable UDP: "rel" is locator metadata, after "?" ("#rel=1" would be ignored).
    assert locator(Endpoint("zenoh+udp", "::1", 7447)) == "udp/[::1]:7447?rel=1"
    assert locator(Endpoint("zenoh+quic", "10.0.0.2", 7447)) == "quic/10.0.0.2:7447"
    with pytest.raises(ValueError, match="not a zenoh endpoint"):
        locator(Endpoint("coap", "127.0.0.1", 5683))
    assert parse_endpoint("zenoh+udp://127.0.0.1:7447") == Endpoint("zenoh+udp", "127.0.0.1", 7447)
    assert parse_endpoint("zenoh+quic://[::1]:7447") == Endpoint("zenoh+quic", "::1", 7447)


def test_keys_of_the_robot_resources() -> None:
    assert key_for_path("/kb/q/object-exists") == f"{KEY_ROOT}/kb/q/object-exists"
    assert key_for_path("/") == KEY_ROOT
    assert key_for_path("/.well-known/core") == f"{KEY_ROOT}/.well-known/core"
    # Zenoh's wildcard and selector characters never reach a key expression.
    assert key_for_path("/a*b/$c/#?") == f"{KEY_ROOT}/a%2Ab/%24c/%23%3F"
    with pytest.raises(ValueError, match="empty segment"):
        key_for_path("/kb//q")
    with pytest.raises(MappingError):
        path_for_key("elsewhere/kb")


@given(paths)
def test_path_round_trip(path: str) -> None:
    assert path_for_key(key_for_path(path)) == path


@given(st.dictionaries(texts, st.text(max_size=20), max_size=4))
def test_parameters_round_trip(query: dict[str, str]) -> None:
    text = parameters_text(query)
    assert query_from_parameters(text) == query
    assert not any(c in text.replace(";", "").replace("=", "") for c in ";=|#?*$")


def test_named_query_parameters_stay_readable() -> None:
    assert parameters_text({"name": "Gucci_bag_14"}) == "name=Gucci_bag_14"


@given(formats)
def test_encoding_round_trip(cf: int | None) -> None:
    assert content_format_of(encoding_for(cf)) == cf


def test_encodings_use_zenohs_own_ids_for_our_formats() -> None:
    assert encoding_for(ContentFormat.CBOR) == "application/cbor"
    assert encoding_for(ContentFormat.TEXT) == "text/plain"
    assert encoding_for(ContentFormat.LINK_FORMAT) == "zenoh/bytes;ct=40"
    assert content_format_of("zenoh/bytes") is None
    # Digits other than ASCII ones: "²" made int() raise a plain ValueError past the server's except.
    for bad in ("image/png", "zenoh/bytes;ct=x", "zenoh/bytes;ct=70000", "zenoh/bytes;ct=\u00b2", "zenoh/bytes;ct=\u0663"):
        with pytest.raises(MappingError):
            content_format_of(bad)


def test_a_plain_get_and_a_bare_205_carry_no_attachment() -> None:
    assert encode_request_header(RequestHeader()) is None
    assert encode_response_header(ResponseHeader()) is None
    assert decode_request_header(None) == RequestHeader()
    assert decode_response_header(None) == ResponseHeader()
    # A named query's answer: status, Max-Age, 4-byte ETag in 10 bytes.
    assert len(encode_response_header(ResponseHeader(Status.CONTENT, 60, b"\x01\x02\x03\x04")) or b"") == 10


@given(
    st.sampled_from(list(Method)), formats.filter(lambda f: f is None or f < 65536), etags,
    st.sampled_from([None, Observe.REGISTER, Observe.DEREGISTER]),
)
def test_request_header_round_trip(method: Method, accept: int | None, tags: tuple[bytes, ...], observe: Observe | None) -> None:
    header = RequestHeader(method, accept, tags, observe, None if observe is None else "coapkb-obs/ab/1")
    assert decode_request_header(encode_request_header(header)) == header


@given(paths, st.dictionaries(texts, texts, max_size=3), st.sampled_from(list(Method)), st.binary(max_size=40), formats, formats, etags)
def test_request_round_trip(path, query, method, payload, cf, accept, tags) -> None:
    request = Request(method, path, query, payload, cf, accept, tags)
    header = RequestHeader(method, accept, tags)
    decoded, _ = request_from_query(
        key_for_path(path), parameters_text(query), payload, encoding_for(cf), encode_request_header(header)
    )
    assert decoded == request


@given(st.sampled_from(list(Status)), st.binary(max_size=40), formats, st.one_of(st.none(), st.integers(0, 2**32 - 1)),
       st.one_of(st.none(), st.binary(min_size=1, max_size=8)), st.one_of(st.none(), st.integers(0, 2**64 - 1)))
def test_response_round_trip(status, payload, cf, max_age, etag, seq) -> None:
    response = Response(status, payload, cf, max_age, etag)
    attachment = encode_response_header(ResponseHeader(status, max_age, etag, seq))
    assert response_from_reply(payload, encoding_for(cf), attachment) == (response, seq)


@settings(max_examples=300)
@given(st.binary(max_size=64))
def test_fuzz_attachments_only_mapping_error(data: bytes) -> None:
    for decode in (decode_request_header, decode_response_header):
        try:
            decode(data)
        except MappingError:
            pass


@settings(max_examples=300)
@given(st.recursive(st.none() | st.booleans() | st.integers() | st.binary(max_size=9) | st.text(max_size=9),
                    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
                    max_leaves=12))
def test_fuzz_cbor_structures_only_mapping_error(value: object) -> None:
    data = cbor2.dumps(value)
    for decode in (decode_request_header, decode_response_header):
        try:
            decode(data)
        except MappingError:
            pass
