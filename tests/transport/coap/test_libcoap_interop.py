"""Interoperability with an independent CoAP implementation: libcoap's
``coap-client-notls`` (Debian libcoap3-bin) against ``coapkb serve``.

Binary answers are read from ``-o FILE`` (on stdout coap-client appends a
newline).  coap-client 4.3.x reports an error response on stderr as
``<code> <diagnostic>`` (e.g. ``4.00 malformed SPARQL: ...``), writes no
output file, and still exits 0, so the tests check stderr, not the status.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from rdflib import URIRef
from support import GRIPPING_ROBOTS, KB_FILES, ServerProcess, free_udp_port, require_libcoap, varied_query

from coapkb.kb.named_queries import NAMED_QUERIES
from coapkb.kb.store import KnowledgeBase
from coapkb.model.results import SelectResult
from coapkb.transport import open_client
from coapkb.transport.messages import Method, Request, Status
from coapkb.transport.registry import parse_endpoint
from coapkb.wire import codec

pytestmark = [pytest.mark.libcoap, pytest.mark.asyncio(loop_scope="module")]

OBJ = "http://www.tcs.org/2018/Object#"
CAP = "http://www.tcs.org/2018/Capability#"


BIG = "SELECT * WHERE { ?s ?p ?o } LIMIT 100"


@pytest.fixture
def coap_client() -> str:
    return require_libcoap()


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def server() -> AsyncIterator[ServerProcess]:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}")
    yield srv
    assert srv.proc.returncode is None, "the server died during the tests"
    await srv.stop()


@pytest.fixture
def base(server: ServerProcess) -> str:
    return server.uri  # coap://127.0.0.1:PORT


class Run:
    def __init__(self, returncode: int, stdout: bytes, stderr: bytes, output: bytes | None) -> None:
        self.returncode = returncode
        self.stdout = stdout
        self.stderr = stderr
        self.output = output  # the -o file, None if coap-client wrote none

    @property
    def error(self) -> str:
        return self.stderr.decode(errors="replace").strip()


#: Numbers the output files of coap-client runs.
_OUTPUTS = itertools.count()


async def coap(binary: str, tmp_path: Path, *args: str, out: bool = True) -> Run:
    """Run coap-client with a 30 s break (-B) and a hard 60 s limit: bounds
    on a hang, long enough for a busy machine's server."""
    # A name of its own: runs at once (the concurrent test) named their output
    # by counting the folder, and two could count alike before either wrote.
    output = tmp_path / f"out-{next(_OUTPUTS)}.bin"
    argv = [binary, "-B", "30", *(("-o", str(output)) if out else ()), *args]
    proc = await asyncio.create_subprocess_exec(
        *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    try:
        stdout, stderr = await asyncio.wait_for(proc.communicate(), 60)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    return Run(proc.returncode or 0, stdout, stderr, output.read_bytes() if output.exists() else None)


def query_file(tmp_path: Path, text: str, name: str = "query.rq") -> str:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


async def aiocoap_payload(base: str, request: Request) -> bytes:
    """The same request through coapkb's own (aiocoap) client, for comparison."""
    transport = await open_client("coap")
    try:
        response = await transport.request(parse_endpoint(base), request, timeout=10)
    finally:
        await transport.aclose()
    assert response.status == Status.CONTENT, response.text()
    return response.payload


def check_gripping_robots(result: SelectResult) -> None:
    assert isinstance(result, SelectResult)
    rows = result.as_dicts()
    assert [str(r["robo_id"]) for r in rows] == list(GRIPPING_ROBOTS)
    assert {str(r["robo_id"]): r["payload"].toPython() for r in rows} == GRIPPING_ROBOTS
    assert all(r["robots"] == URIRef(CAP + str(r["robo_id"])) for r in rows)


# --------------------------------------------------------------------------- discovery


async def test_discovery(coap_client: str, base: str, tmp_path: Path) -> None:
    run = await coap(coap_client, tmp_path, "-m", "get", f"{base}/.well-known/core", out=False)
    assert run.returncode == 0, run.error
    links = run.stdout.decode()
    assert '</kb/sparql>;rt="sparql";ct="60 50"' in links
    assert "</kb>;" in links
    for name in ("object-exists", "object-location", "object-features", "robots-for-grip"):
        assert f'</kb/q/{name}>;rt="coapkb.q";ct="60 50"' in links

    run = await coap(coap_client, tmp_path, "-m", "get", f"{base}/.well-known/core?rt=sparql", out=False)
    assert run.stdout.decode().strip().startswith('</kb/sparql>;rt="sparql"')
    assert "</kb/q/" not in run.stdout.decode()


# --------------------------------------------------------------------------- SPARQL over FETCH/POST


@pytest.mark.parametrize("method", ["fetch", "post"])
async def test_cbor_answer(coap_client: str, base: str, tmp_path: Path, method: str) -> None:
    text = NAMED_QUERIES["robots-for-grip"].render({"grip": "gripping"})
    run = await coap(coap_client, tmp_path, "-m", method, "-t", "0", "-A", "60",
                     "-f", query_file(tmp_path, text), f"{base}/kb/sparql")
    assert run.output is not None, run.error
    check_gripping_robots(codec.decode_cbor(run.output))
    # byte for byte what coapkb's own client gets
    assert run.output == await aiocoap_payload(
        base, Request(Method.FETCH, "/kb/sparql", payload=text.encode(), content_format=0, accept=60)
    )


async def test_json_answer(coap_client: str, base: str, tmp_path: Path) -> None:
    text = NAMED_QUERIES["object-location"].render({"name": "Gucci_bag_14"})
    run = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-A", "50",
                     "-f", query_file(tmp_path, text), f"{base}/kb/sparql")
    assert run.output is not None, run.error
    doc = json.loads(run.output)
    assert doc["head"]["vars"] == ["loc", "warehouse", "aisle_no", "bin_no", "rack_no"]
    [binding] = doc["results"]["bindings"]
    assert binding["warehouse"] == {"type": "literal", "value": "Warehouse_A"}
    assert (int(binding["aisle_no"]["value"]), int(binding["rack_no"]["value"]), int(binding["bin_no"]["value"])) == (
        3, 21, 3)


