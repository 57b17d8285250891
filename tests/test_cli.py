"""The ``coapkb`` command as a user sees it: ``python -m coapkb ...`` in a
subprocess, against a real server process.

Every user mistake must end in exactly one ``coapkb: ...`` line on stderr and
a non-zero exit, with no traceback anywhere.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import re
import socket
from collections.abc import AsyncIterator
from decimal import Decimal
from pathlib import Path

import pytest
import pytest_asyncio
from support import GRIPPING_ROBOTS, KB_FILES, ONTOLOGIES, CliResult, ServerProcess, coapkb, free_udp_port

pytestmark = pytest.mark.asyncio(loop_scope="module")


def assert_user_error(result: CliResult, *fragments: str) -> str:
    """One ``coapkb: ...`` line on stderr, non-zero exit, no traceback; returns the line."""
    assert "Traceback" not in result.stdout + result.stderr, result.stderr
    assert result.code != 0, result
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    [line] = lines
    assert line.startswith("coapkb: "), line
    for fragment in fragments:
        assert fragment in line, (fragment, line)
    return line


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server() -> AsyncIterator[ServerProcess]:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}")
    yield srv
    assert srv.proc.returncode is None
    await srv.stop()


@pytest.fixture
def uri(server: ServerProcess) -> str:
    return server.uri


def table(text: str) -> tuple[list[str], list[list[str]], str]:
    """The CLI's table: header, rows (split on 2+ spaces), footer line."""
    lines = text.rstrip("\n").splitlines()
    header = lines[0].split()
    assert set(lines[1].replace(" ", "")) == {"-"}
    rows = [re.split(r"\s{2,}", line.strip()) for line in lines[2:-1]]
    return header, rows, lines[-1]


# --------------------------------------------------------------------------- query


async def test_query_table(uri: str) -> None:
    result = await coapkb("query", f"{uri}/kb/q/object-location?name=Gucci_bag_14")
    assert result.code == 0, result.stderr
    assert result.stderr == ""
    header, rows, footer = table(result.stdout)
    assert header == ["loc", "warehouse", "aisle_no", "bin_no", "rack_no"]
    assert rows == [["loc:Warehouse_A", "Warehouse_A", "3", "3", "21"]]
    assert footer == "(1 row)"


async def test_query_sparql_text_every_method(uri: str, tmp_path: Path) -> None:
    text = ("PREFIX l: <http://www.tcs.org/2018/Location#>\n"
            "SELECT ?aisle ?rack ?bin WHERE { l:Gucci_bag_14 l:Inventory_aisle_no ?aisle ;"
            " l:Inventory_rack_no ?rack ; l:Inventory_bin_no ?bin }")
    (tmp_path / "q.rq").write_text(text)
    results = await asyncio.gather(
        *(coapkb("query", uri, text, *how)
          for how in (["--method", "fetch"], ["--method", "post"], ["--method", "get"], ["--accept", "json"])),
        coapkb("query", uri, f"@{tmp_path / 'q.rq'}"),
        coapkb("query", uri, "-", stdin=text),
    )
    assert all(r.code == 0 for r in results), [r.stderr for r in results]
    outputs = [r.stdout for r in results]
    assert len(set(outputs)) == 1, outputs
    header, rows, _ = table(outputs[0])
    assert header == ["aisle", "rack", "bin"] and rows == [["3", "21", "3"]]


async def test_query_json(uri: str) -> None:
    result = await coapkb("query", f"{uri}/kb/q/object-features?name=Gucci_bag_14", "--accept", "json",
                          "--format", "json")
    assert result.code == 0, result.stderr
    doc = json.loads(result.stdout)
    assert doc["head"]["vars"] == ["frag", "price", "color", "shape", "dim", "grip", "weight"]
    [b] = doc["results"]["bindings"]
    assert b["grip"] == {"type": "uri", "value": "http://www.tcs.org/2018/Object#gripping"}
    assert b["weight"]["type"] == "literal" and Decimal(b["weight"]["value"]) == Decimal("0.8")
    # the wire format does not change the printed answer
    via_cbor = await coapkb("query", f"{uri}/kb/q/object-features?name=Gucci_bag_14", "--format", "json")
    assert json.loads(via_cbor.stdout) == doc


