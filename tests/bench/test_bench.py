"""The benchmark runner (coapkb.bench.run) and the experiment scripts around it.

The runner test starts real teams in real network namespaces (root only; a
skip on a laptop, a failure under CI).  Everything else is pure: the CSV
append/resume logic, the sweep's plan, and the figure and report scripts on a
small synthetic CSV.
"""

from __future__ import annotations

import csv
import json
import os
import socket
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from support import ROOT, coapkb, require

from coapkb.bench import run as bench
from coapkb.bench.linkemu import LinkCounters, LinkSpec, Testbed, available, enter_netns
from coapkb.bench.run import COLUMNS, SYSTEMS, BenchRow, append_rows, done_keys, read_rows
from coapkb.harness.record import TeamRecord
from coapkb.harness.stats import percentile
from coapkb.harness.team import Fault


def _require_netns() -> None:
    ok, why = available()
    require(ok, why)


# --------------------------------------------------------------------------- real runs (root)


@pytest.mark.root
@pytest.mark.timeout(120)
async def test_run_once_in_namespaces_gives_full_ok_rows() -> None:
    """3 robots, 2 tasks, 512 kbit/s, 2 % loss: one CoAP and one ZeroMQ system.

    The feeder only reaches the robots (10.77.0.x exists only inside the
    testbed's namespaces) if enter_netns really moved its sockets there."""
    _require_netns()
    rows = [await bench.run_once(system, 3, 2, 512, 2, rep=0) for system in ("coap-distributed", "zmq-central")]
    for row in rows:
        assert tuple(row.to_dict()) == COLUMNS
        assert row.ok is True, row.error
        assert row.error == ""
        assert row.tasks_agreed == 2
        # Headers, ACKs and retransmissions make the wire heavier than the payloads.
        assert row.wire_bytes > row.app_bytes > 0
        assert row.wire_packets > 0 and row.completion_s >= row.coordination_s > 0
        # Facts from teammates, asked or pushed by their holder, and their latencies.
        assert row.remote_queries + row.pushed_answers > 0 and row.query_p99_ms >= row.query_p50_ms > 0
        assert row.feeder_wire_bytes > 0 and row.queue_drops == 0
    coap, zmq = rows
    assert coap.retransmission_profile == "robust" and zmq.retransmission_profile == "tcp"
    assert coap.local_queries > 0 and zmq.local_queries == 0  # distributed answers some queries itself
    assert (coap.security, zmq.security) == ("oscore", "curve")  # on by default, as in coapkb team


class _Watch:
    """A :class:`coapkb.bench.run.RunObserver` that keeps what it is shown."""

    def __init__(self) -> None:
        self.records: list[tuple[BenchRow, TeamRecord]] = []

    def team_recorded(self, row: BenchRow, record: TeamRecord) -> None:
        self.records.append((row, record))


class _CountingTestbed(Testbed):
    """A testbed that counts the bench's counter readings."""

    readings = 0

    async def acounters(self) -> dict[str, LinkCounters]:
        type(self).readings += 1
        return await super().acounters()


@pytest.mark.root
@pytest.mark.timeout(120)
async def test_insecure_runs_are_their_own_rows_and_the_seeds_wire_stays_plain(tmp_path: Path) -> None:
    _require_netns()
    watch = _Watch()
    plain = await bench.run_once("coap-distributed", 3, 2, 512, 2, rep=0, security=False, trace_dir=tmp_path,
                                 observer=watch, testbed_class=_CountingTestbed)
    assert plain.ok, plain.error
    # The hooks: the observer got the team's record once, the testbed class built the testbed.
    [(seen, record)] = watch.records
    assert seen.system == "coap-distributed" and seen.tasks_agreed == 2 and seen.wire_bytes is None
    assert len(record.tasks) == 2
    assert _CountingTestbed.readings >= 2  # the two counter readings around the team's work
    # --trace: each robot's log at INFO level and the team's record, in a folder named after the run.
    [run] = tmp_path.iterdir()
    assert run.name == "coap-distributed-3r2t-512k-2pct-none-rep0"
    assert "task 2 " in (run / "Robot1.log").read_text()
    assert (run / "feeder.log").exists()
    assert len(json.loads((run / "record.json").read_text())["tasks"]) == 2
    with (run / "run.mcap").open("rb") as f:  # and the run for Foxglove
        reader = make_reader(f)
        assert [c.topic for _, c, _ in reader.iter_messages()].count("/tasks") == 2
        [meta] = reader.iter_metadata()
        assert meta.metadata["system"] == "coap-distributed" and float(meta.metadata["loss_pct"]) == 2
    assert plain.security == "none"
    assert plain.key() != replace(plain, security="oscore").key()
    assert bench.security_label("seed-distributed", True) == "none"  # the seed's baseline, as it ran