async def test_ask_both_formats(coap_client: str, base: str, tmp_path: Path) -> None:
    rq = query_file(tmp_path, f"ASK {{ <{OBJ}Gucci_bag_14> ?p ?o }}")
    as_cbor = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-A", "60", "-f", rq, f"{base}/kb/sparql")
    assert as_cbor.output == b"\xf5"  # CBOR true, exactly one byte
    as_json = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-A", "50", "-f", rq, f"{base}/kb/sparql")
    assert as_json.output is not None and json.loads(as_json.output)["boolean"] is True


# --------------------------------------------------------------------------- named queries


async def test_named_query(coap_client: str, base: str, tmp_path: Path) -> None:
    run = await coap(coap_client, tmp_path, "-m", "get", "-A", "60", f"{base}/kb/q/object-exists?name=Gucci_bag_14")
    assert run.output is not None, run.error
    result = codec.decode_cbor(run.output)
    assert result.as_dicts() == [{"object": URIRef(OBJ + "Gucci_bag_14"), "class": URIRef(OBJ + "PersonalItems")}]

    run = await coap(coap_client, tmp_path, "-m", "get", "-A", "50", f"{base}/kb/q/robots-for-grip?grip=gripping")
    assert run.output is not None, run.error
    check_gripping_robots(codec.decode_json(run.output))


# --------------------------------------------------------------------------- block-wise


async def test_blockwise_answer(coap_client: str, base: str, tmp_path: Path) -> None:
    rq = query_file(tmp_path, BIG)
    default = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-A", "50", "-f", rq, f"{base}/kb/sparql")
    assert default.output is not None, default.error
    assert len(default.output) > 1024
    assert len(json.loads(default.output)["results"]["bindings"]) == 100
    small = await coap(coap_client, tmp_path, "-b", "64", "-m", "fetch", "-t", "0", "-A", "50", "-f", rq,
                       f"{base}/kb/sparql")
    assert small.output == default.output  # 64-byte blocks (~360 of them), same bytes
    cbor = await coap(coap_client, tmp_path, "-b", "64", "-m", "fetch", "-t", "0", "-A", "60", "-f", rq,
                      f"{base}/kb/sparql")
    assert cbor.output is not None and len(cbor.output) > 64
    assert codec.decode_cbor(cbor.output) == codec.decode_json(default.output)
    assert default.output == await aiocoap_payload(
        base, Request(Method.FETCH, "/kb/sparql", payload=BIG.encode(), content_format=0, accept=50)
    )