async def test_query_ask(uri: str) -> None:
    result = await coapkb("query", uri, "ASK { ?s ?p ?o }")
    assert (result.code, result.stdout) == (0, "true\n")
    as_json = await coapkb("query", uri, "ASK { ?s ?p <urn:nothing> }", "--format", "json")
    assert json.loads(as_json.stdout) == {"head": {}, "boolean": False}


async def test_query_csv(uri: str) -> None:
    result = await coapkb("query", f"{uri}/kb/q/robots-for-grip?grip=gripping", "--format", "csv")
    assert result.code == 0, result.stderr
    assert result.stdout.endswith("\r\n")  # SPARQL 1.1 CSV uses CRLF
    rows = list(csv.reader(io.StringIO(result.stdout, newline="")))
    assert rows[0] == ["robots", "robo_id", "payload"]
    assert {r[1]: Decimal(r[2]) for r in rows[1:]} == GRIPPING_ROBOTS
    assert [r[1] for r in rows[1:]] == list(GRIPPING_ROBOTS)
    assert rows[1][0] == "http://www.tcs.org/2018/Capability#Robot1"


async def test_query_csv_says_when_the_server_truncated(uri: str) -> None:
    """CSV has no room for "more results exist" (the table's footer and
    SPARQL-JSON's "truncated" say it): one line on stderr does."""
    everything = await coapkb("query", uri, "SELECT ?s WHERE { ?s ?p ?o }", "--format", "csv")
    assert everything.code == 0, everything.stderr
    rows = list(csv.reader(io.StringIO(everything.stdout, newline="")))
    assert rows[0] == ["s"] and len(rows) == 1 + 1000  # the server's default row limit
    [line] = everything.stderr.splitlines()
    assert line.startswith("coapkb: ") and "truncated" in line and "1000 rows" in line, line
    few = await coapkb("query", uri, "SELECT ?s WHERE { ?s ?p ?o } LIMIT 3", "--format", "csv")
    assert (few.code, few.stderr) == (0, "")
    assert len(list(csv.reader(io.StringIO(few.stdout, newline="")))) == 1 + 3


async def test_query_over_zmq_matches(tmp_path: Path) -> None:
    from support import free_tcp_port

    port = free_tcp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--transport", "zmq", "--bind", f"127.0.0.1:{port}")
    try:
        result = await coapkb("query", f"zmq://127.0.0.1:{port}/kb/q/object-location?name=Gucci_bag_14")
        assert result.code == 0, result.stderr
        assert table(result.stdout)[1] == [["loc:Warehouse_A", "Warehouse_A", "3", "3", "21"]]
    finally:
        await srv.stop()


# --------------------------------------------------------------------------- query mistakes


QUERY_MISTAKES = [
    (["query", "htp://127.0.0.1:5683", "ASK {}"], ["htp"]),
    (["query", "coap://127.0.0.1:5", "ASK {}"], ["no answer from coap://127.0.0.1:5", "nothing listens"]),
    (["query", "coap://127.0.0.1:99999", "ASK {}"], ["port 99999 out of range (0-65535) in 'coap://127.0.0.1:99999'"]),
    (["query", "coap://127.0.0.1:http", "ASK {}"], ["expected HOST:PORT"]),
    (["query", "coap://127.0.0.1:5683/kb/other", "ASK {}"], ["/kb/other"]),
    (["query", "coap://127.0.0.1:5683"], ["no query"]),
    (["query", "coap://127.0.0.1:5683/kb/q/object-exists?name=x", "ASK {}"], ["not both"]),
    (["query", "coap://127.0.0.1:5683", "@/nonexistent/q.rq"], ["/nonexistent/q.rq"]),
]


