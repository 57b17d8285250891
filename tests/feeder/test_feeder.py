"""The feeder as a component: its task stream, the team it reads from a
folder of TOML files, and feeding real robots (separate processes on
loopback, started by the harness) through :class:`~coapkb.feeder.Feeder`."""

from __future__ import annotations

import asyncio
import shutil
import socket
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import cbor2
import pytest
import tomli_w
from support import ROOT

from coapkb.agent.robot_state import Decision, LiveState, PlannedState, RobotState
from coapkb.config import ConfigError
from coapkb.feeder import (
    Feeder,
    FeederError,
    FeederSettings,
    Roster,
    TaskRecord,
    read_tasks_file,
    split_tasks,
    task_post,
)
from coapkb.feeder.channel import Channel
from coapkb.feeder.membership import Membership
from coapkb.feeder.task_poster import TaskPoster
from coapkb.feeder.team_folder import read_team_folder
from coapkb.harness.team import Team, TeamSpec
from coapkb.transport.base import Endpoint
from coapkb.transport.messages import ContentFormat, Method

EXAMPLE = ROOT / "examples" / "three-robots"


# --------------------------------------------------------------------------- the task stream


def test_a_task_post_is_the_documented_body() -> None:
    post = task_post(3, "Gucci_bag_14")
    assert (post.method, post.path, post.content_format) == (Method.POST, "/tasks", ContentFormat.CBOR)
    assert cbor2.loads(post.payload) == {"seq": 3, "object": "Gucci_bag_14"}
    assert cbor2.loads(task_post(7, "Bosch_rug_837", ["Robot2"]).payload) == {
        "seq": 7, "object": "Bosch_rug_837", "join": ["Robot2"]}
    named = task_post(7, "Bosch_rug_837", ["Robot2", "Robot3"], boots={"Robot2": 41, "Robot3": 0})
    assert cbor2.loads(named.payload)["join"] == [["Robot2", 41], "Robot3"]  # the process that took it, if known
    repeated = task_post(7, "Bosch_rug_837", ["Robot2"], boots={"Robot2": 41}, missed=["Robot3"])
    assert cbor2.loads(repeated.payload) == {"seq": 7, "object": "Bosch_rug_837", "join": [["Robot2", 41]],
                                             "missed": ["Robot3"]}  # named to Robot2 before, did not take it
    # A member that ran again as a new process while the task was posted, and did not take it.
    assert cbor2.loads(task_post(7, "Bosch_rug_837", restarted=["Robot3"]).payload) == {
        "seq": 7, "object": "Bosch_rug_837", "restarted": ["Robot3"]}


def test_a_lone_robots_membership_does_not_void_the_majoritys_decisions() -> None:
    """Robot1, left out by its teammates while it was cut off, back and
    joining alone, decides in a membership of its own whose epoch (the
    task's number) is ahead of theirs: the cluster's decision is still the
    majority's, and the lone robot's is void (simulator seeds 96 and 126 of
    the rejoin profile: the feeder voided the majority's, and every task the
    lone robot dropped under its fence went round again, picked already)."""
    channel = cast(Channel, SimpleNamespace(watcher=SimpleNamespace(down={})))
    poster = TaskPoster(channel, cast(Membership, None))
    record = TaskRecord(object="Apple", cluster=1, seq=10)
    lone = Decision(10, "Apple", assigned_to="Robot1", epoch=10, members=("Robot1",))
    majority = Decision(10, "Apple", assigned_to="Robot2", epoch=4, members=("Robot2", "Robot3"))
    poster._record(record, ["Robot1", "Robot2", "Robot3"], {"Robot1": lone, "Robot2": majority, "Robot3": majority},
                   [])
    assert record.decisions == {"Robot2": "Robot2", "Robot3": "Robot2"} and record.assigned_to == "Robot2"
    assert record.absent == {"Robot1": "left out of membership epoch 4 (its decision is void)"}


@pytest.mark.parametrize("robot1_decided,robot3_decided,rejoins", [
    (True, True, True), (False, True, True), (True, False, False)])
