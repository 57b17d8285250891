"""Shared test helpers: KB files, robots that grip, real server processes, skips that fail in CI
(and the one kind that does not: a case that cannot apply)."""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import sys
import time
import tokenize
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from decimal import Decimal
from pathlib import Path
from typing import NamedTuple, NoReturn

import pytest

from coapkb.transport.base import ResourceInfo
from coapkb.transport.messages import Method, Request, Response, Status
from coapkb.transport.router import Router

ROOT = Path(__file__).resolve().parent.parent
ONTOLOGIES = ROOT / "ontologies"
KB_FILES = [str(ONTOLOGIES / f"{n}.owl") for n in ("Object", "Location", "Capability")]


def comments(root: Path) -> Iterator[tuple[str, str]]:
    """Every comment in the Python files under ``root``: (file:line, text)."""
    for path in sorted(root.rglob("*.py")):
        with tokenize.open(path) as f:
            for token in tokenize.generate_tokens(f.readline):
                if token.type == tokenize.COMMENT:
                    yield f"{path.relative_to(ROOT)}:{token.start[0]}", token.string


#: Robots of the committed ontologies that can pick by gripping (Query_4), and their payloads.
GRIPPING_ROBOTS = {
    "Robot1": Decimal("60.6"),
    "Robot2": Decimal("31.4"),
    "Robot4": Decimal("75.4"),
    "Robot6": Decimal("32.1"),
    "Robot7": Decimal("73"),
    "Robot8": Decimal("29.9"),
}


def varied_query(i: int) -> str:
    """A different question for each ``i``, its JSON answer 1 to 6 blocks long.

    Fast on purpose (no ORDER BY, well under aiocoap's 100 ms EMPTY_ACK_DELAY):
    libcoap 4.3.1's coap-client cannot take a multi-block answer sent as a
    separate response ("large body receive internal issue" in coap_block.c).
    Without ORDER BY the row order is the store's, the same in every process
    that loads the same files with the same backend."""
    return f"SELECT ?s ?p ?o WHERE {{ ?s ?p ?o }} OFFSET {i * 13} LIMIT {2 + i % 5 * 6}"


#: Values of the ``CI`` environment variable that mean "this is CI" (``CI=false`` does not).
CI_TRUE = frozenset({"1", "true", "yes", "on"})


def in_ci(environ: Mapping[str, str] = os.environ) -> bool:
    """Whether the tests run in CI: ``CI`` set to a true value such as ``true``, ``1`` or ``yes``."""
    return environ.get("CI", "").strip().lower() in CI_TRUE


def require(condition: bool, reason: str) -> None:
    """Skip when ``condition`` fails: the one way a test skips. In CI, where
    the project installs everything these tests need, the skip is turned into
    a failure (``pytest_runtest_makereport`` below)."""
    if not condition:
        pytest.skip(reason)


def not_applicable(reason: str) -> NoReturn:
    """Skip a case that cannot apply to what it is run on (a parametrised
    contract case on a transport that has no such thing: security on DDS),
    not one whose tool is missing.  Nothing could be installed to run it, so
    this skip stays a skip in CI."""
    __tracebackhide__ = True  # reported at the caller's line
    try:
        pytest.skip(f"does not apply: {reason}")
    except pytest.skip.Exception as skip:
        skip.not_applicable = True  # type: ignore[attr-defined]
        raise


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """The rule for every skip (``require``, a ``skipif`` marker, a plugin's):
    in CI it fails, so CI cannot go green without having run every test.
    The one exception is :func:`not_applicable`'s.  Registered by tests/conftest.py."""
    outcome = yield
    report: pytest.TestReport = outcome.get_result()
    not_applying = call.excinfo is not None and getattr(call.excinfo.value, "not_applicable", False)
    if report.skipped and not hasattr(report, "wasxfail") and not not_applying and in_ci():
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"required in CI: {reason.removeprefix('Skipped: ')}"


