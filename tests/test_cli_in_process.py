"""``coapkb.cli.main`` called in this process, as the ``coapkb`` command runs
it: a user's mistakes end in one ``coapkb...: error`` line and an exit code,
never a traceback; a query against a server on loopback prints its answer.
(tests/test_cli.py runs the same command as a subprocess.)"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import KB_FILES, ONTOLOGIES, free_udp_port

from coapkb.cli import main
from coapkb.kb.resources import KBResources
from coapkb.kb.store import KnowledgeBase
from coapkb.transport import serve
from coapkb.transport.base import Endpoint
from coapkb.transport.router import Router


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``coapkb ARGV``: (exit code, stdout, stderr)."""
    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse and main's one-line error exit
        code = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_error_line(code: int, err: str, *fragments: str) -> str:
    """A non-zero exit and, after any usage text, exactly one error line naming ``fragments``."""
    assert code != 0
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("coapkb")]
    assert len(errors) == 1, err
    [line] = errors
    assert "usage:" in err or len(err.splitlines()) == 1, err
    for fragment in fragments:
        assert fragment in line, (fragment, line)
    return line


@pytest.fixture(scope="module")
def server() -> Iterator[Endpoint]:
    """The three warehouse KBs served over CoAP on loopback, by an event loop
    on a thread of this process (``main`` runs its own loop on this one)."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="kb-server", daemon=True)
    thread.start()

    async def start():  # type: ignore[no-untyped-def]
        router = Router()
        KBResources(KnowledgeBase.load(KB_FILES)).mount(router)
        return await serve(router, Endpoint("coap", "127.0.0.1", free_udp_port()))

    transport = asyncio.run_coroutine_threadsafe(start(), loop).result(timeout=60)
    try:
        yield transport.endpoint
    finally:
        asyncio.run_coroutine_threadsafe(transport.aclose(), loop).result(timeout=60)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=60)
        loop.close()


def test_a_named_query_prints_its_table(server: Endpoint, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "query", f"coap://{server.hostport}/kb/q/object-location?name=Gucci_bag_14")
    assert (code, err) == (0, "")
    assert "Warehouse_A" in out and out.rstrip().endswith("(1 row)")


def test_sparql_text_as_json(server: Endpoint, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "query", f"coap://{server.hostport}", "ASK { ?s ?p ?o }", "--format", "json")
    assert (code, err) == (0, "")
    assert json.loads(out) == {"head": {}, "boolean": True}


def test_a_server_error_is_one_line(server: Endpoint, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, "query", f"coap://{server.hostport}", "SELECT ?x WHERE { ?x ?p }")
    assert out == ""
    assert_one_error_line(code, err, "4.00", "malformed SPARQL")


def test_an_unreachable_peer_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    closed = free_udp_port()
    code, out, err = run(capsys, "query", f"coap://127.0.0.1:{closed}", "ASK {}", "--timeout", "5")
    assert (code, out) == (1, "")
    assert_one_error_line(code, err, str(closed))


CONFIG = """\
robot_id = "Robot1"
bind = "coap://127.0.0.1:0"
kb = ["{kb}"]
{extra}
[team.Robot1]
endpoint = "coap://127.0.0.1:5701"
kbs = ["Location"]
"""


@pytest.mark.parametrize(
    ("argv", "fragments"),
    [
        (["frobnicate"], ["invalid choice", "frobnicate"]),
        (["query"], ["uri"]),
        (["query", "coap://127.0.0.1:5683", "ASK {}", "--timeout", "soon"], ["--timeout", "soon"]),
        (["query", "coap://127.0.0.1:5683", "ASK {}", "--accept", "xml"], ["--accept", "xml"]),
        (["query", "htp://127.0.0.1:5683", "ASK {}"], ["htp"]),
        (["query", "coap://127.0.0.1:port", "ASK {}"], ["HOST:PORT"]),
        (["query", "coap://127.0.0.1:5683"], ["no query"]),
        (["query", "coap://127.0.0.1:5683/kb/q/object-exists?name=x", "ASK {}"], ["not both"]),
        (["query", "coap://127.0.0.1:5683", "@/nonexistent/q.rq"], ["/nonexistent/q.rq"]),
        (["serve", "--kb", "/nonexistent/kb.owl", "--bind", "127.0.0.1:0"], ["/nonexistent/kb.owl"]),
        (["serve", "--kb", str(ONTOLOGIES / "Capability.owl"), "--bind", "nonsense"], ["nonsense"]),
        (["serve", "--kb", str(ONTOLOGIES / "Capability.owl"), "--time-budget", "0"], ["time_budget"]),
        (["agent", "--config", "/nonexistent/robot.toml"], ["/nonexistent/robot.toml"]),
        (["team", "--robots", "4", "--tasks", "1"], ["multiple of 3"]),
        (["sim", "--seed", "1", "--observers", "2"], ["--observers", "--writes"]),
        (["sim", "--seed", "1", "--writes", "5", "--observers", "-1"], ["--observers", "negative"]),
    ],
)
def test_user_mistakes(argv: list[str], fragments: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(capsys, *argv)
    assert out == ""
    assert_one_error_line(code, err, *fragments)


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("robot_id = \n", ["TOML"]),
        (CONFIG.format(kb=ONTOLOGIES / "Location.owl", extra='strategy = "nope"'), ["strategy", "nope"]),
        (CONFIG.format(kb=ONTOLOGIES / "Location.owl", extra="") + "\n[start]\nbatery_wh = 10\n", ["batery_wh"]),
        (CONFIG.format(kb="/nonexistent/Location.owl", extra=""), ["kb[0]", "/nonexistent/Location.owl"]),
    ],
)
def test_bad_configurations(
    text: str, fragments: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(text)
    code, out, err = run(capsys, "agent", "--config", str(path))
    assert (code, out) == (2, "")
    assert_one_error_line(code, err, str(path), *fragments)


async def test_a_signal_on_the_ready_line_stops_a_server_cleanly() -> None:
    """A command prints its ready line inside ``stop_signals``: SIGINT or
    SIGTERM sent the moment the line is read, before the command's next
    statement, sets the stop event (it used to end the process with a
    KeyboardInterrupt, status 130, on a busy machine)."""
    import os
    import signal

    from coapkb.cli.common import stop_signals

    for sig in (signal.SIGINT, signal.SIGTERM):
        with stop_signals() as stopped:
            os.kill(os.getpid(), sig)  # as a supervisor would, on the ready line
            async with asyncio.timeout(5):
                await stopped.wait()
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # handed back on the way out
