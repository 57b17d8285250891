"""The package layering, read from the source and held to the layers
``docs/architecture.md`` lists: every import is an arrow (at module level,
inside a function, or for type checking only), no arrow points up or
sideways against the list, and no module imports one that imports it,
however far round.  Which transport is which is the registry's business,
not a scheme name compared somewhere above it."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

from coapkb.transport.registry import REGISTERED

PACKAGE = Path(__file__).resolve().parent.parent / "coapkb"
ARCHITECTURE = PACKAGE.parent / "docs" / "architecture.md"
#: Scheme comparisons tolerated outside transport/.
MAX_SCHEME_COMPARISONS = 2

Graph = Mapping[str, frozenset[str]]


def _sources(under: Path) -> list[tuple[Path, ast.Module]]:
    return [(f, ast.parse(f.read_text(), str(f))) for f in sorted(under.rglob("*.py"))]


def _module_name(path: Path) -> str:
    """``kb.store`` for ``coapkb/kb/store.py``, ``kb`` for its ``__init__.py``."""
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(path: Path, node: ast.Import | ast.ImportFrom) -> list[str]:
    """What ``node`` names, relative to the ``coapkb`` package where it is in
    it: a module, or a name a module defines (``from .x import y`` gives
    ``x.y``, which :func:`_resolve` brings back to ``x`` unless ``y`` is a module)."""
    if isinstance(node, ast.Import):
        return [alias.name.removeprefix("coapkb.") for alias in node.names]
    if node.level == 0:
        base = [] if node.module == "coapkb" else [(node.module or "").removeprefix("coapkb.")]
    else:
        package = list(path.relative_to(PACKAGE).parts[:-1])
        base = package[: len(package) - (node.level - 1)] + ([node.module] if node.module else [])
    return [".".join([*base, alias.name]) for alias in node.names]


def _resolve(name: str, modules: Iterable[str]) -> str | None:
    """The module of the package ``name`` is or lies in (its longest prefix that is one)."""
    known = set(modules)
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


def _graph(sources: Iterable[tuple[str, Path, ast.Module]]) -> dict[str, frozenset[str]]:
    """Each module's arrows: the modules of coapkb it imports anywhere in its text."""
    sources = list(sources)
    modules = [name for name, _, _ in sources]
    graph = {}
    for name, path, tree in sources:
        arrows = set()
        for node in ast.walk(tree):  # module level, functions and ``if TYPE_CHECKING:`` alike
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                if isinstance(node, ast.ImportFrom) and node.level == 0 and not (node.module or "").startswith("coapkb"):
                    continue
                if isinstance(node, ast.Import) and not any(a.name.startswith("coapkb") for a in node.names):
                    continue
                arrows |= {m for imported in _imported(path, node) if (m := _resolve(imported, modules))}
        graph[name] = frozenset(arrows - {name})
    return graph


def _package_graph() -> dict[str, frozenset[str]]:
    return _graph((_module_name(path), path, tree) for path, tree in _sources(PACKAGE) if _module_name(path))