def test_a_robot_every_member_left_out_is_made_to_join_again(robot1_decided: bool, robot3_decided: bool,
                                                            rejoins: bool) -> None:
    """Robot1, cut off at the start and left out, never learned it and went
    on deciding in its own membership (simulator seeds 6028 and 16092 of
    nine robots with partitions), or was frozen through it and decided
    nothing (seed 27897).  Once every member of the newest membership is
    seen deciding without it, the feeder names it to join again; while one
    was not heard from, it does not (seed 4246: that one still counted it,
    and admitted it in another epoch)."""
    down = {**({} if robot1_decided else {"Robot1": "frozen"}), **({} if robot3_decided else {"Robot3": "cut"})}
    channel = cast(Channel, SimpleNamespace(watcher=SimpleNamespace(down=down)))
    poster = TaskPoster(channel, cast(Membership, None))
    record = TaskRecord(object="Apple", cluster=1, seq=2)
    apart = Decision(2, "Apple", assigned_to="Robot2", epoch=0, members=("Robot1", "Robot2", "Robot3"))
    majority = Decision(2, "Apple", assigned_to="Robot2", epoch=1, members=("Robot2", "Robot3"))
    decisions = {**({"Robot1": apart} if robot1_decided else {}), "Robot2": majority,
                 **({"Robot3": majority} if robot3_decided else {})}
    left_out = poster._record(record, ["Robot1", "Robot2", "Robot3"], decisions, [])
    assert "Robot1" in record.absent and "Robot1" not in record.decisions
    assert left_out == ({"Robot1": "left out of membership epoch 1 at task 2"} if rejoins else {})


@pytest.mark.parametrize("done,credited", [(2, True), (1, False)])
def test_a_job_done_before_a_power_cut_stays_in_the_record(done: int, credited: bool) -> None:
    """Robot1 and Robot3 decide task 7 for Robot1, which picks it and then
    dies with Robot3 in a power cut; Robot2, its holders gone, settles the
    task unavailable.  Robot1's last observed state counts the job (its
    second, after task 6): its decision is what happened, and the record
    gives it the pick (simulator, storage profile seeds 54749, 54974 and
    55904: voided, the record gave a picked object to nobody).  Seen with
    one job done, it did not do task 7, and its decision stays void."""
    state = RobotState("Robot1", PlannedState(1, 1, 100.0, 0.0, 0.0, seq=7), LiveState(1.0, 1.0, done=done))
    watcher = SimpleNamespace(down={"Robot1": "power cut", "Robot3": "power cut"}, states={"Robot1": state})
    channel = cast(Channel, SimpleNamespace(watcher=watcher))
    poster = TaskPoster(channel, Membership(channel))
    earlier = [TaskRecord(object="Muji_lamp", cluster=1, seq=6, assigned_to="Robot1")]
    record = TaskRecord(object="Lavazza_rice_sack", cluster=1, seq=7)
    decided = Decision(7, "Lavazza_rice_sack", assigned_to="Robot1")
    settled = Decision(7, "Lavazza_rice_sack", unavailable="no live robot holds the Location KB")
    poster._record(record, ["Robot1", "Robot2", "Robot3"], {"Robot1": decided, "Robot2": settled, "Robot3": decided},
                   earlier)
    assert "Robot3" in record.absent  # down, and did no job of it
    if credited:
        assert record.decisions == {"Robot1": "Robot1", "Robot2": None} and record.assigned_to == "Robot1"
        assert record.fate == "failed"  # the survivor decided otherwise: a split, as it was
    else:
        assert record.decisions == {"Robot2": None} and record.assigned_to is None
        assert record.fate == "unavailable"


def test_tasks_file_ignores_comments_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "tasks.txt"
    path.write_text("# header\nGucci_bag_14\n\n  Canon_tv_538   # a comment\n", encoding="utf-8")
    assert read_tasks_file(path) == ["Gucci_bag_14", "Canon_tv_538"]
    with pytest.raises(FeederError, match="cannot read tasks file"):
        read_tasks_file(tmp_path / "missing.txt")
    (tmp_path / "binary").write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(FeederError, match="not UTF-8"):
        read_tasks_file(tmp_path / "binary")


def test_tasks_are_shared_in_contiguous_near_equal_parts() -> None:
    assert split_tasks(list("abcdefg"), 3) == [["a", "b"], ["c", "d", "e"], ["f", "g"]]
    assert split_tasks(["a"], 2) == [[], ["a"]]


# --------------------------------------------------------------------------- the team from its TOML files


def _insecure_copy(tmp_path: Path, change: dict[str, dict] | None = None) -> Path:
    """The example's robots without [security] (no keys needed), kb paths
    absolute; ``change``: robot -> top-level fields to replace."""
    folder = tmp_path / "team"
    folder.mkdir()
    for path in sorted(EXAMPLE.glob("*.toml")):
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        data.pop("security")
        data["kb"] = [str((EXAMPLE / kb).resolve()) for kb in data["kb"]]
        data.update((change or {}).get(data["robot_id"], {}))
        (folder / path.name).write_text(tomli_w.dumps(data), encoding="utf-8")
    return folder