async def check_mistakes(cases: list[tuple[list[str], list[str]]]) -> None:
    """Run the cases concurrently (each is a cold Python start), check each."""
    results = await asyncio.gather(*(coapkb(*args) for args, _ in cases))
    for (args, fragments), result in zip(cases, results):
        try:
            assert_user_error(result, *fragments)
            assert result.stdout == ""
        except AssertionError as exc:
            raise AssertionError(f"coapkb {' '.join(args)}: {exc}") from None


async def test_query_user_mistakes() -> None:
    await check_mistakes(QUERY_MISTAKES)


async def test_query_unreachable_peer() -> None:
    closed = free_udp_port()  # nobody listens: ICMP port unreachable
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:  # bound, never answers
        silent.bind(("127.0.0.1", 0))
        port = silent.getsockname()[1]
        to_closed, to_silent = await asyncio.gather(
            coapkb("query", f"coap://127.0.0.1:{closed}", "ASK {}", "--timeout", "2"),
            coapkb("query", f"coap://127.0.0.1:{port}", "ASK {}", "--timeout", "2"),
        )
    # A closed port fails on the ICMP error it sends back, not at the timeout; a silent one at the timeout.
    assert "within" not in assert_user_error(to_closed, str(closed))
    assert_user_error(to_silent, str(port), "within 2s")


async def test_query_server_errors_shown(uri: str) -> None:
    await check_mistakes([
        (["query", uri, "SELECT ?x WHERE { ?x ?p }"], ["4.00", "malformed SPARQL", "line 1, column"]),
        (["query", uri, "CLEAR ALL"], ["4.03"]),
        (["query", f"{uri}/kb/q/object-exists?name=x%22%20%7D"], ["4.00", "name"]),
        (["query", f"{uri}/kb/q/nope?x=1"], ["4.04"]),
    ])


async def test_query_misspelled_name_lists_the_named_queries(uri: str) -> None:
    result = await coapkb("query", f"{uri}/kb/q/object-locaton?name=Gucci_bag_14")
    assert_user_error(result, "4.04", "/kb/q/object-locaton", "object-location", "object-exists", "warehouse-layout")


# --------------------------------------------------------------------------- serve mistakes


async def test_serve_mistakes(tmp_path: Path) -> None:
    junk = []
    for suffix in (".owl", ".ttl"):
        path = tmp_path / f"junk{suffix}"
        path.write_bytes(b"<rdf:RDF this is <not> RDF \x00\xff\xfe {{{ ")
        junk.append(path)
    unknown = tmp_path / "kb.docx"
    unknown.write_text("hello")
    cap = KB_FILES[2]
    await check_mistakes([
        (["serve", "--kb", "nonexistent.owl", "--bind", "127.0.0.1:0"], ["nonexistent.owl"]),
        *((["serve", "--kb", str(p), "--bind", "127.0.0.1:0"], [p.name]) for p in junk),
        (["serve", "--kb", cap, str(junk[0]), "--bind", "127.0.0.1:0"], [junk[0].name]),
        (["serve", "--kb", str(unknown), "--bind", "127.0.0.1:0"], ["kb.docx"]),
        (["serve", "--kb", cap, "--bind", "nonsense"], ["nonsense"]),
        (["serve", "--kb", cap, "--bind", "127.0.0.1:70000"], ["70000"]),
        (["serve", "--kb", cap, "--bind", "no-such-host.invalid:5683"], ["no-such-host.invalid"]),
        (["serve", "--kb", cap, "--bind", "127.0.0.1:0", "--row-limit", "0"], ["row_limit"]),
        (["serve", "--kb", cap, "--bind", "127.0.0.1:0", "--time-budget", "0"], ["time_budget"]),
    ])


# --------------------------------------------------------------------------- agent and team mistakes


