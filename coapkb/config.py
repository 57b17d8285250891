"""Configuration (the seed's Fig. 2): a robot's fixed parameters, from TOML.

Read once at start-up and never changed while running, as in the seed.  It
holds the robot-vs-KB map of the team, so the Query Handler knows where each
knowledge base lives.  Every field is validated into frozen dataclasses
(:class:`RobotConfig` and its sections); a mistake is reported as a
:class:`ConfigError` naming the field.  Relative paths (``kb``,
``kb_index``, ``[security] credentials``) resolve against the folder of the
TOML file, not the working directory.

docs/configuration.md is the reference: an example, and every field with
its type, default and meaning (``tests/test_configuration_doc.py`` holds it
to this module).  ``examples/three-robots/`` holds a whole team of three.
"""

from __future__ import annotations

import dataclasses
import io
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import tomli_w

from .errors import CoapkbError
from .security.settings import SecurityConfig, parse_security
from .transport.base import Endpoint
from .transport.registry import parse_endpoint, transport_for
from .typed_fields import typed_fields

KB_MODULES = ("Object", "Location", "Capability")
STRATEGIES = ("compute-by-all", "compute-and-communicate")
DISCOVERY_METHODS = ("static", "rd")


class ConfigError(CoapkbError, ValueError):
    """A configuration mistake; the message names the field."""


@dataclass(frozen=True)
class Teammate:
    robot_id: str
    endpoint: Endpoint
    #: Knowledge-base modules this teammate serves (e.g. ``("Object",)``).
    kbs: tuple[str, ...] = ()
    #: A replica asked only when this robot's usual holders of a module do
    #: not answer (``[replicas.NAME] standby = true``).
    standby: bool = False


@dataclass(frozen=True)
class StartState:
    """Where a robot starts and what it carries.  The default position is
    the depot (aisle 1, rack 0: the front end of the first aisle), which
    every warehouse has; aisles are numbered from 1, and rack 0 and
    ``racks_per_aisle + 1`` are an aisle's ends on the cross-aisles."""

    aisle: int = 1
    rack: int = 0
    battery_wh: float = 400.0
    payload_kg: float = 40.0


@dataclass(frozen=True)
class CostModel:
    """Team-wide rules of the Task Assigner (each robot's energy use per metre
    and per pick comes from the Capability KB)."""

    #: Battery a robot keeps in reserve: it never takes a task that would dip below.
    reserve_wh: float = 20.0
    #: After a pick that loads the robot to this fraction of its payload, it
    #: carries everything to the depot and unloads (part of that task's cost).
    unload_at_fraction: float = 0.75
    #: Power a charging dock delivers, W: charging E Wh takes E / charge_w hours.
    charge_w: float = 500.0
    #: What a second at a dock adds to a task's cost, Wh: about the energy a
    #: working robot spends per second (1.5 m/s at 0.03 Wh/m), so a robot
    #: that must charge first takes a task only when that beats one that need not.
    charge_time_wh_per_s: float = 0.05


@dataclass(frozen=True)
class ExecutionModel:
    """How the Task Executor simulates motion."""

    speed_m_s: float = 1.5
    pick_s: float = 4.0
    #: Simulated seconds per wall-clock second (1.0 = real time).
    time_scale: float = 20.0


@dataclass(frozen=True)
class DiscoveryConfig:
    """How a robot finds its teammates (``[discovery]``): ``static`` takes
    the ``team`` table as it is; ``rd`` registers this robot in a Resource
    Directory and looks its cluster up there (:mod:`coapkb.discovery`)."""

    method: str = "static"
    #: The Resource Directory (``rd`` only); None = find it by multicast
    #: (``GET /.well-known/core?rt=core.rd*`` to All-CoAP-Nodes on the
    #: interface of ``bind``).
    rd: Endpoint | None = None
    #: The UDP port multicast discovery asks on (CoAP's own by default).
    multicast_port: int = 5683
    #: The team member whose credential the directory must show under
    #: OSCORE/EDHOC (the feeder hosts it in ``coapkb team``).
    rd_identity: str = "feeder"
    #: This robot's cluster: the directory's sector (``d=``); teammates are
    #: the robots registered in the same one.
    cluster: str = "team"
    #: Robots of the cluster, this one included: discovery waits for them all.
    members: int = 3
    #: Registration lifetime (``lt=``, whole seconds); renewed at half of it,
    #: so a robot that dies is gone from the directory within this time.
    lifetime_s: int = 60
    #: How long to wait for the whole cluster before falling back to the
    #: robots registered so far and the ``team`` table.
    wait_s: float = 30.0


