"""``GET /kb/dump``: every triple a robot's queries see, or one module's, as
sorted N-Triples; a new rendering once the KB changed."""

from __future__ import annotations

from support import ONTOLOGIES

from coapkb.kb.live import LiveKB, wall_ms
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport.messages import ContentFormat, Method, Request, Status

CAPABILITY = "http://www.tcs.org/2018/Capability#"


def _dump(query: dict[str, str] | None = None, accept: int | None = None) -> Request:
    return Request(Method.GET, "/kb/dump", query=query or {}, accept=accept)


async def test_a_module_this_robot_lacks_or_another_format_is_refused() -> None:
    resources = KBResources(KnowledgeBase.load([ONTOLOGIES / "Capability.owl"]), threads=False)
    refused = await resources.dumps.dump(_dump({"module": "Object"}))
    assert refused.status == Status.BAD_REQUEST and "holds Capability" in refused.text()
    assert (await resources.dumps.dump(_dump(accept=ContentFormat.CBOR))).status == Status.NOT_ACCEPTABLE


async def test_a_write_shows_in_the_next_dump() -> None:
    live = LiveKB(KnowledgeBase.load([ONTOLOGIES / "Capability.owl"]), "R.1", wall_ms=wall_ms)
    resources = KBResources(live, threads=False)
    before = await resources.dumps.dump(_dump({"module": "Capability"}))
    assert before.status == Status.CONTENT and before.content_format == ContentFormat.TEXT
    live.update(f"PREFIX : <{CAPABILITY}> INSERT DATA {{ :Robot1 :note \"dumped\" }}")
    after = await resources.dumps.dump(_dump({"module": "Capability"}))
    line = f'<{CAPABILITY}Robot1> <{CAPABILITY}note> "dumped" .'
    assert line not in before.payload.decode() and line in after.payload.decode().splitlines()
    assert after.etag != before.etag
    assert (await resources.dumps.dump(_dump({"module": "Capability"}))).payload is after.payload  # rendered once
