"""The pushed answers' codec (coapkb.wire.pushed): what it encodes it
decodes, a key names a request alike on every robot, and anything else is a
CodecError."""

from __future__ import annotations

from pathlib import Path

import cbor2
import pytest
from support import require

from coapkb.wire.codec import CodecError
from coapkb.wire.pushed import MAX_PUSHED, PushedAnswer, decode_pushed, encode_pushed, request_key


def test_answers_round_trip() -> None:
    answers = (PushedAnswer(request_key("pick-facts", {"name": "X"}), 2, b"\x80"),
               PushedAnswer(request_key("warehouse-layout", {}), None, b""))
    assert decode_pushed(encode_pushed(answers)) == answers


def test_a_key_names_the_query_and_its_parameters_in_any_order() -> None:
    key = request_key("robots-for-grip-among", {"grip": "lifting", "robots": "Robot1,Robot2"})
    assert key == request_key("robots-for-grip-among", {"robots": "Robot1,Robot2", "grip": "lifting"})
    assert key != request_key("robots-for-grip-among", {"grip": "suction", "robots": "Robot1,Robot2"})
    assert key != request_key("robots-for-grip", {"grip": "lifting", "robots": "Robot1,Robot2"})
    assert len(key) == 8


@pytest.mark.parametrize("data", [
    b"\xff", cbor2.dumps({}), cbor2.dumps([[b"12345678", 2]]), cbor2.dumps([[b"1234", 2, b""]]),
    cbor2.dumps([[b"12345678", -1, b""]]), cbor2.dumps([[b"12345678", "2", b""]]),
    cbor2.dumps([[b"12345678", 2, "text"]]), cbor2.dumps([[b"12345678", None, b""]] * (MAX_PUSHED + 1)),
])
def test_anything_else_is_a_codec_error(data: bytes) -> None:
    with pytest.raises(CodecError):
        decode_pushed(data)


def test_matches_the_cddl() -> None:
    try:
        import cddl_verifier
    except ImportError:
        require(False, "cddl-verifier is not installed (a test dependency in pyproject.toml)")
    validator = cddl_verifier.Validator((Path(__file__).resolve().parents[2] / "docs" / "robot-state.cddl").read_text())
    data = encode_pushed([PushedAnswer(request_key("pick-facts", {"name": "X"}), 2, b"\x80"),
                          PushedAnswer(request_key("charging-docks", {}), None, b"\x80")])
    outcome = validator.validate(data, root_type="robot-facts")
    assert outcome.valid, [str(d) for d in outcome.diagnostics]
