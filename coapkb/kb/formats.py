"""KB files: the RDF format of a file, the prefixes it declares, and what
says it has not changed while it was loaded."""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import rdflib

from .errors import KBLoadError

#: suffix -> rdflib format name.
_SUFFIX_FORMATS = {
    ".owl": "xml",
    ".rdf": "xml",
    ".xml": "xml",
    ".ttl": "turtle",
    ".turtle": "turtle",
    ".nt": "nt",
    ".ntriples": "nt",
    ".n3": "n3",
    ".jsonld": "json-ld",
    ".json-ld": "json-ld",
}

_TURTLE_PREFIX = re.compile(
    rb"^[ \t]*(?:@prefix|PREFIX)[ \t]+([A-Za-z][A-Za-z0-9_.-]*)?:[ \t]*<([^>\s]*)>", re.MULTILINE | re.IGNORECASE
)


class Digest(Protocol):
    """What a file's bytes are fed to (any hashlib digest)."""

    def update(self, data: bytes, /) -> None: ...


def _format_for(path: Path, head: bytes) -> str:
    """The file's format from its suffix (and, for ``.owl``, its first bytes)."""
    suffix = path.suffix.lower()
    fmt = _SUFFIX_FORMATS.get(suffix)
    if fmt is None:
        fmt = rdflib.util.guess_format(path.name)
    if fmt is None:
        raise KBLoadError(path, f"unknown RDF format for suffix {suffix!r} (use .owl/.rdf, .ttl, .nt, .n3, .jsonld)")
    if suffix == ".owl" and not head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"<"):
        fmt = "turtle"  # Protege can save .owl files as Turtle too
    return fmt


_TAIL = 1 << 16


def _xml_root(path: Path, size: int) -> dict[str, str]:
    """The prefixes an RDF/XML file declares on its root, after checking that
    the file ends with the root's end tag.

    Prefixes: the root element's ``xmlns:p`` attributes, read by an
    incremental parser that stops at the root (large files cost nothing).
    End tag: Oxigraph's RDF/XML parser accepts a document that stops after
    any complete element, so a file cut short at an element boundary (a
    partial copy) would load part of a KB without a word; the last bytes
    tell.  Malformed heads are left to the real parser and its message.
    """
    found: dict[str, str] = {}
    default_ns: str | None = None
    root: str | None = None
    try:
        with path.open("rb") as f:
            for event, item in ET.iterparse(f, events=("start-ns", "start")):
                if event == "start":
                    root = item.tag
                    break
                prefix, uri = item
                if prefix:
                    found.setdefault(prefix, uri)
                else:
                    default_ns = uri
            if root is None:
                return found  # no element at all: the parser will say so
            f.seek(max(0, size - _TAIL))
            tail = f.read()
    except ET.ParseError:
        return found  # the real parser reports the error with its own message
    except OSError as exc:
        raise KBLoadError(path, exc.strerror or str(exc)) from exc
    uri, _, local = root.rpartition("}")
    uri = uri.lstrip("{")
    names = {f"{p}:{local}" for p, u in found.items() if u == uri}
    if uri == (default_ns or ""):
        names.add(local)
    # What may follow the root: whitespace, comments, processing instructions.
    body = tail.rstrip()
    while body.endswith((b"-->", b"?>")):
        start = body.rfind(b"<!--" if body.endswith(b"-->") else b"<?")
        if start < 0:
            break
        body = body[:start].rstrip()
    start = body.rfind(b"</")
    last = body[start + 2 : -1].strip().decode("utf-8", "replace") if start >= 0 and body.endswith(b">") else None
    if last not in names:
        if not (body.endswith(b"/>") and b"</" not in tail and size <= _TAIL):  # an empty <rdf:RDF/>
            expected = min(names) if names else local
            raise KBLoadError(path, f"truncated: the file does not end with the root element's end tag </{expected}>")
    return found


def _turtle_prefixes(data: bytes, found: dict[str, str]) -> None:
    """``@prefix``/``PREFIX`` lines of Turtle or N3 (whole lines) into ``found``."""
    if b"prefix" not in data.lower():
        return  # 5x faster than the regex on data without any: most chunks of a big file
    for m in _TURTLE_PREFIX.finditer(data):
        if m.group(1):
            found.setdefault(m.group(1).decode(), m.group(2).decode())


_CHUNK = 1 << 20


@dataclass
class KBFile:
    """A KB file as first seen: its format, what says it has not changed, and
    the prefixes it declares (the first declaration of a prefix wins; the
    default namespace is left out: every module has its own, so it names
    nothing across a multi-file KB)."""

    path: Path
    fmt: str
    size: int
    stamp: tuple[int, int, int, int]  # st_dev, st_ino, st_size, st_mtime_ns
    prefixes: dict[str, str]

    @classmethod
    def open(cls, path: Path) -> KBFile:
        try:
            with path.open("rb") as f:
                st = os.fstat(f.fileno())
                head = f.read(_TAIL)
        except OSError as exc:
            raise KBLoadError(path, exc.strerror or str(exc)) from exc
        fmt = _format_for(path, head)
        prefixes = _xml_root(path, st.st_size) if fmt == "xml" else {}
        return cls(path, fmt, st.st_size, _stamp(st), prefixes)

    def hash_into(self, digest: Digest, chunk_bytes: int = _CHUNK) -> None:
        """Feed the file's name, size and bytes to ``digest``; collect Turtle
        prefixes on the way.  Reads in chunks of ``chunk_bytes`` (hashlib
        releases the GIL), so it runs beside a parse on another thread
        without holding the file."""
        digest.update(self.path.name.encode() + b"\0" + self.size.to_bytes(8, "big"))
        turtle = self.fmt in ("turtle", "n3")
        carry = b""
        read = 0
        try:
            with self.path.open("rb") as f:
                while chunk := f.read(chunk_bytes):
                    read += len(chunk)
                    digest.update(chunk)
                    if turtle:
                        text = carry + chunk
                        cut = text.rfind(b"\n") + 1
                        _turtle_prefixes(text[:cut], self.prefixes)
                        carry = text[cut:]
        except OSError as exc:
            raise KBLoadError(self.path, exc.strerror or str(exc)) from exc
        if turtle and carry:
            _turtle_prefixes(carry, self.prefixes)
        if read != self.size:
            raise KBLoadError(self.path, "the file changed while it was being loaded")

    def check_unchanged(self) -> None:
        """The bytes hashed are the bytes parsed: the file was not modified or
        replaced while it was read twice (hash, parse)."""
        try:
            unchanged = _stamp(self.path.stat()) == self.stamp
        except OSError:
            unchanged = False
        if not unchanged:
            raise KBLoadError(self.path, "the file changed while it was being loaded")


def _stamp(st: os.stat_result) -> tuple[int, int, int, int]:
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns
