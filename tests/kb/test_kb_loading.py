"""Loading KB files: malformed input is refused with the file named, the ETag
names the bytes parsed, prefixes are found wherever the reader's chunks end."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from coapkb.kb import formats, oxigraph_backend
from coapkb.kb.errors import KBLoadError
from coapkb.kb.store import BACKENDS, KnowledgeBase

RDF = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
HEAD = f'<?xml version="1.0"?>\n<rdf:RDF xmlns:rdf="{RDF}" xmlns:ex="http://ex.org/">\n'
ITEM = '  <rdf:Description rdf:about="http://ex.org/{n}"><ex:p rdf:resource="http://ex.org/o"/></rdf:Description>\n'
GOOD = HEAD + "".join(ITEM.format(n=n) for n in range(50)) + "</rdf:RDF>\n"


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


@pytest.mark.parametrize("backend", BACKENDS)
def test_truncated_rdfxml_refused(tmp_path: Path, backend: str) -> None:
    # Oxigraph's parser alone accepts a document that stops after a complete
    # element: a partial copy would load part of the KB without a word.
    cut = GOOD.index("</rdf:Description>", len(GOOD) // 2) + len("</rdf:Description>")
    for text in (GOOD[:cut], GOOD[:cut] + "\n", GOOD[: cut - 5], GOOD[: len(GOOD) // 2]):
        path = write(tmp_path, "Part.owl", text)
        with pytest.raises(KBLoadError) as info:
            KnowledgeBase.load([path], backend=backend)
        assert info.value.path == str(path) and info.value.message


@pytest.mark.parametrize("backend", BACKENDS)
def test_complete_rdfxml_forms_accepted(tmp_path: Path, backend: str) -> None:
    trailer = GOOD + "<!-- end of file -->\n<?pi x?>\n  \n"
    assert KnowledgeBase.load([write(tmp_path, "A.owl", trailer)], backend=backend).triple_count == 50
    default_ns = GOOD.replace('<rdf:RDF xmlns:rdf="', '<RDF xmlns="' + RDF + '" xmlns:rdf="').replace(
        "</rdf:RDF>", "</RDF>"
    )
    assert KnowledgeBase.load([write(tmp_path, "B.owl", default_ns)], backend=backend).triple_count == 50
    empty = f'<?xml version="1.0"?>\n<rdf:RDF xmlns:rdf="{RDF}"/>\n'
    assert KnowledgeBase.load([write(tmp_path, "C.owl", empty)], backend=backend).triple_count == 0


@pytest.mark.parametrize(
    "bad",
    [
        '<rdf:Description rdf:about="http://ex.org/a b"><ex:p rdf:resource="http://ex.org/o"/></rdf:Description>',
        '<rdf:Description rdf:about="http://ex.org/a"><ex:p rdf:resource="http://ex.org/<o>"/></rdf:Description>',
        '<rdf:Description rdf:about="http://ex.org/a"><ex:p xml:lang="en-">x</ex:p></rdf:Description>',
    ],
)
def test_invalid_terms_refused(tmp_path: Path, bad: str) -> None:
    # Why the loader does not use pyoxigraph's lenient=True: it lets these in.
    # (rdflib only logs a warning for the IRI with a space.)
    path = write(tmp_path, "Bad.owl", HEAD + bad + "\n</rdf:RDF>\n")
    with pytest.raises(KBLoadError) as info:
        KnowledgeBase.load([path])
    assert info.value.path == str(path)


def test_first_bad_file_is_named(tmp_path: Path) -> None:
    good = write(tmp_path, "Good.owl", GOOD)
    bad = write(tmp_path, "Bad.ttl", "<urn:a> <urn:b> .\n")
    with pytest.raises(KBLoadError, match=r"Bad\.ttl"):
        KnowledgeBase.load([good, bad])
    with pytest.raises(KBLoadError, match=r"Missing\.owl"):  # before any parsing
        KnowledgeBase.load([bad, tmp_path / "Missing.owl"])


def test_file_changed_while_loading_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write(tmp_path, "A.owl", GOOD)
    real_load = oxigraph_backend.OxigraphBackend.load

    def load_then_edit(self: object, p: Path, fmt: str) -> None:
        real_load(self, p, fmt)  # type: ignore[arg-type]
        p.write_text(GOOD.replace("http://ex.org/o", "http://ex.org/other"))

    monkeypatch.setattr(oxigraph_backend.OxigraphBackend, "load", load_then_edit)
    with pytest.raises(KBLoadError, match="changed while it was being loaded"):
        KnowledgeBase.load([path])


def test_etag_is_the_content_hash(tmp_path: Path) -> None:
    a = write(tmp_path, "A.owl", GOOD)
    first = KnowledgeBase.load([a]).etag
    assert KnowledgeBase.load([a]).etag == first
    write(tmp_path, "A.owl", GOOD.replace("http://ex.org/1\"", "http://ex.org/X\""))  # same size, other bytes
    assert KnowledgeBase.load([a]).etag != first


def test_turtle_prefixes_across_chunks(tmp_path: Path) -> None:
    text = "@prefix ex: <http://ex.org/> .\nex:a ex:p ex:o .\nPREFIX late: <http://late.org/>\nlate:a ex:p ex:o .\n"
    path = write(tmp_path, "T.ttl", text)
    source = formats.KBFile.open(path)
    source.hash_into(hashlib.sha256(), chunk_bytes=7)  # every prefix line split between reads
    assert source.prefixes == {"ex": "http://ex.org/", "late": "http://late.org/"}
    kb = KnowledgeBase.load([path])
    assert kb.prefixes == source.prefixes and kb.triple_count == 2


def test_files_after_a_bad_one_are_not_parsed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    parsed: list[str] = []
    real_load = oxigraph_backend.OxigraphBackend.load

    def spy(self: object, p: Path, fmt: str) -> None:
        parsed.append(p.name)
        real_load(self, p, fmt)  # type: ignore[arg-type]

    monkeypatch.setattr(oxigraph_backend.OxigraphBackend, "load", spy)
    bad = write(tmp_path, "Bad.ttl", "<urn:a> <urn:b> .\n")
    good = write(tmp_path, "Good.owl", GOOD)
    with pytest.raises(KBLoadError, match=r"Bad\.ttl"):
        KnowledgeBase.load([bad, good])
    assert parsed == ["Bad.ttl"]


def test_unordered_answers_repeat_between_loads(tmp_path: Path) -> None:
    files = [write(tmp_path, "A.owl", GOOD),
             write(tmp_path, "B.ttl", "".join(f"<urn:s{n}> <http://ex.org/p> <urn:o{n % 7}> .\n" for n in range(300)))]
    query = "SELECT ?s ?o WHERE { ?s <http://ex.org/p> ?o }"
    first = KnowledgeBase.load(files).query(query, row_limit=10_000)
    for _ in range(3):
        assert KnowledgeBase.load(files).query(query, row_limit=10_000) == first