def test_the_team_is_read_from_its_robots_files(tmp_path: Path) -> None:
    team = read_team_folder(_insecure_copy(tmp_path))
    assert team.roster.clusters == [["Robot1", "Robot2", "Robot3"]]
    assert team.roster.endpoints == {f"Robot{i}": Endpoint("coap", "127.0.0.1", 5720 + i) for i in (1, 2, 3)}
    assert team.settings.transport == "coap" and team.settings.lease_s == 3.0
    assert team.credentials is None and team.security() is None
    assert team.start_command("Robot2") == f"coapkb agent --config {tmp_path / 'team' / 'Robot2.toml'}"


def test_the_example_needs_its_keys_first(tmp_path: Path) -> None:
    # A copy without keys: the README's own blocks make keys in the example folder.
    example = tmp_path / "examples" / "three-robots"
    shutil.copytree(EXAMPLE, example, ignore=shutil.ignore_patterns("keys"))
    (tmp_path / "ontologies").symlink_to(ROOT / "ontologies", target_is_directory=True)
    with pytest.raises(ConfigError, match="coapkb keys --team-dir .*examples/three-robots/keys"):
        read_team_folder(example)


@pytest.mark.parametrize("change, message", [
    ({"Robot2": {"team": {"Robot2": {"endpoint": "coap://127.0.0.1:5722"},
                          "Robot1": {"endpoint": "coap://127.0.0.1:5799"}}}}, "expects Robot1 at coap://127.0.0.1:5799"),
    ({"Robot3": {"team": {"Robot3": {"endpoint": "coap://127.0.0.1:5723"},
                          "Robot4": {"endpoint": "coap://127.0.0.1:5724"}}}}, "lists Robot4 in its team"),
    ({"Robot3": {"robot_id": "Robot1", "bind": "coap://127.0.0.1:5721"}}, "are both Robot1"),
])
def test_a_team_that_does_not_add_up_is_one_error(tmp_path: Path, change: dict, message: str) -> None:
    for robot in change.values():  # the team tables above need KBs for every module: hold them all
        if "team" in robot:
            for mate in robot["team"].values():
                mate["kbs"] = ["Location", "Object", "Capability"]
    with pytest.raises(FeederError, match=message):
        read_team_folder(_insecure_copy(tmp_path, change))


def test_a_folder_without_robots_is_one_error(tmp_path: Path) -> None:
    with pytest.raises(FeederError, match="no such team folder"):
        read_team_folder(tmp_path / "nowhere")
    with pytest.raises(FeederError, match=r"no robot configuration \(\*\.toml\)"):
        read_team_folder(tmp_path)


# --------------------------------------------------------------------------- feeding real robots


def _silent_endpoint() -> Endpoint:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # closed again: nobody listens there
        s.bind(("127.0.0.1", 0))
        return Endpoint("coap", "127.0.0.1", s.getsockname()[1])


async def test_a_robot_that_does_not_answer_is_named_before_any_task() -> None:
    roster = Roster({"Robot1": _silent_endpoint()}, [["Robot1"]])
    async with Feeder.open(roster, FeederSettings("coap")) as feeder:
        with pytest.raises(FeederError, match=r"Robot1 does not answer at coap://127\.0\.0\.1:\d+ .*; start it"):
            await feeder.check_ready(2.0, {"Robot1": "start it"})


@pytest.mark.slow
async def test_the_feeder_feeds_a_secure_team_in_order() -> None:
    """Three robots (processes, OSCORE): every task decided by all, in order,
    each robot's executions counted; a second feeder goes on where the
    first one stopped."""
    tasks = ["Gucci_bag_14", "Nonexistent_widget_1", "Canon_tv_538", "Zara_jacket_396"]
    more = ["Gucci_bag_187", "Ikea_cookware_set_442"]
    async with asyncio.timeout(180):
        async with Team.launch(TeamSpec(robots=3)) as team:
            assert team.feeder_security() is not None
            seen: list[TaskRecord] = []
            async with Feeder.open(team.roster(), team.feeder_settings(), team.feeder_security()) as feeder:
                await feeder.check_ready(10.0)
                outcome = await feeder.feed(tasks, seen.append)
                assert feeder.traffic.messages_sent > 0
            async with Feeder.open(team.roster(), team.feeder_settings(), team.feeder_security()) as feeder:
                await feeder.check_ready(10.0)
                then = await feeder.feed(more)
                stats = await feeder.collect_stats(team.spec.robot_ids)
    assert seen == outcome.tasks
    assert [(t.seq, t.object) for t in outcome.tasks] == list(enumerate(tasks, 1))
    assert [t.fate for t in outcome.tasks] == ["assigned", "skipped", "assigned", "assigned"]
    assert all(t.agreed and set(t.decisions) == set(team.spec.robot_ids) for t in outcome.tasks + then.tasks)
    assert 0 < outcome.coordination_s <= outcome.completion_s
    assert [(t.seq, t.object, t.fate) for t in then.tasks] == [(5, more[0], "assigned"), (6, more[1], "assigned")]
    assert sum(s.executed for s in stats.values()) == 5


