"""A run as Foxglove sees it: the MCAP file ``coapkb team --record X.mcap``
writes, read back with the mcap library, and the live server a Foxglove
WebSocket client subscribes to."""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest
import websockets
from mcap.reader import make_reader
from support import ROOT

from coapkb.feeder.record import TaskRecord
from coapkb.harness.recording import RunRecorder, warehouse

TASKS = ["Gucci_bag_14", "Canon_tv_538", "Gucci_bag_14", "Barilla_pasta_1"]


def _coapkb(*args: str, cwd: Path = ROOT, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "coapkb", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.slow
def test_a_team_run_recorded_as_mcap_has_every_channel_task_and_its_metadata(tmp_path: Path) -> None:
    tasks_file = tmp_path / "tasks.txt"
    tasks_file.write_text("\n".join(TASKS) + "\n")
    out = tmp_path / "run.mcap"
    result = _coapkb("team", "--robots", "3", "--tasks-file", str(tasks_file), "--writable", "--insecure",
                     "--misplace", "Barilla_pasta_1", "--quiet", "--record", str(out))
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"recording written to {out}" in result.stdout
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: (summary.schemas[c.schema_id].name, c.message_encoding) for c in summary.channels.values()}
        assert topics["/warehouse"] == ("foxglove.SceneUpdate", "protobuf")
        assert topics["/robots/markers"] == ("foxglove.SceneUpdate", "protobuf")
        assert topics["/robots/poses"] == ("foxglove.FrameTransforms", "protobuf")
        assert topics["/robots/state"] == ("coapkb.RobotState", "json")
        assert topics["/tasks"] == ("coapkb.Task", "json")
        assert topics["/robots/traffic"] == ("coapkb.Traffic", "json")
        [meta] = [m for m in reader.iter_metadata() if m.name == "coapkb"]
        assert "--record" in meta.metadata["command"] and meta.metadata["writable"] == "true"
        assert meta.metadata["misplaced"] == '["Barilla_pasta_1"]'
        times: dict[str, list[int]] = defaultdict(list)
        tasks: dict[int, dict] = {}
        states = []
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            times[channel.topic].append(message.log_time)
            if channel.topic == "/tasks":
                task = json.loads(message.data)
                tasks[task["seq"]] = task  # the last word on a task wins (a late not-found)
            elif channel.topic == "/robots/state":
                states.append(json.loads(message.data))
    for topic, stamps in times.items():
        assert stamps == sorted(stamps), topic  # in order on each channel
    assert len(times["/warehouse"]) == 1 and len(times["/robots/traffic"]) >= 3  # sampled, and at the end
    assert sorted(tasks) == [1, 2, 3, 4] and [tasks[s]["object"] for s in (1, 2, 3, 4)] == TASKS
    assert tasks[3]["fate"] == "skipped" and tasks[3]["skip_reason"].startswith("picked by")
    assert tasks[4]["fate"] == "not-found" and "misplaced" in tasks[4]["not_found"]
    assert {s["robot"] for s in states} == {"Robot1", "Robot2", "Robot3"}
    assert len(times["/robots/poses"]) == len(states)

    # The picture of the run: its title is the whole command, inside the figure.
    import matplotlib.pyplot as plt

    from experiments import mcap_picture
    mcap_picture.draw(out, tmp_path / "run.png", ROOT / "ontologies")
    fig = plt.gcf()
    title = fig._suptitle
    assert title is not None and title.get_text().replace("\n", " ") == f"run.mcap: {meta.metadata['command']}"
    fig.canvas.draw()
    box = title.get_window_extent()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.x1 and box.y1 <= fig.bbox.y1, (box, fig.bbox)
    plt.close(fig)


def test_a_bad_recording_option_is_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such"
    for args, needle in ((["--foxglove", "nope"], "--foxglove takes [HOST:]PORT"),
                         (["--record", str(missing / "run.mcap")], f"--record: no folder {missing}")):
        result = _coapkb("team", "--robots", "3", "--tasks", "1", "--insecure", *args, timeout=60)
        assert result.returncode != 0 and "Traceback" not in result.stderr, result.stderr
        assert needle in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr


