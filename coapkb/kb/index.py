"""The on-disk KB index: an Oxigraph store built once from a KB's files,
named by their content, then opened read-only by every later start."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pyoxigraph as ox

from .errors import KBLoadError, short_message
from .formats import KBFile
from .oxigraph_backend import OxigraphBackend

#: Written last into a built index: an index without it is not complete.
_INDEX_MANIFEST = "coapkb-index.json"


def open_or_build_index(path: Path, files: list[KBFile]) -> OxigraphBackend:
    """Open the on-disk index at ``path`` read-only, building it first if
    it does not exist (robots of one host may share an index directory)."""
    manifest = path / _INDEX_MANIFEST
    if not manifest.exists():
        _build_index(path, files)
    try:
        triples = int(json.loads(manifest.read_text())["triples"])
        store = ox.Store.read_only(str(path))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise KBLoadError(path, f"unreadable KB index ({short_message(exc)}); delete it to have it rebuilt") from exc
    return OxigraphBackend(store, triples)


def _build_index(path: Path, files: list[KBFile]) -> None:
    """Build the index in a private directory beside ``path`` and move it
    into place only when complete, so a crash or a concurrent builder never
    leaves a half-built index under the final name."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        building = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    except OSError as exc:
        raise KBLoadError(path.parent, f"cannot create the KB index: {exc.strerror or exc}") from exc
    try:
        engine = OxigraphBackend(ox.Store(str(building)))
        for f in files:
            engine.load(f.path, f.fmt)
        for f in files:  # the index must hold the bytes its name hashes
            f.check_unchanged()
        engine.store.optimize()
        triples = len(engine.store)
        engine.store.flush()
        del engine  # closes the store before its directory moves
        manifest = {"triples": triples, "oxigraph": ox.__version__, "files": [str(f.path) for f in files]}
        (building / _INDEX_MANIFEST).write_text(json.dumps(manifest))
        try:
            building.rename(path)
        except OSError:
            if not (path / _INDEX_MANIFEST).exists():
                raise
            # Another robot built the same index meanwhile: keep theirs.
    except OSError as exc:
        raise KBLoadError(path, f"cannot build the KB index: {exc.strerror or exc}") from exc
    finally:
        shutil.rmtree(building, ignore_errors=True)

