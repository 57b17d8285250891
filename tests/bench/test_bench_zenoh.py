"""The Zenoh systems in the benchmark: real runs in network namespaces (root)."""

from __future__ import annotations

import pytest
from support import require

from coapkb.bench import run as bench
from coapkb.bench.linkemu import available


@pytest.mark.root
@pytest.mark.timeout(120)
async def test_zenoh_runs_one_after_another_in_one_process() -> None:
    """Two Zenoh runs in the same benchmark process, each with a fresh feeder
    namespace: the feeder reaches the robots (10.77.0.x exists only inside
    the testbed) in both, so the feeder's Zenoh sockets were created in the
    namespace of the run at hand, not in the first run's."""
    ok, why = available()
    require(ok, why)
    rows = [await bench.run_once(system, 3, 2, 512, 2, rep=0) for system in ("zenoh-distributed", "zenoh-central")]
    for row in rows:
        assert row.ok is True, row.error
        assert row.tasks_agreed == 2 and row.transport == "zenoh"
        assert row.retransmission_profile == "tcp" and row.tcp_aborts is not None
        assert row.security == "tls"  # mutual TLS from the team's keys, on by default
        # Zenoh's framing, keep-alives, TCP/IP headers and ACKs: the wire is heavier than what it was handed.
        assert row.wire_bytes > row.app_bytes > 0
        # Facts from teammates (asked, or pushed by their holder) or from the central server.
        assert row.feeder_wire_bytes > 0 and row.remote_queries + row.pushed_answers > 0
    assert rows[0].local_queries > 0 and rows[1].local_queries == 0