@pytest.mark.root
@pytest.mark.timeout(120)
async def test_run_once_over_delayed_bursty_links() -> None:
    """50 +- 5 ms one-way delay and 5 % burst loss on every robot's link: the
    team still agrees, and the row carries the link columns (so the resume key does)."""
    _require_netns()
    row = await bench.run_once("coap-distributed", 3, 2, 512, 5, rep=0, delay_ms=50, jitter_ms=5,
                               loss_model="burst", burst_len=2)
    assert row.ok is True, row.error
    assert (row.delay_ms, row.jitter_ms, row.loss_model, row.burst_len) == (50, 5, "burst", 2)
    # A fact from a teammate is at least a one-way delay away (50 - 5 ms):
    # pushed by its holder once the holder's own task came, or a round trip if asked.
    assert row.query_p50_ms >= 45
    assert row.key() != replace(row, delay_ms=0).key()


@pytest.mark.root
@pytest.mark.timeout(180)
@pytest.mark.parametrize("system", ["coap-distributed"])
async def test_run_once_with_a_robot_killed_on_a_slow_lossy_link(system: str) -> None:
    """``coapkb bench --fail``: 6 robots at 35 kbit/s and 10 % loss, Robot2
    killed 2 s in, every module on two robots: the row is ok (each task given
    decided once, survivors agreeing) and says when the kill was detected.
    Over CoAP only: the protocol under kills and lossy links runs through
    thousands of seeded schedules in the simulator (tests/sim), and ZeroMQ's
    kill on real sockets in tests/harness/test_cli_team.py."""
    _require_netns()
    row = await bench.run_once(system, 6, 20, 35, 10, rep=0, replication=2, faults=[Fault("kill", "Robot2", 2.0)])
    assert row.ok is True, row.error
    assert (row.replication, row.faults) == (2, "Robot2@2")
    assert row.fault_detected_s is not None and 0 <= row.fault_detected_s < 40
    assert row.tasks_unavailable == 0 and row.tasks_reassigned is not None
    assert row.key() != replace(row, faults="").key()


@pytest.mark.root
@pytest.mark.timeout(30)
def test_enter_netns_moves_only_the_calling_thread_and_back() -> None:
    _require_netns()

    def netns_inode() -> int:
        return os.stat("/proc/thread-self/ns/net").st_ino

    home = netns_inode()
    with Testbed(["a", "b"], LinkSpec()) as tb:
        target = os.stat(f"/run/netns/{tb['a'].netns}").st_ino
        with enter_netns(tb["a"].netns):
            assert netns_inode() == target
            inside = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            inside.bind((tb.address("a"), 0))  # the address exists only in that namespace
        assert netns_inode() == home
        with inside, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as outside:
            with pytest.raises(OSError):
                outside.bind((tb.address("a"), 0))
            # The socket made inside stays there: it reaches b over the testbed link.
            with enter_netns(tb["b"].netns):
                receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                receiver.bind((tb.address("b"), 0))
            with receiver:
                receiver.settimeout(5)
                inside.sendto(b"ping", receiver.getsockname())
                assert receiver.recv(16) == b"ping"


def test_enter_netns_refuses_bad_names() -> None:
    with pytest.raises(ValueError), enter_netns("../etc"):
        pass


# --------------------------------------------------------------------------- pure parts


