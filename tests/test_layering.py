"""The package layering, read from the source: the transport is the floor
(it imports nothing above it, not even inside a function), and which
transport is which is the registry's business, not a scheme name compared
somewhere above it."""

from __future__ import annotations

import ast
from pathlib import Path

from coapkb.transport.registry import REGISTERED

PACKAGE = Path(__file__).resolve().parent.parent / "coapkb"
#: What lies above the transport.
ABOVE_TRANSPORT = frozenset({
    "security", "kb", "agent", "harness", "bench", "discovery", "world", "config", "cli", "feeder", "sim", "host",
})
#: Scheme comparisons tolerated outside transport/.
MAX_SCHEME_COMPARISONS = 2


def _sources(under: Path) -> list[tuple[Path, ast.Module]]:
    return [(f, ast.parse(f.read_text(), str(f))) for f in sorted(under.rglob("*.py"))]


def _imported(path: Path, node: ast.Import | ast.ImportFrom) -> list[str]:
    """The modules ``node`` imports, relative to the ``coapkb`` package where they are in it."""
    if isinstance(node, ast.Import):
        return [alias.name.removeprefix("coapkb.") for alias in node.names]
    if node.level == 0:
        return [(node.module or "").removeprefix("coapkb.")]
    package = list(path.relative_to(PACKAGE).parts[:-1])
    base = package[: len(package) - (node.level - 1)]
    return [".".join(base + ([node.module] if node.module else []))]


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


def test_the_transport_imports_nothing_above_it() -> None:
    upward = []
    for path, tree in _sources(PACKAGE / "transport"):
        for node in ast.walk(tree):  # module level and inside functions alike
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                upward += [f"{path.relative_to(PACKAGE)}:{node.lineno} imports {module}"
                           for module in _imported(path, node) if module.split(".")[0] in ABOVE_TRANSPORT]
    assert upward == []


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
    """The two checks above would find an upward import inside a function and a comparison."""
    source = "def f(x):\n    from ...security.coap import ClientSecurity\n    return x == 'zenoh+udp'\n"
    path = PACKAGE / "transport" / "coap" / "example.py"
    tree = ast.parse(source)
    imports = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert _imported(path, imports[0]) == ["security.coap"]
    assert _scheme_comparisons(path, tree, _scheme_names()) == ["transport/coap/example.py:3"]


#: What wire/ (the KB payloads' pure codecs) may import: the error root and
#: the data model it encodes, nothing of the KB, the transport or above.
WIRE_MAY_IMPORT = frozenset({"errors", "model", "wire"})


def test_wire_is_pure_codecs_over_the_data_model() -> None:
    found = []
    for path, tree in _sources(PACKAGE / "wire"):
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                found += [f"{path.relative_to(PACKAGE)}:{node.lineno} imports {module}"
                          for module in _imported(path, node)
                          if _inside_package(module)
                          and not any(module == m or module.startswith(m + ".") for m in WIRE_MAY_IMPORT)]
    assert found == []


def _inside_package(module: str) -> bool:
    return (PACKAGE / module.split(".")[0]).exists() or (PACKAGE / f"{module.split('.')[0]}.py").exists()


def test_no_module_of_security_imports_one_that_imports_it() -> None:
    imports: dict[str, set[str]] = {}
    for path, tree in _sources(PACKAGE / "security"):
        module = "security." + path.stem if path.stem != "__init__" else "security"
        imports[module] = {m for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))
                           for m in _imported(path, node) if m.startswith("security.")}
    cycles = sorted(f"{a} <-> {b}" for a, deps in imports.items() for b in deps if a in imports.get(b, set()) and a < b)
    assert cycles == []