VALID_CONFIG = """\
robot_id = "Robot1"
bind = "coap://127.0.0.1:0"
kb = ["{kb}"]
strategy = "{strategy}"

[team.Robot1]
endpoint = "coap://127.0.0.1:5701"
kbs = ["Location"]
[team.Robot2]
endpoint = "coap://127.0.0.1:5702"
kbs = ["Object"]
[team.Robot3]
endpoint = "coap://127.0.0.1:5703"
kbs = ["Capability"]
"""


async def test_agent_mistakes(tmp_path: Path) -> None:
    location = ONTOLOGIES / "Location.owl"
    (tmp_path / "strategy.toml").write_text(VALID_CONFIG.format(kb=location, strategy="nope"))
    (tmp_path / "field.toml").write_text(VALID_CONFIG.format(kb=location, strategy="compute-by-all")
                                         + "\n[start]\nbatery_wh = 10\n")
    (tmp_path / "syntax.toml").write_text("robot_id = \n")
    (tmp_path / "kb.toml").write_text(VALID_CONFIG.format(kb="/nonexistent/Location.owl", strategy="compute-by-all"))
    await check_mistakes([
        (["agent", "--config", "/nonexistent/robot.toml"], ["/nonexistent/robot.toml"]),
        (["agent", "--config", str(tmp_path / "strategy.toml")], ["strategy", "nope"]),
        (["agent", "--config", str(tmp_path / "field.toml")], ["batery_wh"]),
        (["agent", "--config", str(tmp_path / "syntax.toml")], ["TOML"]),
        (["agent", "--config", str(tmp_path / "kb.toml")], ["kb[0]", "/nonexistent/Location.owl"]),
    ])


async def test_agent_refuses_a_start_outside_the_warehouse(tmp_path: Path) -> None:
    """Aisle 0 is refused as the file is read; an aisle past the Location
    KB's last, at start-up, by a robot holding that KB; keys not made yet
    name the command that makes them."""
    config = VALID_CONFIG.format(kb=ONTOLOGIES / "Location.owl", strategy="compute-by-all")
    (tmp_path / "aisle0.toml").write_text(config + "\n[start]\naisle = 0\n")
    (tmp_path / "far.toml").write_text(config + "\n[start]\naisle = 99\nrack = 3\n")
    (tmp_path / "keys.toml").write_text(config + '\n[security]\ncredentials = "keys"\n')
    await check_mistakes([
        (["agent", "--config", str(tmp_path / "aisle0.toml")], ["start: aisle 0", "outside the warehouse"]),
        (["agent", "--config", str(tmp_path / "far.toml")], ["start: aisle 99, rack 3", "aisles 1..10"]),
        (["agent", "--config", str(tmp_path / "keys.toml")], [f"coapkb keys --team-dir {tmp_path / 'keys'}"]),
    ])


async def test_team_mistakes() -> None:
    await check_mistakes([
        (["team", "--robots", "4", "--tasks", "1"], ["multiple of 3"]),
        (["team", "--robots", "3", "--tasks", "0"], ["--tasks"]),
        (["team", "--robots", "3", "--tasks-file", "/nonexistent/tasks.txt"], ["/nonexistent/tasks.txt"]),
        # Said of the option, not of a robot's configuration file in a temporary folder.
        (["team", "--robots", "3", "--tasks", "1", "--foxglove", "99999"], ["--foxglove: port 99999 out of range"]),
        (["team", "--robots", "3", "--tasks", "1", "--keep-serving"], ["--keep-serving goes with --foxglove"]),
        (["team", "--robots", "3", "--tasks", "1", "--credentials", "/nonexistent/nokeys/"],
         ["--credentials /nonexistent/nokeys/: no team.json in /nonexistent/nokeys;",
          "coapkb keys --team-dir /nonexistent/nokeys/"]),
        # Before the run, not after it.
        (["team", "--robots", "3", "--tasks", "1", "--record", "/nonexistent/dir/out.json"],
         ["--record: no folder /nonexistent/dir"]),
        # An unknown option of a subcommand points at that subcommand's usage.
        (["team", "--robots", "3", "--tasks", "1", "--robts", "3"], ["--robts", "(see coapkb team --help)"]),
    ])