@dataclass(frozen=True)
class RobotConfig:
    robot_id: str
    bind: Endpoint
    kb_files: tuple[Path, ...]
    team: Mapping[str, Teammate]
    start: StartState = field(default_factory=StartState)
    strategy: str = "compute-by-all"
    #: Where all KBs live in the centralised baseline; None = distributed.
    central: Endpoint | None = None
    query_timeout_s: float = 20.0
    #: Rate of the robot's radio link (kbit/s), if known: the reliability
    #: layer adds each exchange's airtime to its timeout and sizes its window.
    link_kbps: float | None = None
    cost: CostModel = field(default_factory=CostModel)
    execution: ExecutionModel = field(default_factory=ExecutionModel)
    #: OSCORE keyed by EDHOC and the team's access policy (``[security]``); None = unprotected.
    security: SecurityConfig | None = None
    #: Keep the KB as an on-disk index here (built once, opened in
    #: milliseconds at every later start); None = load it into memory.
    kb_index: Path | None = None
    #: The fence (coapkb.agent.lease): this robot picks only while a majority
    #: of its cluster has granted it a lease this long, seconds; 0 = no fence.
    lease_s: float = 3.0
    #: How the teammates are found (``[discovery]``); default: the ``team`` table.
    discovery: DiscoveryConfig = field(default_factory=DiscoveryConfig)
    #: Take writes and replicate them with the holders of its modules, and
    #: write what the robot does into the KB.  A TOML file's default is true
    #: (false with ``kb_index`` or ``central``: :func:`parse_config`); a
    #: configuration built in code says which it wants.
    kb_writable: bool = False
    #: Holders of its modules in other clusters (``[replicas]``): writes pass on to them.
    replicas: Mapping[str, Teammate] = field(default_factory=dict)
    #: The Unix socket of a simulated world shared by the team (``coapkb
    #: world``): what the robot finds at the shelf; None: the KB's word.
    world: Path | None = None
    #: Where a writable robot keeps its modules' writes (a journal and
    #: snapshots, docs/knowledge.md): a restart reads them back; None: in
    #: memory only, lost when the process stops.
    data_dir: Path | None = None
    #: ``[transport.SCHEME]`` tables: scheme -> the tunables of that
    #: transport's layer (CoAP's reliability layer: docs/configuration.md).
    transport_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @property
    def transport(self) -> str:
        return self.bind.scheme

    def holder_of(self, kb: str) -> Teammate | None:
        """The teammate that serves KB module ``kb`` (this robot if it has it)."""
        holders = self.holders_of(kb)
        return holders[0] if holders else None

    def holders_of(self, kb: str) -> list[Teammate]:
        """Every teammate serving KB module ``kb`` (replicas), this robot first,
        then in robot-id order: the order the Query Handler fails over in."""
        me = self.team[self.robot_id]
        others = sorted((m for m in self.team.values() if m is not me and kb in m.kbs), key=lambda m: m.robot_id)
        return ([me] if kb in me.kbs else []) + others


