"""What the experiments share: the seed's query mix, KB servers started in
(and stopped from) a testbed's namespaces or on loopback, writing a results CSV and reading a benchmark's."""

from __future__ import annotations

import asyncio
import csv
import random
import socket
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from coapkb.bench.row import BenchRow, read_rows
from coapkb.transport.registry import REGISTERED, transport_for

#: Each transport's usual port (every host of a testbed has its own namespace).
PORTS = {t.scheme: t.default_port for t in REGISTERED}

ROOT = Path(__file__).resolve().parent.parent
KB_FILES = [str(ROOT / "ontologies" / f"{n}.owl") for n in ("Object", "Location", "Capability")]
GRIPS = ("gripping", "grasping", "lifting", "suction")
#: The seed's four queries (Query_1..Query_4) as named queries, and the parameter each takes.
QUERY_MIX: tuple[tuple[str, str], ...] = (
    ("object-exists", "name"),
    ("object-location", "name"),
    ("object-features", "name"),
    ("robots-for-grip", "grip"),
)


def experiment_argv(name: str, *args: str) -> list[str]:
    """The command line of ``python -m experiments.NAME ARGS``: an experiment
    run again as a child process (one of its roles, in its own process or
    namespace).  Start it with ``cwd=ROOT``, where ``-m`` finds the
    ``experiments`` package and this checkout's ``coapkb``."""
    return [sys.executable, "-m", f"experiments.{name}", *args]


def prepare_link_emulation() -> str | None:
    """None when the kernel testbed can run here (after removing what crashed
    runs left behind), else the reason it cannot."""
    from coapkb.bench.linkemu import available, cleanup_stale

    ok, why = available()
    if not ok:
        return why
    cleanup_stale()
    return None


def query_plan(n: int, seed: int, products: Sequence[str]) -> list[tuple[str, dict[str, str]]]:
    """``n`` named queries: the four of the seed in turn (so each is a quarter
    of the load), with product names and grips drawn from ``seed``."""
    if not products:
        raise ValueError("no products")
    rng = random.Random(seed)
    plan = []
    for i in range(n):
        name, param = QUERY_MIX[i % len(QUERY_MIX)]
        value = rng.choice(GRIPS) if param == "grip" else rng.choice(list(products))
        plan.append((name, {param: value}))
    return plan


async def start_kb_server(tb: Any, host: str, scheme: str = "coap") -> Any:
    """``coapkb serve`` with the three warehouse KBs in ``host``'s namespace."""
    proc = await tb.spawn(host, [sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES, "--transport", scheme,
                                 "--bind", f"{tb.address(host)}:{PORTS[scheme]}"],
                          stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, cwd=str(ROOT))
    line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
    if not line.startswith("serving"):
        err = (await proc.stderr.read()).decode()[-500:] if proc.stderr else ""
        raise RuntimeError(f"server on {host} did not start: {line!r} {err}")
    return proc


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port on 127.0.0.1 that nothing uses now (UDP by default, or TCP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def start_loopback_kb_server(transport: str) -> tuple[asyncio.subprocess.Process, Any]:
    """``coapkb serve`` with the three warehouse KBs on a free loopback port;
    returns the process and its endpoint."""
    from coapkb.transport import Endpoint

    port = free_port(socket.SOCK_DGRAM if transport_for(transport).datagram else socket.SOCK_STREAM)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}",
        "--transport", transport, stdout=asyncio.subprocess.PIPE, cwd=ROOT,
    )
    assert proc.stdout is not None
    line = (await proc.stdout.readline()).decode()
    if not line.startswith("serving"):
        raise SystemExit(f"server did not start: {line!r}")
    return proc, Endpoint(transport, "127.0.0.1", port)


async def stop_processes(procs: Iterable[Any], grace_s: float = 10.0) -> None:
    """SIGTERM, then SIGKILL whatever has not exited after ``grace_s``."""
    procs = list(procs)
    for proc in procs:
        if proc.returncode is None:
            proc.terminate()
    for proc in procs:
        try:
            await asyncio.wait_for(proc.wait(), grace_s)
        except TimeoutError:
            proc.kill()


def write_csv(path: Path, fieldnames: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> None:
    """``rows`` as a new CSV at ``path`` (its folder made if needed), and say where."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(fieldnames))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")


def benchmark_rows(path: Path, prog: str) -> list[BenchRow] | None:
    """The rows of a benchmark CSV, or None once ``prog`` has said in one
    line why there are none (no such file, not a benchmark CSV, empty)."""
    try:
        rows = read_rows(path)
    except (OSError, ValueError) as exc:  # not a file, not a benchmark CSV
        print(f"{prog}: {exc}", file=sys.stderr)
        return None
    if not rows:
        print(f"{prog}: no rows in {path}" + ("" if path.exists() else " (no such file)"), file=sys.stderr)
        return None
    return rows


def rss_mib(pid: int) -> float:
    """A process's VmRSS, MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for process {pid}")
