"""Named updates (coapkb.kb.named_updates): a robot's usual writes sent as a
name and their arguments, rendered by the holder into the SPARQL Update the
text would be, and refused (4.00) when a name, an argument or a module is
wrong."""

from __future__ import annotations

from pathlib import Path

import cbor2
import pytest

from coapkb.kb.live import LiveKB
from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.named_updates import (
    PROLOGUE,
    NamedUpdate,
    decode_named_updates_bytes,
    encode_named_updates,
    load_update,
    pick_update,
    robot_at_update,
)
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.messages import ContentFormat, Method, Request, Status
from coapkb.wire.codec import CodecError

ONTOLOGIES = Path(__file__).resolve().parents[2] / "ontologies"
BAG = "Gucci_bag_14"


def _location() -> LiveKB:
    return LiveKB(KnowledgeBase.load([ONTOLOGIES / "Location.owl"]), "R.1", wall_ms=lambda: 1)


def _patch(body: bytes) -> Request:
    return Request(Method.PATCH, "/kb", {"ack": "local"}, payload=body, content_format=ContentFormat.CBOR)


def _place(live: LiveKB, obj: str) -> list[dict[str, str]]:
    rows = live.query(NAMED_QUERIES["pick-place"].render({"name": obj})).as_dicts()  # type: ignore[union-attr]
    return [{k: str(v) for k, v in row.items()} for row in rows]


def test_a_named_update_renders_its_text_and_costs_a_tenth_of_it() -> None:
    pick = NamedUpdate("pick", (BAG, "Robot2", 7))
    at = NamedUpdate("robot-at", ("Robot2", 3, 21, 1_795_930_476_254))
    assert pick.text() == pick_update(BAG, "Robot2", 7)
    assert at.text() == robot_at_update("Robot2", 3, 21, 1_795_930_476_254)
    body = encode_named_updates([pick, at])
    text = PROLOGUE["Location"] + pick.text() + " ;\n" + at.text()
    assert decode_named_updates_bytes(body) == (pick, at)
    assert len(body) * 5 < len(text.encode())
    load = NamedUpdate("load", ("Robot1", 12.5, 380.25, 4000))
    assert load.text() == load_update("Robot1", 12.5, 380.25, 4000)


@pytest.mark.parametrize(("item", "why"), [
    (["teleport", BAG], "no named update"),
    (["pick", BAG, "Robot2"], "takes 3 arguments"),
    (["pick", "Gucci_bag_14 } ; DROP ALL ; {", "Robot2", 7], "object"),
    (["pick", BAG, "Robot2", -1], "task"),
    (["pick", BAG, "Robot2", True], "task"),
    (["load", "Robot1", float("nan"), 1.0, 5], "load_kg"),
    ([7, BAG], "starts with its name"),
])
def test_a_wrong_name_or_argument_is_refused(item: list, why: str) -> None:
    with pytest.raises(CodecError, match=why):
        decode_named_updates_bytes(cbor2.dumps([item]))


def test_updates_of_two_modules_in_one_write_are_refused() -> None:
    with pytest.raises(CodecError, match="one module"):
        decode_named_updates_bytes(cbor2.dumps([["pick", BAG, "Robot2", 7], ["load", "Robot2", 1, 2, 3]]))
    with pytest.raises(ValueError, match="one module"):
        encode_named_updates([NamedUpdate("pick", (BAG, "Robot2", 7)), NamedUpdate("load", ("Robot2", 1, 2, 3))])


async def test_a_holder_writes_named_updates_as_it_writes_their_text() -> None:
    by_name, by_text = _location(), _location()
    updates = [NamedUpdate("pick", (BAG, "Robot2", 7)), NamedUpdate("robot-at", ("Robot2", 3, 21, 1000))]
    answer = await KBResources(by_name).write(_patch(encode_named_updates(updates)))
    assert answer.status == Status.CHANGED, answer.text()
    by_text.update(PROLOGUE["Location"] + " ;\n".join(u.text() for u in updates))
    assert _place(by_name, BAG) == _place(by_text, BAG) == [{"picked_by": "Robot2", "picked_task": "7"}]
    assert by_name.etag == by_text.etag and by_name.triple_count == by_text.triple_count


async def test_a_malformed_named_update_is_400_and_writes_nothing() -> None:
    live = _location()
    before = live.etag
    answer = await KBResources(live).write(_patch(cbor2.dumps([["pick", "a b", "Robot2", 7]])))
    assert answer.status == Status.BAD_REQUEST and "object" in answer.text()
    assert live.etag == before