def load_config(path: str | Path) -> RobotConfig:
    """Read and validate a robot's TOML configuration."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror}") from None
    return config_from_bytes(raw, path)


def config_from_bytes(raw: bytes, path: Path) -> RobotConfig:
    """What :func:`load_config` makes of ``raw`` as the contents of ``path``
    (its relative paths taken from ``path``'s folder), without the file."""
    try:
        # Read as a text file is: UTF-8, universal newlines.
        data = tomllib.loads(io.TextIOWrapper(io.BytesIO(raw), encoding="utf-8").read())
    except UnicodeDecodeError as exc:  # TOML is UTF-8 (a ValueError, but no ConfigError)
        raise ConfigError(f"{path}: not UTF-8: byte {exc.start} is {exc.object[exc.start]:#04x}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    try:
        return parse_config(data, base_dir=path.parent)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def config_to_dict(config: RobotConfig) -> dict[str, Any]:
    """The mapping :func:`parse_config` reads back into an equal ``config``
    (file paths absolute, so it does not depend on where it is written)."""
    data: dict[str, Any] = {
        "robot_id": config.robot_id,
        "bind": str(config.bind),
        "kb": [str(path.resolve()) for path in config.kb_files],
        "strategy": config.strategy,
        "query_timeout_s": config.query_timeout_s,
        "lease_s": config.lease_s,
    }
    if config.link_kbps is not None:
        data["link_kbps"] = config.link_kbps
    if config.central is not None:
        data["central"] = str(config.central)
    if config.kb_index is not None:
        data["kb_index"] = str(config.kb_index.resolve())
    if config.security is not None:
        data["security"] = config.security.to_dict()
    data["start"] = asdict(config.start)
    data["cost"] = asdict(config.cost)
    data["execution"] = asdict(config.execution)
    if config.discovery != DiscoveryConfig():
        discovery = asdict(config.discovery)
        discovery["rd"] = None if config.discovery.rd is None else str(config.discovery.rd)
        data["discovery"] = {k: v for k, v in discovery.items() if v is not None}
    data["team"] = {m.robot_id: {"endpoint": str(m.endpoint), "kbs": list(m.kbs)} for m in config.team.values()}
    # Always said: the TOML's default depends on other fields (parse_config).
    data["kb_writable"] = config.kb_writable
    if config.replicas:
        data["replicas"] = {m.robot_id: {"endpoint": str(m.endpoint), "kbs": list(m.kbs)}
                            | ({"standby": True} if m.standby else {}) for m in config.replicas.values()}
    if config.world is not None:
        data["world"] = str(config.world.resolve())
    if config.data_dir is not None:
        data["data_dir"] = str(config.data_dir.resolve())
    if config.transport_options:
        data["transport"] = {scheme: dict(options) for scheme, options in config.transport_options.items()}
    return data


def dump_config(config: RobotConfig) -> str:
    """``config`` as TOML that :func:`load_config` reads back into an equal config."""
    return tomli_w.dumps(config_to_dict(config))


#: :class:`RobotConfig`'s fields whose TOML key is another.
_TOML_KEYS = {"kb_files": "kb", "transport_options": "transport"}
#: Top-level settings of a plain type: typed and defaulted by their declaration in :class:`RobotConfig`.
_PLAIN = ("strategy", "query_timeout_s", "link_kbps", "lease_s", "kb_writable")


def parse_config(data: Mapping[str, Any], base_dir: Path = Path(".")) -> RobotConfig:
    """Validate a configuration mapping (as read from TOML)."""
    _no_unknown(data, {_TOML_KEYS.get(f.name, f.name) for f in dataclasses.fields(RobotConfig)}, "")
    robot_id = _get(data, "robot_id", str)
    if not robot_id:
        raise ConfigError("robot_id: must not be empty")
    bind = _endpoint(_get(data, "bind", str), "bind")
    kb_files = tuple(_path(base_dir, p, f"kb[{i}]") for i, p in enumerate(_get(data, "kb", list, [])))
    kb_index = data.get("kb_index")
    if kb_index is not None and not isinstance(kb_index, str):
        raise ConfigError(f"kb_index: expected a directory path, got {type(kb_index).__name__}")
    try:
        plain = typed_fields(RobotConfig, {k: data[k] for k in _PLAIN if k in data}, _PLAIN)
    except ValueError as exc:  # names the field
        raise ConfigError(str(exc)) from None
    team = _teammates(_get(data, "team", dict), "team", bind)
    replicas = _teammates(_get(data, "replicas", dict, {}), "replicas", bind)
    if robot_id in replicas or set(replicas) & set(team):
        raise ConfigError("replicas: list robots of other clusters, not this robot or its teammates")
    if robot_id not in team:
        raise ConfigError(f"team: must list this robot ({robot_id}) too")
    try:
        security = None if data.get("security") is None else parse_security(data["security"], base_dir)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    central = data.get("central")
    central_ep = _endpoint(central, "central") if central is not None else None
    if "kb_writable" not in plain:
        # A team's KB follows the world by default (the paper's Location KB
        # holds the robots' positions as they move); an index on disk is
        # opened read-only, and a centralised robot holds no module.
        plain["kb_writable"] = kb_index is None and central_ep is None
    elif plain["kb_writable"] and kb_index is not None:
        raise ConfigError("kb_writable: a writable KB is kept in memory; with kb_index (opened read-only "
                          "from disk) set kb_writable = false or leave kb_index out")
    config = RobotConfig(
        robot_id=robot_id,
        bind=bind,
        kb_files=kb_files,
        team=team,
        start=_section(data, "start", StartState),
        central=central_ep,
        cost=_section(data, "cost", CostModel),
        execution=_section(data, "execution", ExecutionModel),
        security=security,
        kb_index=None if kb_index is None else (base_dir / kb_index),
        discovery=_discovery(data),
        replicas=replicas,
        world=None if data.get("world") is None else base_dir / _get(data, "world", str),
        data_dir=_data_dir(data, base_dir),
        transport_options=_transport_options(_get(data, "transport", dict, {}), bind.scheme),
        **plain,
    )
    _check_values(config)
    return config


def _data_dir(data: Mapping[str, Any], base_dir: Path) -> Path | None:
    if data.get("data_dir") is None:
        return None
    text = _get(data, "data_dir", str)
    if not text:
        raise ConfigError("data_dir: must not be empty (leave it out to keep writes in memory only)")
    path = base_dir / text
    if path.exists() and not path.is_dir():
        raise ConfigError(f"data_dir: {path} is not a folder")
    return Path(path)


def _transport_options(table: Mapping[str, Any], scheme: str) -> dict[str, dict[str, Any]]:
    """``[transport.SCHEME]`` tables, each checked by its transport's layer
    (the robot's own transport's is the one used; another's is still checked,
    so a typo does not wait for the day the robot changes transport)."""
    from .transport import check_table

    options: dict[str, dict[str, Any]] = {}
    for name, section in table.items():
        if not isinstance(section, dict):
            raise ConfigError(f"transport.{name}: expected a table")
        try:
            check_table(name, section)  # an unknown scheme raises too
        except ValueError as exc:
            # "FIELD: why" names a field of the table; anything else is about the table.
            field_name = str(exc).split(":", 1)[0]
            where = f"transport.{name}." if field_name in section else f"transport.{name}: "
            raise ConfigError(f"{where}{exc}") from None
        options[name] = dict(section)
    return options


def _teammates(table: Mapping[str, Any], section: str, bind: Endpoint) -> dict[str, Teammate]:
    team = {}
    for mate_id, mate in table.items():
        where = f"{section}.{mate_id}"
        if not isinstance(mate, dict):
            raise ConfigError(f"{where}: expected a table")
        _no_unknown(mate, {"endpoint", "kbs", "standby"} if section == "replicas" else {"endpoint", "kbs"}, where + ".")
        endpoint = _endpoint(_get(mate, "endpoint", str, where=where), where + ".endpoint")
        kbs = tuple(_get(mate, "kbs", list, [], where=where))
        standby = _get(mate, "standby", bool, False, where=where)
        for kb in kbs:
            if kb not in KB_MODULES:
                raise ConfigError(f"{where}.kbs: unknown KB module {kb!r} (choose from {', '.join(KB_MODULES)})")
        if endpoint.scheme != bind.scheme:
            raise ConfigError(f"{where}.endpoint: {endpoint.scheme} teammate, but this robot uses {bind.scheme}")
        team[mate_id] = Teammate(mate_id, endpoint, kbs, standby)
    return team


def _check_values(c: RobotConfig) -> None:
    if c.strategy not in STRATEGIES:
        raise ConfigError(f"strategy: {c.strategy!r} is not one of {', '.join(STRATEGIES)}")
    if c.query_timeout_s <= 0:
        raise ConfigError("query_timeout_s: must be positive")
    if c.lease_s < 0:
        raise ConfigError("lease_s: must not be negative (0 turns the fence off)")
    if c.link_kbps is not None and c.link_kbps <= 0:
        raise ConfigError("link_kbps: must be positive")
    if c.start.battery_wh <= 0 or c.start.payload_kg <= 0:
        raise ConfigError("start: battery_wh and payload_kg must be positive")
    if c.start.aisle < 1 or c.start.rack < 0:
        raise ConfigError(
            f"start: aisle {c.start.aisle}, rack {c.start.rack} is outside the warehouse "
            "(aisles are numbered from 1, racks from 0; leave [start] out to start at the depot, aisle 1, rack 0)"
        )
    if c.execution.speed_m_s <= 0 or c.execution.time_scale <= 0 or c.execution.pick_s < 0:
        raise ConfigError("execution: speed_m_s and time_scale must be positive, pick_s non-negative")
    if c.cost.reserve_wh < 0:
        raise ConfigError("cost.reserve_wh: must not be negative")
    if not 0 < c.cost.unload_at_fraction <= 1:
        raise ConfigError("cost.unload_at_fraction: must be in (0, 1]")
    if not c.cost.charge_w > 0:
        raise ConfigError("cost.charge_w: must be positive")
    if c.cost.charge_time_wh_per_s < 0:
        raise ConfigError("cost.charge_time_wh_per_s: must not be negative")
    if c.discovery.method == "rd" and not transport_for(c.transport).resource_directory:
        raise ConfigError(f"discovery.method: a Resource Directory speaks CoAP, but this robot uses {c.transport}")
    if c.central is None:
        # With a directory the teammates, and so the holders, are found at start-up.
        missing = [kb for kb in KB_MODULES if c.holder_of(kb) is None]
        if missing and c.discovery.method == "static":
            raise ConfigError(f"team: nobody holds {', '.join(missing)} (and no central server is set)")
    elif c.central.scheme != c.bind.scheme:
        raise ConfigError(f"central: {c.central.scheme} server, but this robot uses {c.bind.scheme}")


def _discovery(data: Mapping[str, Any]) -> DiscoveryConfig:
    discovery = _section(data, "discovery", DiscoveryConfig, convert={"rd": _endpoint_value})
    if discovery.method not in DISCOVERY_METHODS:
        raise ConfigError(f"discovery.method: {discovery.method!r} is not one of {', '.join(DISCOVERY_METHODS)}")
    if discovery.rd is not None and not transport_for(discovery.rd.scheme).resource_directory:
        raise ConfigError(f"discovery.rd: a Resource Directory is a coap:// endpoint, got {discovery.rd}")
    if not 0 < discovery.multicast_port < 65536:
        raise ConfigError("discovery.multicast_port: must be a UDP port (1-65535)")
    if not discovery.cluster or not all(c.isalnum() or c in "-_." for c in discovery.cluster):
        raise ConfigError(f"discovery.cluster: letters, digits, '-', '_' and '.' only, got {discovery.cluster!r}")
    if discovery.members < 1:
        raise ConfigError("discovery.members: must be at least 1")
    if discovery.lifetime_s < 1:
        raise ConfigError("discovery.lifetime_s: must be at least 1 (seconds)")
    if discovery.wait_s <= 0:
        raise ConfigError("discovery.wait_s: must be positive")
    return discovery


def _no_unknown(data: Mapping[str, Any], known: set[str], where: str) -> None:
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"{where}{unknown[0]}: unknown field (known: {', '.join(sorted(known))})")


_MISSING = object()


def _get(data: Mapping[str, Any], key: str, kind: Any, default: Any = _MISSING, where: str = "") -> Any:
    name = f"{where}.{key}" if where else key
    if key not in data:
        if default is _MISSING:
            raise ConfigError(f"{name}: missing")
        return default
    value = data[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        kinds = kind if isinstance(kind, tuple) else (kind,)
        raise ConfigError(f"{name}: expected {' or '.join(k.__name__ for k in kinds)}, got {value!r}")
    return value


def _endpoint_value(text: Any) -> Endpoint:
    """ValueError saying why ``text`` is not an endpoint."""
    if not isinstance(text, str):
        raise ValueError("expected a URI string like coap://127.0.0.1:5683")
    return parse_endpoint(text)


def _endpoint(text: Any, name: str) -> Endpoint:
    try:
        return _endpoint_value(text)
    except ValueError as exc:
        raise ConfigError(f"{name}: {exc}") from None


def _path(base_dir: Path, value: Any, name: str) -> Path:
    if not isinstance(value, str):
        raise ConfigError(f"{name}: expected a file path")
    path = Path(value) if Path(value).is_absolute() else base_dir / value
    if not path.is_file():
        raise ConfigError(f"{name}: no such file {path}")
    return path


T = TypeVar("T")


def _section(data: Mapping[str, Any], key: str, cls: type[T],
             convert: Mapping[str, Callable[[Any], Any]] | None = None) -> T:
    section = data.get(key, {})
    if not isinstance(section, dict):
        raise ConfigError(f"{key}: expected a table")
    try:
        values = typed_fields(cls, section, convert=convert)
    except ValueError as exc:  # names the field
        raise ConfigError(f"{key}.{exc}") from None
    return cls(**values)
