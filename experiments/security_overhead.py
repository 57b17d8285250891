"""What OSCORE keyed by EDHOC costs, on loopback.

    .venv/bin/python -m experiments.security_overhead [--tasks 20] [--reps 3] [--requests 2000]

Three sections, each printed as a table and written to
``experiments/results/security_overhead.csv``:

* **team**: a team of 3 robot processes (``TeamSpec(robots=3)``, compute-by-all,
  the robust profile) does the same ``--tasks`` tasks with security on and
  off, ``--reps`` times, alternating; bytes the robots sent per task (UDP
  payloads, EDHOC runs included) and completion time (medians).
* **edhoc**: one EDHOC run (method 3, suite 2, message_4 flow) between two
  fresh processes' worth of contexts in this process: CoAP round trips,
  datagrams and bytes each way (the UDP payloads).
* **cpu**: ``coapkb serve`` (the three KBs) in its own process, with and
  without ``--credentials``; one client sends ``--requests`` named queries
  one after another (the four of the seed in turn); the server's CPU time
  per request from /proc, and the bytes per request on the wire.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from coapkb.harness.team import DEFAULT_ONTOLOGIES, Team, TeamSpec, draw_tasks
from coapkb.security import generate_team, load_identity
from coapkb.security.coap import ClientSecurity, ServerSecurity
from coapkb.security.keys import default_members
from coapkb.transport import Endpoint, open_client, serve
from coapkb.transport.base import ResourceInfo
from coapkb.transport.messages import Method, Request, Response, Status
from coapkb.transport.router import Router
from experiments.common import KB_FILES, free_port, query_plan, write_csv

ROOT = Path(__file__).resolve().parent.parent

CSV = ROOT / "experiments" / "results" / "security_overhead.csv"
FIELDS = ["section", "security", "runs", "tasks", "bytes_per_task", "completion_s", "messages_per_task",
          "round_trips", "datagrams_sent", "datagrams_received", "bytes_sent", "bytes_received",
          "requests", "server_cpu_us_per_req", "bytes_per_req", "seconds"]


async def team_section(tasks: int, reps: int) -> list[dict[str, Any]]:
    names = draw_tasks(tasks, DEFAULT_ONTOLOGIES, seed=3)
    results: dict[bool, list[tuple[float, float, float]]] = {True: [], False: []}
    for rep in range(reps):
        for security in (False, True) if rep % 2 == 0 else (True, False):
            spec = TeamSpec(robots=3, security=security)
            async with Team.launch(spec) as team:
                record = await team.run(names)
            if record.disputed or any(t.errors for t in record.tasks):
                raise SystemExit(f"run with security={security} had errors or disagreements")
            sent = sum(s.traffic.bytes_sent for s in record.robot_stats.values())
            messages = sum(s.traffic.messages_sent for s in record.robot_stats.values())
            results[security].append((sent / tasks, record.completion_s, messages / tasks))
            print(f"  team run {rep + 1}/{reps} security={'on' if security else 'off'}: "
                  f"{sent / tasks:,.0f} B/task, {record.completion_s:.2f} s", flush=True)
    return [
        {"section": "team", "security": "on" if security else "off", "runs": reps, "tasks": tasks,
         "bytes_per_task": round(statistics.median(r[0] for r in rows)),
         "completion_s": round(statistics.median(r[1] for r in rows), 3),
         "messages_per_task": round(statistics.median(r[2] for r in rows), 1)}
        for security, rows in results.items()
    ]


async def edhoc_section(team_dir: Path) -> list[dict[str, Any]]:
    router = Router()

    async def ok(request: Request) -> Response:
        return Response(Status.CONTENT, b"")

    router.add(ResourceInfo("/x"), ok)
    server = await serve(router, Endpoint("coap", "127.0.0.1", 0),
                         security=ServerSecurity(load_identity(team_dir, "Robot1")))
    client = await open_client("coap", security=ClientSecurity(load_identity(team_dir, "Robot2")))
    try:
        before = client.counters.as_dict()
        started = time.perf_counter()
        await client.security.ensure(client._ctx, server.endpoint)
        seconds = time.perf_counter() - started
        after = client.counters.as_dict()
        run = client.security.handshakes[0]
        return [{
            "section": "edhoc", "security": "on", "round_trips": run.round_trips,
            "datagrams_sent": after["messages_sent"] - before["messages_sent"],
            "datagrams_received": after["messages_received"] - before["messages_received"],
            "bytes_sent": after["bytes_sent"] - before["bytes_sent"],
            "bytes_received": after["bytes_received"] - before["bytes_received"],
            "seconds": round(seconds, 4),
        }]
    finally:
        await client.aclose()
        await server.aclose()


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def cpu_section(team_dir: Path, requests: int) -> list[dict[str, Any]]:
    plan = query_plan(requests, 1, draw_tasks(200, DEFAULT_ONTOLOGIES, seed=1))
    rows = []
    for security in (False, True):
        port = free_port()
        args = [sys.executable, "-m", "coapkb", "serve", "--kb", *KB_FILES, "--bind", f"127.0.0.1:{port}"]
        if security:
            args += ["--credentials", str(team_dir)]
        proc = await asyncio.create_subprocess_exec(*args, stdout=asyncio.subprocess.PIPE, cwd=str(ROOT))
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
        assert line.startswith("serving"), line
        peer = Endpoint("coap", "127.0.0.1", port)
        client = await open_client("coap", security=ClientSecurity(load_identity(team_dir, "operator")) if security else None)
        try:
            # Warm-up (and the EDHOC run), not counted.
            for name, params in plan[:50]:
                await client.request(peer, Request(Method.GET, f"/kb/q/{name}", query=params), timeout=10)
            before, cpu0, t0 = client.counters.as_dict(), _cpu_s(proc.pid), time.perf_counter()
            for name, params in plan:
                response = await client.request(peer, Request(Method.GET, f"/kb/q/{name}", query=params), timeout=10)
                assert response.status.is_success, response
            seconds, cpu = time.perf_counter() - t0, _cpu_s(proc.pid) - cpu0
            after = client.counters.as_dict()
        finally:
            await client.aclose()
            proc.terminate()
            await proc.wait()
        wire = (after["bytes_sent"] - before["bytes_sent"]) + (after["bytes_received"] - before["bytes_received"])
        rows.append({"section": "cpu", "security": "on" if security else "off", "requests": requests,
                     "server_cpu_us_per_req": round(cpu / requests * 1e6), "bytes_per_req": round(wire / requests, 1),
                     "seconds": round(seconds, 3)})
    return rows


def _print(rows: list[dict[str, Any]]) -> None:
    for row in rows:
        print("  " + ", ".join(f"{k}={v}" for k, v in row.items() if k != "section"))


async def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.security_overhead",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", type=int, default=20)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--sections", default="edhoc,cpu,team")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        team_dir = Path(tmp) / "team"
        generate_team(team_dir, default_members(3))
        for section in args.sections.split(","):
            print(f"{section}:", flush=True)
            if section == "edhoc":
                new = await edhoc_section(team_dir)
            elif section == "cpu":
                new = await cpu_section(team_dir, args.requests)
            elif section == "team":
                new = await team_section(args.tasks, args.reps)
            else:
                raise SystemExit(f"unknown section {section}")
            _print(new)
            rows += new
    write_csv(CSV, FIELDS, rows)


if __name__ == "__main__":
    asyncio.run(main())
