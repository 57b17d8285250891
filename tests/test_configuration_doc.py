"""docs/configuration.md against the configuration loader: every field the
loader accepts is documented, every documented field exists, and every
default the page gives is the dataclass's.  The loader's own list of known
fields comes from its "unknown field (known: ...)" message, so the page is
held against what ``parse_config`` really reads."""

from __future__ import annotations

import dataclasses
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from coapkb.config import (
    ConfigError,
    CostModel,
    DiscoveryConfig,
    ExecutionModel,
    RobotConfig,
    StartState,
    Teammate,
    parse_config,
)
from coapkb.security.settings import SecurityConfig
from coapkb.transport.coap.reliability import ReliabilitySettings
from coapkb.transport.dds.transport import DdsOptions
from coapkb.transport.zenoh.transport import ZenohOptions
from coapkb.transport.zmq.transport import ZmqOptions

DOC = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"

#: Section heading of the page -> (the config's key path, the dataclass it fills).
SECTIONS: dict[str, tuple[str, type]] = {
    "Top level": ("", RobotConfig),
    "`[start]`": ("start", StartState),
    "`[cost]`": ("cost", CostModel),
    "`[execution]`": ("execution", ExecutionModel),
    "`[security]`": ("security", SecurityConfig),
    "`[discovery]`": ("discovery", DiscoveryConfig),
    "`[team.NAME]`": ("team.Robot1", Teammate),
    "`[replicas.NAME]`": ("replicas.Robot4", Teammate),
    "`[transport.coap]`": ("transport.coap", ReliabilitySettings),
    "`[transport.zmq]`": ("transport.zmq", ZmqOptions),
    "`[transport.zenoh]`": ("transport.zenoh", ZenohOptions),
    "`[transport.dds]`": ("transport.dds", DdsOptions),
}
#: Top-level keys that are tables, each with a section of its own.
TABLES = {"start", "cost", "execution", "security", "discovery", "team", "replicas", "transport"}
#: TOML key -> dataclass field, where they differ.
RENAMED = {"kb": "kb_files", "transport": "transport_options"}
#: Defaults the loader gives where the dataclass has none.
LOADER_DEFAULTS: dict[str, Any] = {"kb_files": [], "kb_writable": True}
#: Dataclass fields that are not TOML keys (the table's key names the teammate).
NOT_KEYS: dict[type, set[str]] = {Teammate: {"robot_id"}, ReliabilitySettings: {"link_kbps"}, DdsOptions: {"settings"}}
#: Fields of a section's dataclass that another section alone takes (a teammate is no standby: a replica may be).
NOT_IN_SECTION: dict[str, set[str]] = {"`[team.NAME]`": {"standby"}}

MINIMAL: dict[str, Any] = {
    "robot_id": "Robot1",
    "bind": "coap://127.0.0.1:5701",
    "team": {"Robot1": {"endpoint": "coap://127.0.0.1:5701", "kbs": ["Object", "Location", "Capability"]}},
}


def documented() -> dict[str, dict[str, str]]:
    """Section heading -> field -> its default cell, from the page's tables."""
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            heading = line[3:].strip()
            current = sections.setdefault(heading, {}) if heading in SECTIONS else None
            continue
        row = re.match(r"^\| `([a-z_]+)` \| [^|]+ \| ([^|]+) \|", line)
        if current is not None and row:
            current[row.group(1)] = row.group(2).strip()
    return sections


def accepted(where: str) -> set[str]:
    """The fields the loader accepts at ``where`` (a dotted key path)."""
    data: dict[str, Any] = {**MINIMAL, "team": {k: dict(v) for k, v in MINIMAL["team"].items()}}
    target = data
    for key in where.split(".") if where else []:
        target = target.setdefault(key, {})
    target["no_such_field"] = 1
    with pytest.raises((ConfigError, ValueError)) as caught:
        parse_config(data)
    message = str(caught.value)
    known = re.search(r"unknown field \(known: ([^)]*)\)", message)
    assert known, f"the loader did not name its known fields at {where or 'top level'}: {message}"
    return {name.strip() for name in known.group(1).split(",")}


def test_the_page_has_every_section() -> None:
    assert set(documented()) == set(SECTIONS)


@pytest.mark.parametrize("heading", SECTIONS)
def test_every_field_the_loader_accepts_is_documented_and_no_other(heading: str) -> None:
    where, _ = SECTIONS[heading]
    fields = set(documented()[heading])
    if heading == "Top level":
        fields |= TABLES
    assert fields == accepted(where)


@pytest.mark.parametrize("heading", SECTIONS)
def test_every_dataclass_field_is_documented(heading: str) -> None:
    where, cls = SECTIONS[heading]
    keys = {RENAMED.get(name, name) for name in documented()[heading]}
    if heading == "Top level":
        keys |= {RENAMED.get(name, name) for name in TABLES}
    assert keys == {f.name for f in dataclasses.fields(cls)} - NOT_KEYS.get(cls, set()) - NOT_IN_SECTION.get(heading, set())


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if value is None or isinstance(value, (str, int, float, bool, list)):
        return value
    return str(value)  # an Endpoint or a Path: as written in TOML


@pytest.mark.parametrize("heading", SECTIONS)
def test_every_documented_default_is_the_dataclass_default(heading: str) -> None:
    _, cls = SECTIONS[heading]
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for name, cell in documented()[heading].items():
        field = fields[RENAMED.get(name, name)]
        if field.name in LOADER_DEFAULTS and cls is RobotConfig:
            default = LOADER_DEFAULTS[field.name]
        elif field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            assert cell == "required", f"{heading} {name}: no default in {cls.__name__}, the page says {cell}"
            continue
        if default is None:
            assert cell == "none", f"{heading} {name}: default None, the page says {cell}"
            continue
        literal = re.fullmatch(r"`(.+)`", cell)
        assert literal, f"{heading} {name}: default {default!r}, the page says {cell}"
        assert tomllib.loads(f"x = {literal.group(1)}")["x"] == _plain(default), f"{heading} {name}"
