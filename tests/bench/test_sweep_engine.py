"""``python -m experiments.sweep --engine``: parsing, the one-line errors, the row
de-duplication, and a tiny matrix through a local Dask cluster of two workers
(root: real runs in network namespaces; a skip on a laptop, a failure in CI)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from support import require

from coapkb.bench.linkemu import available
from coapkb.bench.run import read_rows
from experiments import sweep


def test_engine_urls() -> None:
    assert sweep.parse_engine("local") == sweep.Engine("local")
    assert sweep.parse_engine("dask://10.0.0.5:8786").address == "tcp://10.0.0.5:8786"
    assert sweep.parse_engine("dask://[::1]:8786/").address == "tcp://[::1]:8786"
    for bad in ("dask", "dask://host", "dask://host:notaport", "dask://host:1/path", "ray://host:1", "tcp://h:1", ""):
        with pytest.raises(sweep.EngineError, match="expected 'local' or 'dask://HOST:PORT'"):
            sweep.parse_engine(bad)


def test_a_bad_engine_or_no_scheduler_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert sweep.main(["--engine", "dask://nowhere", "--dry-run"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "sweep: --engine: expected 'local' or 'dask://HOST:PORT', got 'dask://nowhere'"]
    port = _free_port()  # nobody listens there
    out = tmp_path / "s.csv"
    assert sweep.main(["--engine", f"dask://127.0.0.1:{port}", "--connect-timeout", "1", "--out", str(out),
                       "--systems", "coap-distributed"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"sweep: cannot reach the Dask scheduler at tcp://127.0.0.1:{port}")
    assert not out.exists()


def test_progress_appends_a_key_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    runs = sweep.plan(sweep.PROFILES["quick"])[:2]
    out = tmp_path / "s.csv"
    with sweep.Progress(out, runs, []) as progress:
        for run in (runs[0], runs[0], runs[1]):  # an engine that delivers runs[0] twice
            progress.record(run, run.row(ok=True, seed=run.seed))
    assert [r.key() for r in read_rows(out, latest_only=False)] == [runs[0].key(), runs[1].key()]
    assert [r.seed for r in read_rows(out)] == [1, 1]  # seeded by the repetition: 1 + rep
    assert "already recorded" in capsys.readouterr().out


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.root
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_tiny_matrix_through_a_local_dask_cluster_of_two_workers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """2 repetitions of 3 robots, 2 tasks, 512 kbit/s, 2 % loss, coap-distributed:
    one run on each worker (each holds one netns slot), rows streamed into one
    CSV; a second start finds nothing to do."""
    ok, why = available()
    require(ok, why)
    from distributed import Client, LocalCluster

    tiny = sweep.Profile("tiny", (sweep.Grid((3,), (2,), (512,), (2,), ("coap-distributed",)),), reps=2, note="test")
    monkeypatch.setitem(sweep.PROFILES, "tiny", tiny)
    out = tmp_path / "tiny.csv"
    with LocalCluster(n_workers=2, processes=True, threads_per_worker=1, resources={sweep.NETNS: 1},
                      dashboard_address=None, host="127.0.0.1") as cluster:
        with Client(cluster) as client:  # both registered before the sweep counts its slots
            client.wait_for_workers(2, timeout=60)
        engine = cluster.scheduler_address.replace("tcp://", "dask://")
        argv = ["--profile", "tiny", "--engine", engine, "--out", str(out)]
        assert sweep.main(argv) == 0
        text = capsys.readouterr().out
        assert "2 workers, 2 run slots" in text and "[2/2 100%]" in text and " ETA " in text
        rows = read_rows(out, latest_only=False)
        assert sorted(r.rep for r in rows) == [0, 1] and all(r.ok for r in rows), [r.error for r in rows]
        assert sorted(r.seed for r in rows) == [1, 2]
        assert {r.key() for r in rows} == {run.key() for run in sweep.plan(tiny)}
        # Resume: every key is in the CSV, nothing is submitted or appended.
        assert sweep.main(argv) == 0
        assert "0 to go" in capsys.readouterr().out
        assert len(read_rows(out, latest_only=False)) == 2


@pytest.mark.root
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_worker_that_joins_without_link_emulation_takes_no_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A worker started mid-sweep without the capabilities for namespaces
    (root, but CAP_SYS_ADMIN and CAP_NET_ADMIN dropped) gives up its netns
    slot: every run still lands on the fit worker, and all succeed."""
    ok, why = available()
    require(ok, why)
    setpriv = shutil.which("setpriv")
    require(setpriv is not None, "setpriv (util-linux) not installed")
    from distributed import Client, LocalCluster

    tiny = sweep.Profile("tiny", (sweep.Grid((3,), (2,), (512,), (2,), ("coap-distributed",)),), reps=3, note="test")
    monkeypatch.setitem(sweep.PROFILES, "tiny", tiny)
    out = tmp_path / "tiny.csv"
    with LocalCluster(n_workers=1, processes=True, threads_per_worker=1, resources={sweep.NETNS: 1},
                      dashboard_address=None, host="127.0.0.1") as cluster:
        engine = cluster.scheduler_address.replace("tcp://", "dask://")
        argv = ["--profile", "tiny", "--engine", engine, "--out", str(out)]
        with ThreadPoolExecutor(1) as pool, Client(cluster) as client:
            client.wait_for_workers(1, timeout=60)
            swept = pool.submit(sweep.main, argv)
            deadline = time.monotonic() + 60
            while "coapkb-link-emulation" not in client.run_on_scheduler(_worker_plugins):
                assert time.monotonic() < deadline and not swept.done(), "the sweep registered no gate"
                time.sleep(0.05)
            unfit = subprocess.Popen(
                [setpriv, "--bounding-set", "-sys_admin,-net_admin", sys.executable, "-m", "distributed.cli.dask_worker",
                 cluster.scheduler_address, "--nthreads", "1", "--resources", f"{sweep.NETNS}=1",
                 "--no-dashboard", "--no-nanny", "--name", "unfit"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
            try:
                client.wait_for_workers(2, timeout=60)
                deadline = time.monotonic() + 60
                while _slots(client, "unfit") != 0:
                    assert time.monotonic() < deadline, "the unfit worker kept its netns slot"
                    time.sleep(0.05)
                assert swept.result(timeout=180) == 0
            finally:
                unfit.terminate()
                unfit.wait(timeout=30)
    rows = read_rows(out, latest_only=False)
    assert sorted(r.rep for r in rows) == [0, 1, 2] and all(r.ok for r in rows), [r.error for r in rows]


def _worker_plugins(dask_scheduler: Any) -> list[str]:
    return list(dask_scheduler.worker_plugins)


def _slots(client: Any, name: str) -> float | None:
    for worker in client.scheduler_info(n_workers=-1)["workers"].values():
        if worker.get("name") == name:
            return worker.get("resources", {}).get(sweep.NETNS)
    return None