async def test_a_robot_started_again_by_hand_joins_at_the_next_feed() -> None:
    """Robot2 restarted by hand after a feed: a new process that took no
    task while its teammates took one.  The next feeder has it join them at
    its first task, and it takes part in the decisions from there."""
    async with asyncio.timeout(120):
        async with Team.launch(TeamSpec(robots=3, security=False)) as team:
            async with Feeder.open(team.roster(), team.feeder_settings()) as feeder:
                await feeder.check_ready(10.0)
                await feeder.feed(["Gucci_bag_14"])
            await team.kill("Robot2")
            await team.restart("Robot2")
            async with Feeder.open(team.roster(), team.feeder_settings()) as feeder:
                await feeder.check_ready(10.0)
                outcome = await feeder.feed(["Gucci_bag_15", "Gucci_bag_16"])
    assert [t.seq for t in outcome.tasks] == [2, 3]
    assert all(t.agreed and set(t.decisions) == set(team.spec.robot_ids) for t in outcome.tasks), outcome.tasks


async def test_a_post_to_a_restarted_robot_is_forgotten_not_delivered_to_its_new_process() -> None:
    """The feeder stops the posts still in flight to a robot it is told has
    restarted: a retransmission of the old process's post would reach the
    new process as a task of its own (simulator seed 3291 of the 3-robot
    mixed profile: the new process picked it, and so did the robot it went
    round again to)."""
    from coapkb.agent.observed_states import OUTCOME_PATH, ObservedStates
    from coapkb.feeder.channel import Channel, FeederSettings
    from coapkb.feeder.roster import Roster

    class Silent:
        """A robot that never answers: the post stays in flight."""

        counters = None

        async def request(self, peer: Endpoint, request: object, *, timeout: float) -> object:
            await asyncio.Event().wait()

        async def aclose(self) -> None:
            pass

    endpoint = Endpoint("coap", "127.0.0.1", 5683)
    watcher = ObservedStates(Silent(), {"Robot1": endpoint}, OUTCOME_PATH, liveness=True)  # type: ignore[arg-type]
    channel = Channel(Silent(), watcher, Roster({"Robot1": endpoint}, [["Robot1"]]),  # type: ignore[arg-type]
                      FeederSettings(transport="coap"))
    posting = asyncio.create_task(channel.post_task("Robot1", task_post(1, "Gucci_bag_14"), 1, "Gucci_bag_14"))
    await asyncio.sleep(0)
    channel.forget_posts("Robot1")
    await asyncio.wait_for(posting, 1)  # returns: the post is void, not an error
    assert posting.result() is None and not channel._posting.get("Robot1")


@pytest.mark.looptime  # the retries' sleeps on the event loop's own clock
async def test_a_robot_that_may_be_dead_is_asked_its_statistics_once() -> None:
    """A robot the run's end may find dead (``maybe``) is asked once: asked
    again for a task timeout, a robot killed just before the end held the
    statistics of the others, and the restart scheduled for it waited
    behind them past the test's bound (a secure team restarting a robot,
    on a busy machine).  A robot counted alive is asked again, as before."""
    from coapkb.feeder.robot_stats import collect_stats
    from coapkb.transport.base import PeerGone

    asked: list[str] = []

    async def request(endpoint: str, request: object, *, timeout: float) -> object:
        asked.append(endpoint)
        raise PeerGone(f"nothing listens at {endpoint}")

    channel = SimpleNamespace(client=SimpleNamespace(request=request), endpoint=lambda robot_id: robot_id,
                              settings=SimpleNamespace(task_timeout_s=60.0, query_timeout_s=5.0))
    loop = asyncio.get_running_loop()
    started = loop.time()
    assert await collect_stats(cast(Channel, channel), [], ["Robot3"]) == {}
    assert asked == ["Robot3"] and loop.time() - started < 1.0
    with pytest.raises(PeerGone):
        await collect_stats(cast(Channel, channel), ["Robot2"])
    assert asked.count("Robot2") > 1 and loop.time() - started >= 60.0