def unmeasured(environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """``environ`` without coverage's hook, for a process that forks the
    simulator's worker pool: coverage would trace every forked worker, and
    a worker's data is never saved (the pool ends it without its exit
    handlers), so measuring it only made the scan slower (1.7x).  Such
    scans run code the single-process tests measure.  Also for runs that
    repeat what those measure (a replay, a planted bug's seeds): coverage
    made them about 1.4x slower for no line more."""
    return {name: value for name, value in environ.items() if name != "COVERAGE_PROCESS_CONFIG"}


def require_libcoap() -> str:
    path = shutil.which("coap-client-notls") or shutil.which("coap-client")
    require(path is not None, "libcoap's coap-client-notls is not installed (Debian: libcoap3-bin)")
    return path  # type: ignore[return-value]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``coapkb serve`` in its own OS process; ready once it prints its endpoint."""

    def __init__(self, proc: asyncio.subprocess.Process, uri: str) -> None:
        self.proc = proc
        self.uri = uri

    @classmethod
    async def start(cls, *args: str, timeout: float = 30.0) -> ServerProcess:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "coapkb", "serve", *args,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
        )
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), timeout)).decode()
        if not line.startswith("serving"):
            err = (await proc.stderr.read()).decode() if proc.stderr else ""
            raise RuntimeError(f"server did not start: {line!r} {err}")
        return cls(proc, line.rsplit(" on ", 1)[1].strip())

    async def stop(self) -> int:
        if self.proc.returncode is None:
            self.proc.terminate()
        try:
            return await asyncio.wait_for(self.proc.wait(), 10)
        except TimeoutError:
            self.proc.kill()
            return await self.proc.wait()


@pytest.fixture
async def kb_server() -> AsyncIterator[ServerProcess]:
    """A robot serving all three warehouse KBs over CoAP on loopback."""
    port = free_udp_port()
    server = await ServerProcess.start(
        "--kb", *(str(ONTOLOGIES / f"{n}.owl") for n in ("Object", "Location", "Capability")),
        "--bind", f"127.0.0.1:{port}",
    )
    yield server
    await server.stop()


class CliResult(NamedTuple):
    """What one ``coapkb`` command did."""

    code: int
    stdout: str
    stderr: str


async def coapkb(*args: str, stdin: str | None = None, timeout: float = 60) -> CliResult:
    """``python -m coapkb ARGS`` in a subprocess, as a user runs it (killed after ``timeout``)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "coapkb", *args,
        stdin=asyncio.subprocess.PIPE if stdin is not None else asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=ROOT,
    )
    try:
        out, err = await asyncio.wait_for(proc.communicate(stdin.encode() if stdin is not None else None), timeout)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise AssertionError(f"coapkb {' '.join(args)} did not exit within {timeout}s") from None
    return CliResult(proc.returncode or 0, out.decode(), err.decode())


def recording_router(*paths: str) -> tuple[Router, list[tuple[str, str]]]:
    """A robot's /tasks and /decisions (and ``paths``, GET only) that answer
    "ok" and record each ``(method, path)`` that got through the policy."""
    calls: list[tuple[str, str]] = []

    async def handle(request: Request) -> Response:
        calls.append((str(request.method), request.path))
        return Response(Status.CHANGED if request.method == Method.POST else Status.CONTENT, b"ok")

    router = Router()
    router.add(ResourceInfo("/tasks", methods=("GET", "POST")), handle)
    router.add(ResourceInfo("/decisions", methods=("POST",)), handle)
    for path in paths:
        router.add(ResourceInfo(path, methods=("GET",)), handle)
    return router, calls


async def until(condition: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    """Poll ``condition`` (what a server holds: no event tells a test) under ``timeout``."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g}s: {what}")
        await asyncio.sleep(0.01)


def observation_count(server: object) -> int:
    """The observations ``server`` holds.  The CoAP server does not say
    (observations are aiocoap's, per resource, behind the OSCORE site
    wrapper when secured): they are counted there."""
    count = getattr(server, "observation_count", None)
    if count is not None:
        return int(count)
    site = server._ctx.serversite  # type: ignore[attr-defined]  # the CoAP server's aiocoap context
    site = getattr(site, "_inner_site", site)
    return sum(len(getattr(r, "_observations", ())) for r in site._resources.values())
