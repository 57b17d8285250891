"""Robot configuration: a valid TOML file round-trips; every mistake is a ConfigError naming the field."""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import pytest

from coapkb.config import (
    ConfigError,
    CostModel,
    ExecutionModel,
    RobotConfig,
    StartState,
    config_from_bytes,
    config_to_dict,
    dump_config,
    load_config,
    parse_config,
)
from coapkb.harness.team import TeamSpec, robot_configs
from coapkb.transport.base import Endpoint

ROOT = Path(__file__).resolve().parent.parent
ONTOLOGIES = ROOT / "ontologies"

VALID_TOML = """\
robot_id = "Robot1"
bind = "coap://127.0.0.1:5701"
kb = ["{ontologies}/Location.owl"]
strategy = "compute-and-communicate"
query_timeout_s = 3

[start]
aisle = 2
rack = 7
battery_wh = 500          # an int where a float is expected is fine
payload_kg = 35.5

[cost]
reserve_wh = 15.0
unload_at_fraction = 0.5

[execution]
speed_m_s = 2.0
pick_s = 1.5
time_scale = 100.0

[team.Robot1]
endpoint = "coap://127.0.0.1:5701"
kbs = ["Location"]
[team.Robot2]
endpoint = "coap://127.0.0.1:5702"
kbs = ["Object"]
[team.Robot3]
endpoint = "coap://127.0.0.1:5703"
kbs = ["Capability"]
"""


def base() -> dict[str, Any]:
    """A valid configuration mapping, as tomllib would return it."""
    return {
        "robot_id": "Robot1",
        "bind": "coap://127.0.0.1:5701",
        "kb": [str(ONTOLOGIES / "Location.owl")],
        "team": {
            "Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Location"]},
            "Robot2": {"endpoint": "coap://127.0.0.1:5702", "kbs": ["Object"]},
            "Robot3": {"endpoint": "coap://127.0.0.1:5703", "kbs": ["Capability"]},
        },
    }


def test_valid_toml_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "robot1.toml"
    path.write_text(VALID_TOML.format(ontologies=ONTOLOGIES), encoding="utf-8")
    config = load_config(path)
    assert isinstance(config, RobotConfig)
    assert config.robot_id == "Robot1"
    assert config.bind == Endpoint("coap", "127.0.0.1", 5701)
    assert config.transport == "coap"
    assert config.kb_files == (ONTOLOGIES / "Location.owl",)
    assert config.strategy == "compute-and-communicate"
    assert config.query_timeout_s == 3.0 and isinstance(config.query_timeout_s, float)
    assert config.central is None
    assert config.start == StartState(aisle=2, rack=7, battery_wh=500.0, payload_kg=35.5)
    assert isinstance(config.start.battery_wh, float)
    assert config.cost == CostModel(reserve_wh=15.0, unload_at_fraction=0.5)
    assert config.execution == ExecutionModel(speed_m_s=2.0, pick_s=1.5, time_scale=100.0)
    assert list(config.team) == ["Robot1", "Robot2", "Robot3"]
    assert config.team["Robot2"].endpoint == Endpoint("coap", "127.0.0.1", 5702)
    assert config.team["Robot2"].kbs == ("Object",)
    assert config.holder_of("Location").robot_id == "Robot1"  # type: ignore[union-attr]
    assert config.holder_of("Object").robot_id == "Robot2"  # type: ignore[union-attr]
    assert config.holder_of("Capability").robot_id == "Robot3"  # type: ignore[union-attr]


def test_relative_kb_path_is_relative_to_the_config_file(tmp_path: Path) -> None:
    (tmp_path / "kbs").mkdir()
    owl = tmp_path / "kbs" / "Location.owl"
    owl.write_bytes((ONTOLOGIES / "Location.owl").read_bytes()[:100])
    text = VALID_TOML.format(ontologies="kbs")  # kb = ["kbs/Location.owl"]
    path = tmp_path / "r.toml"
    path.write_text(text, encoding="utf-8")
    assert load_config(path).kb_files == (owl,)


def test_defaults() -> None:
    config = parse_config(base())
    assert config.strategy == "compute-by-all"
    assert config.start == StartState()
    assert config.cost == CostModel()
    assert config.execution == ExecutionModel()


def test_without_start_a_robot_starts_at_the_depot() -> None:
    """Aisle 1, rack 0: the front end of the first aisle, in every warehouse."""
    assert parse_config(base()).start == StartState(aisle=1, rack=0, battery_wh=400.0, payload_kg=40.0)


def test_zmq_and_central_mode() -> None:
    data = base()
    data["bind"] = "zmq://127.0.0.1:6001"
    data["kb"] = []
    data["central"] = "tcp://127.0.0.1:6000"  # tcp:// is zmq
    data["team"] = {r: {"endpoint": f"zmq://127.0.0.1:600{i}"} for i, r in enumerate(["Robot1", "Robot2"], 1)}
    config = parse_config(data)
    assert config.transport == "zmq"
    assert config.central == Endpoint("zmq", "127.0.0.1", 6000)
    assert config.kb_files == ()