async def test_blockwise_query_upload(coap_client: str, base: str, tmp_path: Path) -> None:
    """A 3000-byte query goes up in Block1 blocks and its answer comes down in Block2."""
    tail = "\n" + BIG
    rq = query_file(tmp_path, "#" + "x" * (3000 - 1 - len(tail)) + tail)
    run = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-A", "50", "-f", rq, f"{base}/kb/sparql")
    assert run.output is not None, run.error
    assert len(json.loads(run.output)["results"]["bindings"]) == 100


# --------------------------------------------------------------------------- errors


async def test_errors(coap_client: str, base: str, tmp_path: Path) -> None:
    malformed = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-A", "60",
                           "-f", query_file(tmp_path, "SELECT ?x WHERE { ?x ?p }"), f"{base}/kb/sparql")
    assert malformed.output is None
    assert malformed.error.startswith("4.00 malformed SPARQL: line 1, column"), malformed.error

    update = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0",
                        "-f", query_file(tmp_path, "CLEAR ALL", "u.rq"), f"{base}/kb/sparql")
    assert update.error.startswith("4.03"), update.error

    tail = "\nASK {}"
    big = query_file(tmp_path, "#" + "x" * (9000 - 1 - len(tail)) + tail, "big.rq")
    too_big = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "0", "-f", big, f"{base}/kb/sparql")
    assert too_big.error.startswith("4.13") and "9000" in too_big.error, too_big.error

    accept = await coap(coap_client, tmp_path, "-A", "41", f"{base}/kb/q/object-exists?name=Gucci_bag_14")
    assert accept.error.startswith("4.06"), accept.error
    assert accept.output is None

    cbor_body = await coap(coap_client, tmp_path, "-m", "fetch", "-t", "60", "-e", "ASK {}", f"{base}/kb/sparql")
    assert cbor_body.error.startswith("4.15"), cbor_body.error

    param = await coap(coap_client, tmp_path, f"{base}/kb/q/object-exists?name=a%22%20%7D")
    assert param.error.startswith("4.00"), param.error

    missing = await coap(coap_client, tmp_path, f"{base}/nothing/here")
    assert missing.error.startswith("4.04"), missing.error

    delete = await coap(coap_client, tmp_path, "-m", "delete", f"{base}/kb/sparql")
    assert delete.error.startswith("4.05"), delete.error

    # and the server is still fine
    ok = await coap(coap_client, tmp_path, "-A", "60", f"{base}/kb/q/object-exists?name=Gucci_bag_14")
    assert ok.output is not None and codec.decode_cbor(ok.output).rows


# --------------------------------------------------------------------------- block-wise from one endpoint


@pytest.fixture(scope="module")
def local_kb() -> KnowledgeBase:
    """The server's KBs, loaded here: every answer is compared with the KB's own result."""
    return KnowledgeBase.load(KB_FILES)


async def test_large_questions_in_a_row_from_one_port(
    coap_client: str, base: str, tmp_path: Path, local_kb: KnowledgeBase
) -> None:
    """coap-client sends Block2 follow-ups without the body.  With ``-p`` every
    run has the same source port, so the server sees one client endpoint
    asking different multi-block FETCH and POST questions one after another."""
    port = str(free_udp_port())
    multi_block = 0
    for i in range(8):
        text = varied_query(i)
        method = ("fetch", "post")[i % 2]
        run = await coap(coap_client, tmp_path, "-p", port, "-m", method, "-t", "0", "-A", "50",
                         "-f", query_file(tmp_path, text, f"q{i}.rq"), f"{base}/kb/sparql")
        assert run.output is not None, (i, run.error)
        assert codec.decode_json(run.output) == local_kb.query(text), text
        multi_block += len(run.output) > 1024
    assert multi_block >= 5, "the test would prove little without multi-block answers"


async def test_large_questions_concurrently_from_many_ports(
    coap_client: str, base: str, tmp_path: Path, local_kb: KnowledgeBase
) -> None:
    """Six client endpoints (fixed ports), each asking three questions in a row, all at once."""
    async def user(n: int) -> None:
        port = str(free_udp_port())
        for i in range(3):
            text = varied_query(n * 3 + i)
            run = await coap(coap_client, tmp_path, "-p", port, "-m", "fetch", "-t", "0", "-A", "50",
                             "-f", query_file(tmp_path, text, f"u{n}-{i}.rq"), f"{base}/kb/sparql")
            assert run.output is not None, (n, i, run.error)
            assert codec.decode_json(run.output) == local_kb.query(text), text

    await asyncio.gather(*(user(n) for n in range(6)))