async def test_a_foxglove_client_subscribed_live_gets_the_scene_and_a_decision() -> None:
    """The Foxglove WebSocket protocol (foxglove.sdk.v1): the server
    advertises the channels; a client subscribing to the warehouse after it
    was drawn still gets it, and then each task as it is decided."""
    layout, docks = warehouse(ROOT / "ontologies")
    recorder = RunRecorder(None, ("127.0.0.1", 0), ["Robot1", "Robot2", "Robot3"], layout, docks)
    try:
        assert recorder.server is not None
        async with websockets.connect(f"ws://127.0.0.1:{recorder.server.port}",
                                      subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            channels: dict[str, int] = {}
            async with asyncio.timeout(10):
                while "/tasks" not in channels:
                    message = await ws.recv()
                    if isinstance(message, str) and json.loads(message)["op"] == "advertise":
                        channels |= {c["topic"]: c["id"] for c in json.loads(message)["channels"]}
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": channels["/warehouse"]}, {"id": 2, "channelId": channels["/tasks"]}]}))
            got: dict[int, bytes] = {}
            async with asyncio.timeout(10):
                while 1 not in got:  # the scene, drawn again for this viewer
                    message = await ws.recv()
                    if isinstance(message, bytes) and message[0] == 1:  # opcode 1: message data
                        got[struct.unpack("<I", message[1:5])[0]] = message[13:]
                recorder.task(TaskRecord("Gucci_bag_14", 1, 7, assigned_to="Robot2",
                                         decisions={"Robot1": "Robot2", "Robot2": "Robot2"}))
                while 2 not in got:
                    message = await ws.recv()
                    if isinstance(message, bytes) and message[0] == 1:
                        got[struct.unpack("<I", message[1:5])[0]] = message[13:]
        assert len(got[1]) > 1000  # the racks of the warehouse
        task = json.loads(got[2])
        assert (task["seq"], task["object"], task["assigned_to"], task["fate"]) == (7, "Gucci_bag_14", "Robot2", "assigned")
    finally:
        recorder.close()


def test_the_foxglove_layout_names_only_topics_the_recording_writes() -> None:
    layout = json.loads((ROOT / "examples" / "foxglove-layout.json").read_text())
    written = {"/warehouse", "/robots/markers", "/robots/poses", "/robots/state", "/tasks", "/robots/traffic", "/log"}
    named = set()
    for _panel, config in layout["configById"].items():
        named |= set(config.get("topics", {}))
        named |= {path["value"].split("{")[0].split(".")[0] for path in config.get("paths", [])}
        named |= {config[key] for key in ("topicPath", "topicToRender") if key in config}
    assert named and named <= written, named - written
    source = (ROOT / "coapkb" / "harness" / "recording.py").read_text()
    assert all(f'"{topic}"' in source for topic in written)


@pytest.mark.slow
async def test_keep_serving_serves_the_finished_run_until_ctrl_c(tmp_path: Path) -> None:
    """``--foxglove PORT --keep-serving``: the run ends, its summary and its
    recording are written, and a viewer opened afterwards still gets the
    channels, until Ctrl-C ends the command with status 0."""
    import signal

    from support import free_tcp_port

    port = free_tcp_port()
    out = tmp_path / "run.mcap"
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "coapkb", "team", "--robots", "3", "--tasks", "2", "--insecure", "--quiet",
        "--record", str(out), "--foxglove", str(port), "--keep-serving", cwd=ROOT,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    assert proc.stdout is not None
    try:
        lines: list[str] = []
        async with asyncio.timeout(180):
            while not lines or "until Ctrl-C" not in lines[-1]:
                line = (await proc.stdout.readline()).decode()
                assert line, "".join(lines)
                lines.append(line)
        assert any(line.startswith(f"recording written to {out}") for line in lines), lines
        assert lines[-1].startswith(f"foxglove: the run is over; still serving it on ws://127.0.0.1:{port}")
        with out.open("rb") as f:  # the recording is whole already
            assert sum(1 for _ in make_reader(f).iter_messages()) > 0
        async with websockets.connect(f"ws://127.0.0.1:{port}",
                                      subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            async with asyncio.timeout(10):
                advertised = json.loads(await ws.recv())
                while advertised["op"] != "advertise":
                    advertised = json.loads(await ws.recv())
            assert "/tasks" in {c["topic"] for c in advertised["channels"]}
        proc.send_signal(signal.SIGINT)
        assert await asyncio.wait_for(proc.wait(), 30) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