@pytest.mark.parametrize("central", [False, True])
def test_dump_config_is_read_back_as_the_same_config(tmp_path: Path, central: bool) -> None:
    data = base()
    data.update(strategy="compute-and-communicate", query_timeout_s=7.5,
                start={"aisle": 3, "rack": 9, "battery_wh": 312.5, "payload_kg": 31.4},
                cost={"reserve_wh": 12.0}, execution={"time_scale": 50.0, "pick_s": 2.0})
    if central:
        data.update(central="coap://127.0.0.1:5700", kb=[])
    config = parse_config(data)
    path = tmp_path / "elsewhere" / "robot.toml"
    path.parent.mkdir()
    path.write_text(dump_config(config), encoding="utf-8")
    assert load_config(path) == config
    assert parse_config(config_to_dict(config)) == config

def _edit(path: str, value: Any) -> dict[str, Any]:
    """base() with the dotted ``path`` set to ``value`` (or deleted if value is DELETE)."""
    data = copy.deepcopy(base())
    *parents, last = path.split(".")
    node = data
    for key in parents:
        node = node.setdefault(key, {})
    if value is DELETE:
        del node[last]
    else:
        node[last] = value
    return data


DELETE = object()

BAD = [
    # (id, dotted path, value, text that must appear in the message)
    ("missing robot_id", "robot_id", DELETE, "robot_id"),
    ("empty robot_id", "robot_id", "", "robot_id"),
    ("robot_id not a string", "robot_id", 1, "robot_id"),
    ("missing bind", "bind", DELETE, "bind"),
    ("bind with unknown scheme", "bind", "http://127.0.0.1:5701", "bind"),
    ("bind without port", "bind", "coap://127.0.0.1", "bind"),
    ("bind with bad port", "bind", "coap://127.0.0.1:99999", "bind"),
    ("bind not a string", "bind", 5701, "bind"),
    ("unknown strategy", "strategy", "compute-by-none", "strategy"),
    ("unknown KB module", "team.Robot2.kbs", ["Objects"], "team.Robot2.kbs"),
    ("teammate with another scheme", "team.Robot2.endpoint", "zmq://127.0.0.1:5702", "team.Robot2.endpoint"),
    ("teammate with bad endpoint", "team.Robot3.endpoint", "coap://nowhere", "team.Robot3.endpoint"),
    ("teammate without endpoint", "team.Robot3.endpoint", DELETE, "team.Robot3.endpoint"),
    ("teammate not a table", "team.Robot3", "coap://127.0.0.1:5703", "team.Robot3"),
    ("unknown teammate field", "team.Robot3.port", 5703, "team.Robot3.port"),
    ("team missing", "team", DELETE, "team"),
    ("unknown top-level field", "colour", "red", "colour"),
    ("start.aisle not int", "start.aisle", "1", "start.aisle"),
    ("start.aisle float", "start.aisle", 1.5, "start.aisle"),
    ("start.battery_wh string", "start.battery_wh", "full", "start.battery_wh"),
    ("start.battery_wh bool", "start.battery_wh", True, "start.battery_wh"),
    ("unknown start field", "start.altitude", 3, "start.altitude"),
    ("start not a table", "start", 3, "start"),
    ("negative battery", "start.battery_wh", -1.0, "start"),
    ("aisle 0 (aisles are numbered from 1)", "start.aisle", 0, "start: aisle 0"),
    ("negative rack", "start.rack", -1, "start: aisle"),
    ("cost.reserve_wh string", "cost.reserve_wh", "20", "cost.reserve_wh"),
    ("cost.unload_at_fraction out of range", "cost.unload_at_fraction", 1.5, "cost.unload_at_fraction"),
    ("negative reserve", "cost.reserve_wh", -1.0, "cost.reserve_wh"),
    ("unknown cost field", "cost.fuel", 1.0, "cost.fuel"),
    ("execution.time_scale string", "execution.time_scale", "fast", "execution.time_scale"),
    ("execution.speed_m_s list", "execution.speed_m_s", [1.0], "execution.speed_m_s"),
    ("zero time scale", "execution.time_scale", 0.0, "execution"),
    ("query_timeout_s string", "query_timeout_s", "3", "query_timeout_s"),
    ("query_timeout_s bool", "query_timeout_s", True, "query_timeout_s"),
    ("query_timeout_s zero", "query_timeout_s", 0, "query_timeout_s"),
    ("kb not a list", "kb", "Location.owl", "kb"),
    ("nonexistent kb file", "kb", ["/nonexistent/Location.owl"], "kb[0]"),
    ("central with another scheme", "central", "zmq://127.0.0.1:6000", "central"),
    ("central not a URI", "central", "nowhere", "central"),
]