def test_every_system_maps_to_a_team_spec() -> None:
    t = bench.timeouts_for(35, 20, 5)
    for name, d in SYSTEMS.items():
        spec = bench.system_spec(name, 6, timeouts=t)
        assert (spec.mode, spec.transport, spec.query_wire) == (d.mode, d.transport, d.query_wire)
        assert spec.query_timeout_s == t.query_s and spec.task_timeout_s == t.task_s
    assert bench.system_spec("seed-central", 3).query_wire == "seed"
    with pytest.raises(ValueError):
        bench.system_spec("carrier-pigeon", 3)


def test_the_zenoh_quic_and_reliable_udp_systems() -> None:
    """Both modes of each; QUIC is secured with mutual TLS like Zenoh/TCP, the
    reliable UDP runs plain; QUIC retransmits for both, inside Zenoh."""
    for link, scheme in (("udp", "zenoh+udp"), ("quic", "zenoh+quic")):
        for mode in ("distributed", "central"):
            d = SYSTEMS[f"zenoh-{link}-{mode}"]
            assert (d.mode, d.transport, d.query_wire) == (mode, scheme, "compact")
            assert bench.retransmission_label(f"zenoh-{link}-{mode}") == "quic"
    assert bench.security_label("zenoh-quic-central", True) == "tls"
    assert bench.security_label("zenoh-quic-central", False) == "none"
    assert bench.security_label("zenoh-udp-distributed", True) == "none"
    assert "reliable UDP" in SYSTEMS["zenoh-udp-distributed"].description
    spec = bench.system_spec("zenoh-quic-distributed", 3)
    assert spec.secure and spec.security_scheme == "tls"
    assert not bench.system_spec("zenoh-udp-central", 3).secure
    assert bench.retransmission_label("zenoh-distributed") == "tcp"


def test_the_dds_systems() -> None:
    """Both modes; RTPS's reliable QoS retransmits; never secured (no DDS Security in the wheel)."""
    for mode in ("distributed", "central"):
        d = SYSTEMS[f"dds-{mode}"]
        assert (d.mode, d.transport, d.query_wire) == (mode, "dds", "compact")
        assert bench.retransmission_label(f"dds-{mode}") == "rtps"
        assert bench.security_label(f"dds-{mode}", True) == "none"
        assert not bench.system_spec(f"dds-{mode}", 3).secure


async def test_bench_help_lists_the_zenoh_quic_and_udp_systems() -> None:
    code, out, err = await coapkb("bench", "--help")
    assert code == 0, err
    listed = " ".join(out.split()).replace("- ", "-")  # argparse wraps the list at hyphens
    for system in ("zenoh-udp-distributed", "zenoh-udp-central", "zenoh-quic-distributed", "zenoh-quic-central",
                   "dds-distributed", "dds-central"):
        assert system in listed, system


def test_timeouts_grow_with_slower_and_lossier_links() -> None:
    fast, slow, lossy = bench.timeouts_for(512, 2, 5), bench.timeouts_for(35, 2, 5), bench.timeouts_for(35, 20, 5)
    assert fast.query_s <= slow.query_s < lossy.query_s
    assert fast.task_s <= slow.task_s < lossy.task_s
    assert bench.timeouts_for(35, 20, 80).run_s > lossy.run_s > lossy.task_s


async def test_a_bad_configuration_is_a_failed_row_not_an_exception() -> None:
    row = await bench.run_once("coap-distributed", 4, 2, 512, 2)  # 4 robots: not clusters of three
    assert row.ok is False and "multiple of 3" in row.error
    assert tuple(row.to_dict()) == COLUMNS
    row = await bench.run_once("carrier-pigeon", 3, 2, 512, 2)
    assert row.ok is False and "unknown system" in row.error


async def test_run_once_builds_its_testbed_with_the_class_given() -> None:
    """``testbed_class`` gets the run's hosts and links (here a testbed that
    refuses to start, so no root is needed); without a team record the
    observer is not called, and the row says why."""
    built: list[list[str]] = []

    class Refusing(Testbed):
        def setup(self) -> None:
            built.append(list(self.hosts))
            raise OSError("no testbed here")

    watch = _Watch()
    row = await bench.run_once("coap-central", 3, 2, 512, 2, observer=watch, testbed_class=Refusing)
    assert built == [["Robot1", "Robot2", "Robot3", "central", "feeder"]]
    assert row.ok is False and row.error == "OSError: no testbed here"
    assert watch.records == []


