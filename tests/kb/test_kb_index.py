"""The on-disk KB index: built once from the files, then opened instead of
loading; same answers as in memory, its own ETag, never half-built."""

from __future__ import annotations

from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from support import ROOT

from coapkb.config import parse_config
from coapkb.kb.errors import KBLoadError
from coapkb.kb.store import KnowledgeBase

ONTOLOGIES = ROOT / "ontologies"
FILES = [ONTOLOGIES / "Object.owl", ONTOLOGIES / "Location.owl"]
QUERY = "SELECT ?s ?p ?o WHERE { ?s ?p ?o }"


def rows(kb: KnowledgeBase) -> Counter:
    return Counter(kb.query(QUERY, row_limit=1_000_000).rows)


def test_index_answers_as_memory_and_is_reused(tmp_path: Path) -> None:
    memory = KnowledgeBase.load(FILES)
    built = KnowledgeBase.load(FILES, index_dir=tmp_path)
    [index] = [p for p in tmp_path.iterdir()]
    assert index.name == f"{built.etag.hex()}.oxigraph"
    stamp = index.stat().st_mtime_ns
    opened = KnowledgeBase.load(FILES, index_dir=tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == [index.name], "a second load built again"
    assert index.stat().st_mtime_ns == stamp
    assert built.triple_count == opened.triple_count == memory.triple_count
    assert rows(opened) == rows(memory)
    assert (opened.names, opened.prefixes) == (memory.names, memory.prefixes)
    # Unordered answers come in the index's key order: other bytes, other ETag.
    assert opened.etag == built.etag != memory.etag


def test_other_content_other_index(tmp_path: Path) -> None:
    copy = tmp_path / "kb" / "Object.owl"
    copy.parent.mkdir()
    copy.write_bytes(FILES[0].read_bytes())
    first = KnowledgeBase.load([copy], index_dir=tmp_path / "index")
    copy.write_bytes(FILES[0].read_bytes().replace(b"</rdf:RDF>", b"<!-- edited --></rdf:RDF>"))
    second = KnowledgeBase.load([copy], index_dir=tmp_path / "index")
    assert first.etag != second.etag
    assert len(list((tmp_path / "index").iterdir())) == 2


def test_concurrent_builders_share_one_index(tmp_path: Path) -> None:
    with ThreadPoolExecutor(3) as pool:
        kbs = list(pool.map(lambda _: KnowledgeBase.load(FILES, index_dir=tmp_path), range(3)))
    assert len({kb.etag for kb in kbs}) == 1
    assert [p.name for p in tmp_path.iterdir()] == [f"{kbs[0].etag.hex()}.oxigraph"], "a builder's leftovers"


def test_bad_file_leaves_no_index(tmp_path: Path) -> None:
    bad = tmp_path / "Bad.owl"
    # Well-formed, so only the parse finds the invalid IRI: the build has begun.
    bad.write_text(
        '<?xml version="1.0"?>\n<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#" '
        'xmlns:ex="http://ex.org/">\n<rdf:Description rdf:about="http://ex.org/a b">'
        '<ex:p rdf:resource="http://ex.org/o"/></rdf:Description>\n</rdf:RDF>\n'
    )
    with pytest.raises(KBLoadError) as info:
        KnowledgeBase.load([FILES[0], bad], index_dir=tmp_path / "index")
    assert info.value.path == str(bad)
    assert list((tmp_path / "index").iterdir()) == []


def test_damaged_index_is_a_clear_error(tmp_path: Path) -> None:
    kb = KnowledgeBase.load(FILES, index_dir=tmp_path)
    (tmp_path / f"{kb.etag.hex()}.oxigraph" / "coapkb-index.json").write_text("{")
    with pytest.raises(KBLoadError, match="unreadable KB index .*delete it"):
        KnowledgeBase.load(FILES, index_dir=tmp_path)


def test_index_dir_that_cannot_be_made_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")  # even root cannot make a directory below a file
    with pytest.raises(KBLoadError, match="cannot create the KB index"):
        KnowledgeBase.load(FILES, index_dir=blocker / "index")


def test_index_needs_oxigraph(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="oxigraph"):
        KnowledgeBase.load(FILES, backend="rdflib", index_dir=tmp_path)


def test_index_is_a_robot_setting(tmp_path: Path) -> None:
    base = {
        "robot_id": "Robot1", "bind": "coap://127.0.0.1:5701", "kb": [str(FILES[0])],
        "team": {"Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Object", "Location", "Capability"]}},
    }
    assert parse_config(base).kb_index is None
    assert parse_config({**base, "kb_index": "idx"}, base_dir=tmp_path).kb_index == tmp_path / "idx"
    with pytest.raises(ValueError, match="kb_index"):
        parse_config({**base, "kb_index": 3})