@pytest.mark.parametrize("path,value,needle", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_field_names_the_field(path: str, value: Any, needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_edit(path, value))
    message = str(info.value)
    assert message.startswith(needle), message


def test_team_must_list_itself() -> None:
    data = base()
    data["robot_id"] = "Robot4"
    data["bind"] = "coap://127.0.0.1:5704"
    with pytest.raises(ConfigError, match=r"^team: .*Robot4"):
        parse_config(data)


@pytest.mark.parametrize("module", ["Object", "Location", "Capability"])
def test_nobody_holds_a_kb_in_distributed_mode(module: str) -> None:
    data = base()
    for mate in data["team"].values():
        mate["kbs"] = [kb for kb in mate["kbs"] if kb != module]
    with pytest.raises(ConfigError, match=rf"^team: nobody holds {module}"):
        parse_config(data)
    # The same team is fine with a central server.
    data["central"] = "coap://127.0.0.1:5700"
    assert parse_config(data).central is not None


def test_retransmission_is_no_longer_a_field() -> None:
    """The reliability layer is the only one, so nothing names it: a file
    that still does is told so, like any other unknown field."""
    with pytest.raises(ConfigError, match=r"^retransmission: unknown field"):
        parse_config(_edit("retransmission", "robust"))


def test_load_config_nonexistent_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(missing)


def test_load_config_not_toml(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("robot_id = \n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(path)


def test_load_config_not_utf8(tmp_path: Path) -> None:
    # Found by fuzzing: the decode error escaped load_config as a traceback.
    path = tmp_path / "bad.toml"
    path.write_bytes(b'robot_id = "R\x94"\n')
    with pytest.raises(ConfigError, match=r"not UTF-8: byte 13 is 0x94"):
        load_config(path)


def test_config_from_bytes_is_load_config_without_the_file(tmp_path: Path) -> None:
    """What the fuzzer feeds: the same reading (UTF-8, universal newlines,
    paths from the file's folder) and the same errors, with no file."""
    path = tmp_path / "robot1.toml"
    raw = VALID_TOML.format(ontologies=ONTOLOGIES).replace("\n", "\r").encode()  # old Mac line ends
    path.write_bytes(raw)
    assert config_from_bytes(raw, tmp_path / "robot1.toml") == load_config(path)
    with pytest.raises(ConfigError, match=r"^/nowhere/r.toml: not UTF-8: byte 13 is 0x94"):
        config_from_bytes(b'robot_id = "R\x94"\n', Path("/nowhere/r.toml"))


def test_load_config_prefixes_errors_with_the_path(tmp_path: Path) -> None:
    path = tmp_path / "robot1.toml"
    text = VALID_TOML.format(ontologies=ONTOLOGIES).replace('strategy = "compute-and-communicate"',
                                                            'strategy = "guess"')
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=rf"^{path}: strategy: 'guess'"):
        load_config(path)
    missing_kb = VALID_TOML.format(ontologies=tmp_path / "nowhere")
    path.write_text(missing_kb, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"kb\[0\]: no such file"):
        load_config(path)


def test_transport_tunables_reach_the_layer_and_bad_ones_name_their_field() -> None:
    from coapkb.transport import reliability_for

    base = {"robot_id": "Robot1", "bind": "coap://127.0.0.1:5701",
            "team": {"Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Object", "Location", "Capability"]}}}
    config = parse_config({**base, "link_kbps": 35, "transport": {"coap": {"silence_rto": 2, "window_max": 8}}})
    layer = reliability_for(config.transport, link_kbps=config.link_kbps, options=config.transport_options["coap"])
    assert (layer.settings.silence_rto, layer.settings.window_max, layer.settings.link_kbps) == (2.0, 8, 35.0)
    for table, message in [
        ({"coap": {"window_max": 1.5}}, "transport.coap.window_max: expected int"),
        ({"coap": {"silence_rto": 99.0}}, "transport.coap: need min_rto <= silence_rto <= max_rto"),
        ({"zmq": {"linger": 1}}, "transport.zmq.linger: unknown field (known: client_sndhwm,"),
        ({"zmq": {"observe_queue": 0}}, "transport.zmq.observe_queue: must be positive, got 0"),
        ({"zenoh": {"open_timeout_s": "soon"}}, "transport.zenoh.open_timeout_s: expected float, got 'soon'"),
        ({"carrier-pigeon": {}}, "transport.carrier-pigeon: unknown transport"),
    ]:
        with pytest.raises(ConfigError, match=re.escape(message)):
            parse_config({**base, "transport": table})


def test_a_nine_robot_teams_replicas_name_standbys_that_round_trip(tmp_path: Path) -> None:
    """Each robot of a writable nine-robot team lists the robot at its place in
    the next cluster, and as standbys the other holders of its modules in the
    next and the previous cluster; the TOML keeps which is which."""
    spec = TeamSpec(robots=9, kb_writable=True)
    endpoints = {f"Robot{i}": Endpoint("coap", "127.0.0.1", 5700 + i) for i in range(1, 10)}
    config = robot_configs(spec, endpoints)["Robot7"]
    pushed = [m.robot_id for m in config.replicas.values() if not m.standby]
    standbys = sorted(m.robot_id for m in config.replicas.values() if m.standby)
    assert pushed == ["Robot1"]
    assert standbys == ["Robot2", "Robot3", "Robot4", "Robot5", "Robot6"]
    assert all(set(m.kbs) & set(config.team["Robot7"].kbs) for m in config.replicas.values())
    path = tmp_path / "robot.toml"
    path.write_text(dump_config(config), encoding="utf-8")
    assert load_config(path) == config
