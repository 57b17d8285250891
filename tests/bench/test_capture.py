"""The bridge capture (coapkb.bench.linkemu.capture): every frame a host
sends, as its counters count it, and which of them the link delivered.
Needs root, like every namespace test (``support.require``)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from support import require

from coapkb.bench.linkemu import LinkSpec, Testbed, available
from coapkb.bench.linkemu.capture import PacketCapture, read_frames
from experiments import linkemu_accuracy as accuracy


@pytest.mark.root
@pytest.mark.timeout(60)
def test_the_capture_sees_what_the_counters_count_and_what_the_link_dropped(tmp_path: Path) -> None:
    ok, reason = available()
    require(ok, f"no kernel link emulation: {reason}")
    n, size = 200, 120
    path = tmp_path / "capture.jsonl"
    with Testbed(["a", "b"], LinkSpec(rate_kbit=512, loss_pct=25)) as tb:
        with PacketCapture(tb.bridge_netns, path) as capture:
            before = tb.counters()
            rx = accuracy.start_receiver(tb, "b", idle=1.0)
            accuracy.result(accuracy.start_sender(tb, "a", "b", size=size, count=n))
            got = accuracy.result(rx)
            after = tb.counters()
        assert capture.frames == 2 * n - (n - got["n"])
    frames = list(read_frames(path))
    assert Counter((f.port, f.direction) for f in frames) == {("p-a", "in"): n, ("p-b", "out"): got["n"]}
    sent = [f for f in frames if f.direction == "in"]
    assert sum(len(f.frame) for f in sent) == after["a"].tx_bytes - before["a"].tx_bytes
    assert all(len(f.frame) == size + accuracy.UDP_IPV4_OVERHEAD for f in sent)
    delivered = [f.frame for f in frames if f.direction == "out"]
    assert set(delivered) <= {f.frame for f in sent}  # the bridge passes frames on unchanged
    assert n - got["n"] == after["a"].dropped - before["a"].dropped