def test_parse_retrans_segs_and_percentile() -> None:
    snmp = ("Ip: Forwarding DefaultTTL\nIp: 1 64\n"
            "Tcp: RtoAlgorithm RtoMin ActiveOpens RetransSegs InErrs\nTcp: 1 200 4 17 0\n")
    assert bench.parse_retrans_segs(snmp) == 17
    assert bench.parse_retrans_segs("") == 0
    assert percentile([], 50) is None
    assert percentile([float(v) for v in range(1, 101)], 99) == pytest.approx(99.01)


def _row(system: str = "coap-distributed", **kw: Any) -> BenchRow:
    row = BenchRow(system=system, robots=3, tasks=5, bandwidth_kbps=35.0, loss_pct=2.0, rep=0,
                   retransmission_profile=bench.retransmission_label(system), ok=True,
                   coordination_s=1.5, completion_s=2.0, wire_bytes=1000, wire_packets=10, retransmissions=0,
                   query_p50_ms=5.0, query_p99_ms=50.0, mode=SYSTEMS[system].mode,
                   transport=SYSTEMS[system].transport, query_wire=SYSTEMS[system].query_wire, app_bytes=500,
                   security=bench.security_label(system, True))
    return replace(row, **kw)


def test_csv_append_writes_one_header_and_reads_back_typed(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "r.csv"
    append_rows(path, [_row()])
    append_rows(path, [_row("zmq-central", ok=False, error="timed out, badly")])
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(COLUMNS) and sum(1 for line in lines if line.startswith("system,")) == 1
    rows = read_rows(path)
    assert [r.system for r in rows] == ["coap-distributed", "zmq-central"]
    assert rows[0].ok is True and rows[1].ok is False and rows[1].error == "timed out, badly"
    assert isinstance(rows[0].wire_bytes, int) and rows[0].bandwidth_kbps == 35.0
    assert rows[0].retransmission_profile == "robust" and rows[1].retransmission_profile == "tcp"


def test_a_row_parses_csv_text_and_json_values_by_field_type() -> None:
    row = _row("zmq-central", ok=False, error="x", tcp_aborts=2, query_p50_ms=None)
    assert BenchRow.from_dict(row.to_csv()) == row  # every cell text, None as ""
    assert BenchRow.from_dict(json.loads(json.dumps(row.to_dict()))) == row  # a --json line
    cells = {**row.to_csv(), "robots": "3.0", "ok": "TRUE", "bandwidth_kbps": "35", "not_a_column": "?"}
    back = BenchRow.from_dict(cells)
    assert (back.robots, back.ok, back.bandwidth_kbps) == (3, True, 35.0)
    assert bench.KEY_COLUMNS == ("system", "robots", "tasks", "bandwidth_kbps", "loss_pct", "rep",
                                 "retransmission_profile", "delay_ms", "jitter_ms", "loss_model", "burst_len",
                                 "replication", "faults", "security", "kb_writable")


def test_the_committed_results_csv_reads_back_and_writes_the_same_cells(tmp_path: Path) -> None:
    """The schema is the one experiments/results/quick.csv was written with (it
    predates the link columns, which come last)."""
    committed = ROOT / "experiments" / "results" / "quick.csv"
    with committed.open(newline="", encoding="utf-8") as f:
        original = list(csv.DictReader(f))
    assert list(original[0]) == list(COLUMNS[: len(original[0])])
    rows = read_rows(committed, latest_only=False)
    copy = tmp_path / "copy.csv"
    append_rows(copy, rows)
    with copy.open(newline="", encoding="utf-8") as f:
        again = list(csv.DictReader(f))
    for before, after in zip(original, again, strict=True):
        for column, text in before.items():  # a float cell may come back as "35.0" for "35"
            assert after[column] == text or float(after[column]) == float(text), (column, text, after[column])


def test_csv_without_link_columns_reads_as_no_delay_random_loss(tmp_path: Path) -> None:
    """A results CSV from before delay_ms/jitter_ms/loss_model/burst_len: its rows
    read with the defaults, and their keys equal those of plain-link runs."""
    path = tmp_path / "old.csv"
    old_columns = [c for c in COLUMNS if c not in ("delay_ms", "jitter_ms", "loss_model", "burst_len")]
    cells = _row(security="none").to_csv()
    path.write_text(",".join(old_columns) + "\n" + ",".join(str(cells[c]) for c in old_columns) + "\n")
    (back,) = read_rows(path)
    assert (back.delay_ms, back.jitter_ms, back.loss_model, back.burst_len) == (0.0, 0.0, "random", 0.0)
    assert back.key() == _row(delay_ms=0, loss_model="random", security="none").key() in done_keys(path)
    assert _row(delay_ms=100, security="none").key() not in done_keys(path)
    from experiments import sweep
    plain = sweep.Run("coap-distributed", 3, 5, 35.0, 2.0, 0, security=False)
    assert plain.key() == back.key()
    # Rows from before the security column were unprotected runs: not a secure run's key.
    assert sweep.Run("coap-distributed", 3, 5, 35.0, 2.0, 0).key() != back.key()
    assert sweep.Run("coap-distributed", 3, 5, 35.0, 2.0, 0, delay_ms=300).key() != plain.key()


def test_resume_keys_and_retry_of_failed_runs(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    assert done_keys(path) == set()
    append_rows(path, [_row(), _row("zmq-central", ok=False)])
    # 35 and 35.0 (and "35") are the same bandwidth.
    assert _row(bandwidth_kbps=35).key() == _row(bandwidth_kbps=35.0).key() in done_keys(path)
    assert len(done_keys(path)) == 2 and len(done_keys(path, include_failed=False)) == 1
    append_rows(path, [_row("zmq-central", ok=True)])  # the retry of the failed key
    latest = {r.system: r.ok for r in read_rows(path)}
    assert latest == {"coap-distributed": True, "zmq-central": True}
    assert len(read_rows(path, latest_only=False)) == 3


def test_sweep_plans_every_run_once_and_skips_the_done_ones(tmp_path: Path) -> None:
    from experiments import sweep
    quick = sweep.PROFILES["quick"]
    runs = sweep.plan(quick)
    assert len(runs) == len({r.key() for r in runs})
    assert {r.system for r in runs} >= set(sweep.QUICK_SYSTEMS)
    path = tmp_path / "quick.csv"
    first = runs[0]
    append_rows(path, [first.row(ok=True)])
    left = sweep.pending(runs, done_keys(path))
    assert first not in left and len(left) == len(runs) - 1
    paper = sweep.plan(sweep.PROFILES["paper"])
    assert len(paper) == 3 * 5 * 4 * 5 * len(sweep.PAPER_SYSTEMS) * 3 == 3 * 5 * 4 * 5 * (len(SYSTEMS) - 6) * 3  # 3 reps, no zenoh-udp, -quic or dds pair
    # Progress counts tasks per cluster (+1 for start-up), so long runs weigh more.
    short, long = (sweep.Run("coap-distributed", r, t, 35.0, 2.0, 0) for r, t in ((3, 5), (3, 80)))
    assert (sweep.units(short), sweep.units(long)) == (6, 81)
    assert sweep.units(sweep.Run("coap-distributed", 9, 80, 35.0, 2.0, 0)) == 28



async def test_sweep_appends_each_row_and_prints_count_and_eta(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from experiments import sweep
    runs = sweep.plan(sweep.PROFILES["quick"])[:3]

    async def child(run: Any, limit_s: float) -> dict[str, Any]:  # no root, no namespaces: the row only
        return _row(run.system, robots=run.robots, tasks=run.tasks, bandwidth_kbps=run.bandwidth,
                    loss_pct=run.loss, rep=run.rep, ok=run is not runs[2], error="" if run is not runs[2] else "x")

    monkeypatch.setattr(sweep, "_run_child", child)
    path = tmp_path / "s.csv"
    assert await sweep.sweep(runs[1:], path, 1, runs[:1]) == 1
    assert [r.system for r in read_rows(path)] == [r.system for r in runs[1:]]
    lines = capsys.readouterr().out.splitlines()
    assert [line.split("]")[0] for line in lines] == ["[2/3  67%", "[3/3 100%"]
    assert all(" ETA " in line and "FAILED" in line for line in lines[1:])

def _synthetic(path: Path) -> None:
    """A small matrix with the seed's trends: central > distributed, seed wire > compact."""
    rows = []
    for system, d in SYSTEMS.items():
        for robots in (3, 9):
            for tasks in (5, 20):
                for bw in (35.0, 256.0):
                    for loss in (2.0, 20.0):
                        factor = (1.7 if d.mode == "central" else 1.0) * (2.5 if d.query_wire == "seed" else 1.0)
                        factor *= 0.6 if d.transport == "coap" else 1.0
                        rows.append(_row(system, robots=robots, tasks=tasks, bandwidth_kbps=bw, loss_pct=loss,
                                         wire_bytes=int(tasks * 4000 * factor * (1 + loss / 100)),
                                         completion_s=tasks * (1 + loss / 10) * (2 if d.transport == "coap" else 1),
                                         query_p99_ms=100 * (1 + loss)))
    rows.append(_row("coap-central", robots=3, tasks=5, bandwidth_kbps=35.0, loss_pct=20.0, rep=1, ok=False,
                     error="run did not finish within 600 s"))
    # CoAP without its keys, beside DDS (which has none): a system of its own in the report.
    rows.append(_row("coap-distributed", security="none", wire_bytes=15_000))
    rows.append(_row("dds-distributed", wire_bytes=30_000) if "dds-distributed" in SYSTEMS else
                _row("zenoh-udp-distributed", wire_bytes=30_000))
    append_rows(path, rows)


def test_figures_script_writes_pngs_from_a_small_csv(tmp_path: Path) -> None:
    from experiments import figures
    path = tmp_path / "synthetic.csv"
    _synthetic(path)
    outdir = tmp_path / "figs"
    assert figures.main([str(path), "--outdir", str(outdir)]) == 0
    pngs = sorted(p.name for p in outdir.glob("*.png"))
    assert {"fig06_bytes_vs_loss.png", "fig09_bytes_difference.png", "fig12_completion_per_robots.png",
            "transport_bytes.png", "query_latency.png"} <= set(pngs)
    assert all((outdir / p).read_bytes().startswith(b"\x89PNG") for p in pngs)
    # A CSV without the data a figure needs skips that figure instead of failing.
    one = tmp_path / "one.csv"
    append_rows(one, [_row()])
    results = figures.draw_all(read_rows(one), tmp_path / "few")
    assert all(isinstance(v, str) for k, v in results.items() if k in ("fig06", "fig08", "fig09", "fig10"))


def test_report_script_writes_the_ratio_table(tmp_path: Path) -> None:
    from experiments import report
    path = tmp_path / "synthetic.csv"
    _synthetic(path)
    out = tmp_path / "report.md"
    assert report.main([str(path), "--out", str(out), "--profile", "test"]) == 0
    text = out.read_text()
    assert "## Key ratios" in text and "| comparison | bytes on the wire | completion time | seed paper |" in text
    # central is 1.7x distributed in the synthetic data: a 41 % saving, next to the seed's ~42 %.
    assert "distributed vs central, CoAP + compact: saving | 41 %" in text
    assert "~42% fewer bytes" in text
    assert "coap-central | 3 | 5 | 35 | 20 | 1 | - | run did not finish" in text  # the failed run is listed
    assert "`coap-distributed --insecure`" in text  # never paired as the secured runs of its cell


def test_the_report_on_a_bench_csv_of_one_cell_says_why_it_has_no_matrix_time(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``coapkb bench``'s own CSV: one cell, every system, wall times.  The
    time model cannot be fitted (nor a cell held out): one line says so, and
    the rest of the report is written."""
    from experiments import report
    path = tmp_path / "bench.csv"
    append_rows(path, [_row(s, wall_s=w) for s, w in (("coap-distributed", 6.0), ("coap-central", 7.0),
                                                      ("zmq-distributed", 5.0), ("zmq-central", 6.5))])
    out = tmp_path / "report.md"
    assert report.main([str(path), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert printed.err == ""
    assert printed.out.splitlines() == [
        f"report written to {out}",
        "paper matrix time not estimated: the runs of this CSV with a wall time cover 1 cell (robots, tasks, "
        "bandwidth, loss): too few to fit how a run's time grows along the matrix; a sweep's CSV covers many"]
    text = out.read_text()
    assert "## Key ratios" in text and "## How long the paper matrix takes\n\nNot estimated: the runs" in text


@pytest.mark.parametrize("tool", ["report", "figures"])
def test_the_report_and_the_figures_say_in_one_line_what_is_wrong_with_their_csv(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tool: str
) -> None:
    """Not a benchmark CSV, or no such file: one line each, exit 1, no traceback."""
    import importlib
    main = importlib.import_module(f"experiments.{tool}").main
    other = tmp_path / "notes.csv"
    other.write_text("when,what\ntoday,a list\n")
    assert main([str(other)]) == 1
    assert capsys.readouterr().err == f"{tool}: {other} is not a benchmark CSV: it has no column system, robots, " \
        "tasks, bandwidth_kbps, loss_pct, rep, retransmission_profile\n"
    assert main([str(tmp_path / "none.csv")]) == 1
    assert capsys.readouterr().err == f"{tool}: no rows in {tmp_path / 'none.csv'} (no such file)\n"


def test_a_central_servers_query_limit_grows_with_the_clusters_it_serves() -> None:
    """The central link carries every cluster's answers: the baseline is given
    the time that takes, so it fails only when something is wrong."""
    alone, shared = bench.timeouts_for(35, 2, 5), bench.timeouts_for(35, 2, 5, central_clusters=33)
    assert bench.timeouts_for(35, 2, 5, central_clusters=0) == alone
    assert shared.query_s - alone.query_s == pytest.approx(2 * 33 * 3300 * 8 / 35000, abs=0.1)
    assert shared.task_s > alone.task_s and shared.run_s > alone.run_s


def test_the_spread_script_shows_the_slow_run_a_median_hides(capsys: pytest.CaptureFixture[str]) -> None:
    from experiments import spread
    row = BenchRow(system="coap-distributed", robots=3, tasks=10, bandwidth_kbps=35, loss_pct=20, rep=0,
                   retransmission_profile="robust", ok=True, completion_s=6.0, coordination_s=5.5,
                   query_p50_ms=10.0, query_p99_ms=900.0, wire_bytes=62_000, security="oscore")
    runs = [replace(row, rep=i, completion_s=c) for i, c in enumerate((6.0, 6.2, 18.0, 5.8, 6.1))]
    lines = spread.report([("after", r) for r in runs])
    assert lines[0] == "after: coap-distributed 3r 10t 35k 20% oscore"
    assert lines[-1].startswith("  5 runs: completion median 6.1 s, slowest 2.95x the median; query p99 at most 0.90 s")


def test_dds_table_pairs_runs_by_setting_and_repetition() -> None:
    """CoAP ÷ DDS per pair (same setting and repetition); a failed run drops its pair."""
    from experiments import dds_table as table
    rows = [
        *(_row("coap-distributed", rep=r, wire_bytes=1000, completion_s=2.0, security="none") for r in range(3)),
        *(_row("dds-distributed", rep=r, wire_bytes=4000 * (r + 1), completion_s=4.0) for r in range(3)),
        _row("dds-distributed", rep=3, ok=False),
    ]
    ratios = "\n".join(table.ratios(rows))
    assert "| 3 robots, 5 tasks, 35 kbit/s, 2 % | 3 | 0.12 [0.083, 0.25]" in ratios  # 1000/8000 the median of 3
    assert "| 0.50 [0.50, 0.50]" in ratios
    medians = "\n".join(table.medians(rows))
    assert "| `dds-distributed` | 3/4 | 8,000 [4,000, 12,000]" in medians