# --------------------------------------------------------------------------- writes (RFC 8132 PATCH)

LOC = "http://www.tcs.org/2018/Location#"
MOVE = (f"PREFIX loc: <{LOC}> DELETE {{{{ loc:Robot2 loc:Robot_rack_no ?r }}}} "
        "INSERT {{ loc:Robot2 loc:Robot_rack_no {rack} }} WHERE {{ loc:Robot2 loc:Robot_rack_no ?r }}")
RACK_OF_ROBOT2 = f"PREFIX loc: <{LOC}> SELECT ?r WHERE {{ loc:Robot2 loc:Robot_rack_no ?r }}"


async def test_an_unprotected_server_without_writable_refuses_a_patch(
    coap_client: str, base: str, tmp_path: Path
) -> None:
    run = await coap(coap_client, tmp_path, "-m", "patch", "-t", "0", "-e", MOVE.format(rack=3), f"{base}/kb",
                     out=False)
    assert run.error.startswith("4.05"), run.error


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def writable() -> AsyncIterator[ServerProcess]:
    port = free_udp_port()
    srv = await ServerProcess.start("--kb", str(Path(KB_FILES[0]).parent / "Location.owl"),
                                    "--bind", f"127.0.0.1:{port}", "--writable")
    yield srv
    await srv.stop()


async def test_coap_client_writes_and_observes(coap_client: str, writable: ServerProcess, tmp_path: Path) -> None:
    """libcoap PATCHes a SPARQL Update asking ``?ack=all`` (2.04, the level
    reached in the payload); an observing libcoap client
    (``-s``) of the query gets the new answer; aiocoap reads it too."""
    rq = query_file(tmp_path, RACK_OF_ROBOT2)
    # Unbuffered, so its first answer (the registration's) shows as it comes.
    watcher = await asyncio.create_subprocess_exec(
        "stdbuf", "-o0", coap_client, "-B", "30", "-s", "4", "-m", "fetch", "-t", "0", "-A", "50", "-f", rq,
        f"{writable.uri}/kb/sparql", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    assert watcher.stdout is not None
    try:
        first = await asyncio.wait_for(watcher.stdout.readuntil(b"}]}}"), 30)  # registered: its answer came
        run = await coap(coap_client, tmp_path, "-m", "patch", "-t", "0", "-e", MOVE.format(rack=3),
                         f"{writable.uri}/kb?ack=all", out=False)
        rest, error = await asyncio.wait_for(watcher.communicate(), 60)
    finally:
        if watcher.returncode is None:
            watcher.kill()
            await watcher.wait()
    # The level reached: all of its holders, itself alone (no data folder).
    assert run.stdout.decode().strip() == "removed 1, added 1; ack all (1 of 1 holder, in memory)", run.error
    # coap-client prints each notification's JSON right after the last one.
    text, answers, at = (first + rest).decode(), [], 0
    while (at := text.find("{", at)) >= 0:
        answer, at = json.JSONDecoder().raw_decode(text, at)
        answers.append(answer)
    racks = [int(b["r"]["value"]) for a in answers for b in a["results"]["bindings"]]
    # An unchanged answer is notified again before its Max-Age runs out (an
    # observer's sign of life): the changes are what count.
    changes = [r for i, r in enumerate(racks) if i == 0 or r != racks[i - 1]]
    assert changes == [16, 3], (text, error)
    payload = await aiocoap_payload(writable.uri, Request(Method.FETCH, "/kb/sparql", payload=RACK_OF_ROBOT2.encode(),
                                                          content_format=0, accept=50))
    assert json.loads(payload)["results"]["bindings"][0]["r"]["value"] == "3"


async def test_coap_client_gets_line_and_column_for_a_bad_update(
    coap_client: str, writable: ServerProcess, tmp_path: Path
) -> None:
    run = await coap(coap_client, tmp_path, "-m", "patch", "-t", "0", "-e", "INSERT DATA { <http://a> <http://b> }",
                     f"{writable.uri}/kb", out=False)
    assert run.error.startswith("4.00 malformed SPARQL Update: line 1, column"), run.error
