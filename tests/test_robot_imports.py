"""A robot imports only what it uses: its transport, its KB back-end, no
benchmark or plotting libraries.  Each check runs in a fresh interpreter
and reads ``sys.modules`` there (this test process has imported everything)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from coapkb.security import generate_team
from coapkb.security.keys import default_members

ROOT = Path(__file__).resolve().parent.parent

#: Never needed by a robot on CoAP with the oxigraph back-end.  rdflib
#: itself is: its terms are the query results' terms; its SPARQL engine
#: (and pyparsing, which it needs) is not.
NOT_FOR_A_COAP_ROBOT = (
    "zmq", "zenoh", "cyclonedds", "numpy", "pandas", "matplotlib", "tqdm", "dask", "scipy",
    "rdflib.plugins.sparql", "pyparsing", "foxglove", "mcap", "coapkb.harness.recording",
    "coapkb.transport.zmq", "coapkb.transport.zenoh", "coapkb.transport.dds", "coapkb.security.curve", "coapkb.security.zenoh_tls",
    "coapkb.kb.rdflib_backend",
)


def _loaded_after(code: str) -> set[str]:
    """The modules loaded in a fresh interpreter after running ``code``."""
    script = f"{code}\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return set(json.loads(done.stdout.splitlines()[-1]))


def _unwanted(modules: set[str]) -> list[str]:
    return sorted(name for name in NOT_FOR_A_COAP_ROBOT if name in modules)


def test_importing_the_robot_loads_no_other_transport_and_no_analysis_library() -> None:
    modules = _loaded_after("import coapkb.agent.robot")
    assert _unwanted(modules) == []


def test_a_coap_robot_process_loads_only_its_transport_and_back_end(tmp_path: Path) -> None:
    """What ``coapkb agent`` loads on CoAP with OSCORE: the command line
    (the agent's options only, as :func:`coapkb.cli.main` builds it), the robot, the CoAP transport and its
    security, the team's keys, and a KB on oxigraph."""
    team = tmp_path / "team"
    generate_team(team, default_members(3))
    modules = _loaded_after(
        "import coapkb.cli as cli\n"
        "cli.build_parser(only='agent')\n"
        "import coapkb.agent.robot, coapkb.transport.coap, coapkb.security.coap\n"
        "from coapkb.security import load_identity\n"
        "from coapkb.kb.store import KnowledgeBase\n"
        f"load_identity({str(team)!r}, 'Robot1')\n"
        "KnowledgeBase.load(['ontologies/Capability.owl']).query('SELECT ?s WHERE { ?s ?p ?o } LIMIT 1')\n"
    )
    assert _unwanted(modules) == []
    assert not {m for m in modules if m.startswith(("coapkb.bench", "coapkb.harness", "coapkb.feeder"))}
    assert {"aiocoap", "pyoxigraph", "coapkb.transport.coap", "coapkb.security.coap"} <= modules


def test_the_rdflib_back_end_is_loaded_when_chosen() -> None:
    modules = _loaded_after(
        "from coapkb.kb.store import KnowledgeBase\n"
        "KnowledgeBase.load(['ontologies/Capability.owl'], backend='rdflib')\n"
    )
    assert "coapkb.kb.rdflib_backend" in modules


def test_the_command_line_does_not_load_the_benchmark_libraries() -> None:
    modules = _loaded_after("import coapkb.cli as cli\ncli.build_parser()")
    assert not {"numpy", "pandas", "tqdm", "matplotlib"} & modules


def test_the_agent_command_builds_only_its_own_options() -> None:
    """``coapkb agent`` never imports the benchmark's systems to build its
    parser; ``coapkb bench`` does (its options name them)."""
    from coapkb.cli import _command

    assert _command(["-v", "agent", "--config", "x"]) == "agent"
    assert _command(["--help"]) is None
    modules = _loaded_after(
        "import coapkb.cli as cli\n"
        "try:\n    cli.main(['agent', '--config', '/nonexistent/robot.toml'])\nexcept SystemExit:\n    pass\n"
    )
    assert "coapkb.cli.agent" in modules and "coapkb.bench.run" not in modules