async def test_bench_output_mistakes_before_any_run(tmp_path: Path) -> None:
    base = ["bench", "--robots", "3", "--tasks", "1", "--loss", "0", "--systems", "coap-distributed"]
    await check_mistakes([
        ([*base, "--bandwidth", "35", "--out", "/etc/passwd/x.csv"], ["/etc/passwd is not a folder"]),
        ([*base, "--bandwidth", "35", "--out", str(tmp_path)], ["is a folder"]),
        ([*base, "--bandwidth", "-5"], ["--bandwidth must be positive"]),
    ])


async def test_a_robot_that_does_not_start_is_said_so_once(tmp_path: Path) -> None:
    """Keys for Robot1 only: Robot2 refuses to start, and its own one-line
    error is passed on without a second "coapkb: error:"."""
    made = await coapkb("keys", "--team-dir", str(tmp_path / "keys"), "--robots", "1")
    assert made.code == 0, made.stderr
    run = await coapkb("team", "--robots", "3", "--tasks", "1", "--credentials", str(tmp_path / "keys"))
    assert run.code == 1 and "Traceback" not in run.stderr, run.stderr
    [line] = [line for line in run.stderr.splitlines() if "did not start" in line]
    assert line.count("coapkb:") == 1 and "error:" not in line, line
    assert line.endswith(f"is not in the team's trust list {tmp_path / 'keys' / 'team.json'}"), line


async def test_keys_warn_when_git_would_commit_them(tmp_path: Path) -> None:
    """Private keys one `git add -A` away from a commit are said so; once
    ignored (or outside a work tree) nothing is said."""
    import subprocess

    repo = tmp_path / "repo"
    repo.mkdir()
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    exposed = await coapkb("keys", "--team-dir", str(repo / "team"))
    assert exposed.code == 0 and "warning" in exposed.stderr and "git add -A" in exposed.stderr
    (repo / ".gitignore").write_text("/ignored/\n")
    quiet = await coapkb("keys", "--team-dir", str(repo / "ignored"))
    assert quiet.code == 0 and "warning" not in quiet.stderr
    outside = await coapkb("keys", "--team-dir", str(tmp_path / "keys"))
    assert outside.code == 0 and "warning" not in outside.stderr


async def test_keys_count_the_robots_apart_from_the_other_members(tmp_path: Path) -> None:
    made = await coapkb("keys", "--team-dir", str(tmp_path / "six"), "--robots", "6")
    assert made.code == 0, made.stderr
    assert made.stdout.startswith(f"6 robots and 3 other members in {tmp_path / 'six'}: Robot1 (robot), "), made.stdout
    assert "Robot6 (robot), feeder (feeder), central (server), operator (client)\n" in made.stdout


async def test_dump_writes_a_module_as_sorted_n_triples(uri: str, tmp_path: Path) -> None:
    """``coapkb dump --module``: the module's triples as the robot holds them
    (those whose subject is in its namespace, and its ontology's header), one
    sorted N-Triples line each."""
    import rdflib

    out = tmp_path / "capability.nt"
    result = await coapkb("dump", uri, "--module", "Capability", "--out", str(out))
    assert result.code == 0, result.stderr
    lines = out.read_text(encoding="utf-8").splitlines()
    assert lines == sorted(lines) and re.fullmatch(rf"{len(lines)} triples, \d+ bytes, version [0-9a-f]+\n",
                                                   result.stderr)
    dumped = rdflib.Graph().parse(out, format="nt")
    source = rdflib.Graph().parse(ONTOLOGIES / "Capability.owl")
    module = "http://www.tcs.org/2018/Capability"  # the ontology's IRI, and its namespace after it
    assert set(dumped) == {t for t in source if str(t[0]).startswith(module)}
    mistake = await coapkb("dump", uri, "--module", "Robots")
    assert mistake.code == 2 and "invalid choice" in mistake.stderr and "Traceback" not in mistake.stderr