def _circles(graph: Graph) -> list[list[str]]:
    """The strongly connected parts of ``graph`` with more than one module:
    in each, every module imports, however far round, one that imports it."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(start: str) -> None:  # Tarjan's, iteratively
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        while work:
            node, arrows = work[-1]
            for target in arrows:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    work.append((target, iter(sorted(graph.get(target, ())))))
                    break
                if target in stack:
                    low[node] = min(low[node], index[target])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    part = []
                    while True:
                        member = stack.pop()
                        part.append(member)
                        if member == node:
                            break
                    if len(part) > 1:
                        found.append(sorted(part))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def _documented_layers(text: str) -> list[list[str]]:
    """The packages of each row of the table under ``## Layers``, top row
    first, in the order the row names them (``cli/`` -> ``cli``,
    ``config.py`` -> ``config``)."""
    section = text.split("\n## Layers\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("|")][2:]  # past the header and its rule
    return [[name.rstrip("/").removesuffix(".py") for name in re.findall(r"`([^`]+)`", row.split("|")[2])]
            for row in rows]


def _upward(graph: Graph, layers: list[list[str]]) -> list[str]:
    """The arrows between packages that point up the layers or against the
    order of a row: a package imports only the packages to its right in its
    row and those in the rows below."""
    place = {package: (row, column) for row, packages in enumerate(layers) for column, package in enumerate(packages)}
    found = []
    for module, arrows in sorted(graph.items()):
        for target in sorted(arrows):
            here, there = module.split(".")[0], target.split(".")[0]
            if here != there and place[there] <= place[here]:
                found.append(f"{module} -> {target}")
    return found


def _packages() -> set[str]:
    """The top-level packages and modules of coapkb (``kb``, ``config``, ``__main__``)."""
    return {p.name if p.is_dir() else p.stem for p in PACKAGE.iterdir()
            if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem != "__init__")}


def test_the_documented_layers_name_every_package_once() -> None:
    layers = _documented_layers(ARCHITECTURE.read_text())
    named = [package for row in layers for package in row]
    assert sorted(named) == sorted(_packages())


def test_no_import_points_up_the_documented_layers() -> None:
    """Module level, inside functions and for type checking only."""
    assert _upward(_package_graph(), _documented_layers(ARCHITECTURE.read_text())) == []


def test_no_module_imports_one_that_imports_it() -> None:
    assert _circles(_package_graph()) == []


def _scheme_names() -> set[str]:
    """The registered schemes (``coap``, ``coap://``) and the names of their security mechanisms."""
    names = {t.scheme for t in REGISTERED}
    return names | {f"{name}://" for name in names} | {t.security for t in REGISTERED if t.security}


def _names_a_scheme(node: ast.AST, schemes: set[str]) -> bool:
    return any(isinstance(sub, ast.Constant) and sub.value in schemes for sub in ast.walk(node))


def _scheme_comparisons(path: Path, tree: ast.Module, schemes: set[str]) -> list[str]:
    """``x == "coap"``, ``x in ("zmq", "zenoh")``, ``uri.startswith("coap://")`` and the like."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare) and any(_names_a_scheme(c, schemes) for c in (node.left, *node.comparators)):
            found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr in ("startswith", "endswith") and any(_names_a_scheme(a, schemes) for a in node.args)):
            found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    return found


def test_nothing_above_the_transport_compares_scheme_names() -> None:
    schemes = _scheme_names()
    found: dict[str, list[str]] = {}
    for path, tree in _sources(PACKAGE):
        module = path.relative_to(PACKAGE).as_posix()
        if not module.startswith("transport/"):
            found[module] = _scheme_comparisons(path, tree, schemes)
    counted = [where for module, places in found.items() for where in places]
    assert len(counted) <= MAX_SCHEME_COMPARISONS, counted


def test_the_checks_see_what_they_look_for() -> None:
    """An upward import inside a function, a circle made of imports for type
    checking only, and a scheme comparison are all found."""
    sources = {
        "transport/coap/example.py": "def f(x):\n    from ...security.coap import ClientSecurity\n"
                                     "    return x == 'zenoh+udp'\n",
        "security/coap.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .keys import Identity\n",
        "security/keys.py": "from coapkb.security import coap\nfrom coapkb import errors\n",
        "security/__init__.py": "",
        "errors.py": "",
    }
    parsed = {_module_name(PACKAGE / path): (PACKAGE / path, ast.parse(text)) for path, text in sources.items()}
    graph = _graph((name, path, tree) for name, (path, tree) in parsed.items())
    assert graph["transport.coap.example"] == {"security.coap"}
    assert graph["security.keys"] == {"security.coap", "errors"}
    assert _circles(graph) == [["security.coap", "security.keys"]]
    assert _upward(graph, [["transport"], ["security"], ["errors"]]) == []
    assert _upward(graph, [["transport", "security"], ["errors"]]) == []
    assert _upward(graph, [["security"], ["transport"], ["errors"]]) == ["transport.coap.example -> security.coap"]
    assert _upward(graph, [["security", "transport"], ["errors"]]) == ["transport.coap.example -> security.coap"]
    assert _upward(graph, [["errors"], ["security"], ["transport"]]) == [
        "security.keys -> errors", "transport.coap.example -> security.coap"]
    path, tree = parsed["transport.coap.example"]
    assert _scheme_comparisons(path, tree, _scheme_names()) == ["transport/coap/example.py:3"]


def test_the_table_is_read_as_written() -> None:
    table = ("# T\n\n## Layers\n\n| layer | packages | what |\n|---|---|---|\n"
             "| top | `cli/`, `__main__.py` | x `not/this` |\n| floor | `errors.py` | y |\n\n## Next\n| a | `b/` | c |\n")
    assert _documented_layers(table) == [["cli", "__main__"], ["errors"]]
