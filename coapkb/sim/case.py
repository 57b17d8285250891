"""One simulated run written out whole: a case file that replays it.

A seed alone replays a run only with the options it ran under, and only
as long as the seed still draws the same schedule and tasks.  A
:class:`SimCase` holds everything instead: the seed (it still drives the
network's draws, the robots' randomness and the operator's writes), the
team, the link faults, the task list and every fault event with all its
fields.  ``coapkb sim --shrink FILE`` writes one (:mod:`.shrink`) and
``coapkb sim --replay FILE`` runs it again.

The file is JSON::

    {"format": "coapkb-sim-case", "version": 1, "seed": 24, "robots": 3,
     "strategy": "compute-by-all", "faults": "loss=0.05", "writes": 0,
     "tasks": ["Uniqlo_dress_255", ...],
     "events": [{"at_s": 3.19, "action": "kill", "targets": ["Robot1"], ...}, ...],
     "violates": "check_finished", ...}
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from ..errors import CoapkbError
from ..harness.team import DEFAULT_ONTOLOGIES
from .faults import ACTIONS, LINK_KINDS, SWARM, FaultEvent, FaultMix, FaultSpecError
from .run import KBCache, SimSpec, SimulatedTeam

FORMAT = "coapkb-sim-case"
VERSION = 1
#: The spec's fields a case holds in its own keys (or cannot hold: a scenario is code).
_OWN_KEYS = frozenset({"robots", "tasks", "strategy", "faults", "ontologies", "task_list", "schedule", "scenario",
                       "writes"})


def settings_defaults() -> dict[str, bool | int | float | str]:
    """The spec's other plain settings and their defaults (timeouts, the time
    scale, the replication, ...): a case keeps those that differ."""
    found: dict[str, bool | int | float | str] = {}
    for f in fields(SimSpec):
        if f.name not in _OWN_KEYS and isinstance(f.default, (bool, int, float, str)):
            found[f.name] = f.default
    return found
_ROBOT = re.compile(r"Robot([1-9][0-9]*)")


class CaseFileError(CoapkbError, ValueError):
    """A case file that is missing, unreadable or malformed (one line says which and why)."""


def mix_text(mix: FaultMix) -> str:
    """``mix`` as ``--faults`` reads it, its amounts exact (``FaultMix.describe`` rounds)."""
    parts = list(mix.events)
    parts += [f"{kind}={getattr(mix, kind)!r}" for kind in LINK_KINDS if getattr(mix, kind)]
    parts += [SWARM] if mix.swarm else []
    return ",".join(parts) or "none"


@dataclass(frozen=True)
class SimCase:
    """One run, exactly: what :meth:`spec` and :attr:`seed` give to
    :func:`~coapkb.sim.run.run_seed`.  ``violates`` and ``finding`` say what
    the run broke when it was written (the first invariant that failed and
    its first line); they are not needed to run it."""

    seed: int
    robots: int
    strategy: str
    #: The fault mix as ``--faults`` reads it: its link faults shape every
    #: link; its event kinds do nothing here (``events`` are the schedule).
    faults: str
    tasks: tuple[str, ...]
    events: tuple[FaultEvent, ...]
    writes: int = 0
    #: The ontologies' directory; None for the committed ones.
    ontologies: str | None = None
    #: The spec's other settings that differ from their defaults (:func:`settings_defaults`).
    settings: Mapping[str, bool | int | float | str] = field(default_factory=dict)
    violates: str | None = None
    finding: str | None = None
    #: PYTHONHASHSEED when it was written (a run depends on the order of sets of names).
    hash_seed: str | None = None

    @classmethod
    def drawn(cls, spec: SimSpec, seed: int, kbs: KBCache | None = None) -> SimCase:
        """The case of seed ``seed``'s run of ``spec``: the tasks and the
        fault schedule the seed draws (or the spec gives), as the run will
        carry them out.  (A run's ``events`` are not the schedule: they also
        hold the faults its traps sprang.)"""
        if spec.scenario is not None:
            raise ValueError("a scenario's faults (SimSpec.scenario) cannot be written to a case")
        team = SimulatedTeam(spec, seed, kbs or KBCache())
        settings = {name: getattr(spec, name) for name, default in settings_defaults().items()
                    if getattr(spec, name) != default}
        return cls(
            seed=seed, robots=spec.robots, strategy=spec.strategy, faults=mix_text(spec.faults),
            tasks=tuple(team.tasks), events=tuple(team.schedule.events), writes=spec.writes,
            ontologies=None if spec.ontologies == DEFAULT_ONTOLOGIES else str(spec.ontologies),
            settings=settings, hash_seed=os.environ.get("PYTHONHASHSEED"),
        )

    def spec(self) -> SimSpec:
        """The spec that runs this case under :attr:`seed`."""
        spec = SimSpec(
            robots=self.robots, tasks=len(self.tasks), strategy=self.strategy, faults=FaultMix.parse(self.faults),
            ontologies=Path(self.ontologies) if self.ontologies else DEFAULT_ONTOLOGIES,
            task_list=self.tasks, schedule=self.events, writes=self.writes,
        )
        settings: dict[str, Any] = dict(self.settings)
        return dataclasses.replace(spec, **settings)

    @property
    def size(self) -> tuple[int, int, int]:
        """(fault events, tasks, robots)."""
        return len(self.events), len(self.tasks), self.robots

    def describe_size(self) -> str:
        events, tasks, robots = self.size
        return f"{events} event{'s' * (events != 1)}, {tasks} task{'s' * (tasks != 1)}, {robots} robots"

    # ------------------------------------------------------------- the file

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT, "version": VERSION, "seed": self.seed, "robots": self.robots,
            "strategy": self.strategy, "faults": self.faults, "writes": self.writes,
            **({"ontologies": self.ontologies} if self.ontologies else {}),
            **({"settings": dict(self.settings)} if self.settings else {}),
            "violates": self.violates, "finding": self.finding, "hash_seed": self.hash_seed,
            "tasks": list(self.tasks),
            "events": [_event_dict(e) for e in self.events],
        }

    def to_json(self) -> str:
        """The file's text: a key a line, a task or a fault event a line."""
        items = list(self.to_dict().items())
        lines = ["{"]
        for i, (key, value) in enumerate(items):
            if key in ("tasks", "events") and value:
                text = "[\n" + ",\n".join(f"  {json.dumps(v)}" for v in value) + "\n ]"
            else:
                text = json.dumps(value)
            lines.append(f" {json.dumps(key)}: {text}{',' if i < len(items) - 1 else ''}")
        return "\n".join([*lines, "}"]) + "\n"

    @classmethod
    def from_dict(cls, raw: object) -> SimCase:
        """Read a case back; :class:`ValueError` (one line) if it is malformed."""
        if not isinstance(raw, dict):
            raise ValueError("expected a JSON object")
        if raw.get("format") != FORMAT:
            raise ValueError(f"not a simulation case (its \"format\" should be {FORMAT!r})")
        if raw.get("version") != VERSION:
            raise ValueError(f"version {raw.get('version')!r} is not one this coapkb reads ({VERSION})")
        known = {"format", "version", "seed", "robots", "strategy", "faults", "writes", "ontologies", "settings",
                 "violates", "finding", "hash_seed", "tasks", "events"}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise ValueError(f"unknown key {unknown[0]!r}")
        seed = _int(raw, "seed")
        robots = _int(raw, "robots")
        if robots < 3 or robots % 3:
            raise ValueError(f"\"robots\" must be a multiple of 3, got {robots}")
        strategy = _str(raw, "strategy")
        if strategy not in ("compute-by-all", "compute-and-communicate"):
            raise ValueError(f"unknown strategy {strategy!r}")
        faults = _str(raw, "faults")
        try:
            FaultMix.parse(faults)
        except FaultSpecError as exc:
            raise ValueError(f"\"faults\": {exc}") from None
        writes = _int(raw, "writes", 0)
        if writes < 0:
            raise ValueError("\"writes\" must not be negative")
        tasks = raw.get("tasks")
        if not isinstance(tasks, list) or not tasks or not all(isinstance(t, str) and t for t in tasks):
            raise ValueError("\"tasks\" must be a non-empty list of object names")
        events_raw = raw.get("events")
        if not isinstance(events_raw, list):
            raise ValueError("\"events\" must be a list of fault events")
        events = tuple(_event(e, i, robots) for i, e in enumerate(events_raw, 1))
        settings = _settings(raw.get("settings", {}))
        ontologies = raw.get("ontologies")
        if ontologies is not None and not isinstance(ontologies, str):
            raise ValueError("\"ontologies\" must be a directory's path")
        return cls(
            seed=seed, robots=robots, strategy=strategy, faults=faults, tasks=tuple(tasks), events=events,
            writes=writes, ontologies=ontologies, settings=settings,
            violates=_optional_str(raw, "violates"), finding=_optional_str(raw, "finding"),
            hash_seed=_optional_str(raw, "hash_seed"),
        )

    def save(self, path: str | Path) -> None:
        """Write the case to ``path`` (:class:`CaseFileError` if it cannot be written)."""
        try:
            Path(path).write_text(self.to_json(), encoding="utf-8")
        except OSError as exc:
            raise CaseFileError(f"cannot write the case file {path}: {exc.strerror}") from None

    @classmethod
    def load(cls, path: str | Path) -> SimCase:
        """Read the case in ``path``; :class:`CaseFileError` says in one line
        why not (missing, unreadable, not JSON, or not a case)."""
        try:
            text = Path(path).read_text(encoding="utf-8")
        except FileNotFoundError:
            raise CaseFileError(f"no case file {path}") from None
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else "not UTF-8 text"
            raise CaseFileError(f"cannot read the case file {path}: {why}") from None
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CaseFileError(f"{path} is not JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
        try:
            return cls.from_dict(raw)
        except ValueError as exc:
            raise CaseFileError(f"{path} is not a valid case: {exc}") from None


def _event_dict(event: FaultEvent) -> dict[str, Any]:
    raw = dataclasses.asdict(event)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in raw.items()}


def _event(raw: object, index: int, robots: int) -> FaultEvent:
    where = f"event {index}"
    if not isinstance(raw, dict):
        raise ValueError(f"{where} must be an object")
    names = {f.name: f for f in fields(FaultEvent)}
    unknown = sorted(set(raw) - set(names))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}")
    values: dict[str, Any] = {}
    for name, value in raw.items():
        default = names[name].default
        if isinstance(default, tuple) or name == "targets":
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise ValueError(f"{where}: {name!r} must be a list of names")
            value = tuple(value)
        elif isinstance(default, float) or name == "at_s":
            if not _number(value):
                raise ValueError(f"{where}: {name!r} must be a number")
            value = float(value)
        values[name] = value
    for required in ("at_s", "action", "targets"):
        if required not in values:
            raise ValueError(f"{where}: {required!r} is missing")
    if values["action"] not in ACTIONS:
        raise ValueError(f"{where}: unknown action {values['action']!r} (one of {', '.join(ACTIONS)})")
    if not values["targets"]:
        raise ValueError(f"{where}: no targets")
    for name in (*values["targets"], *values.get("other", ())):
        match = _ROBOT.fullmatch(name)
        if name != "feeder" and (match is None or int(match[1]) > robots):
            raise ValueError(f"{where} names {name!r}, not the feeder nor one of Robot1..Robot{robots}")
    return FaultEvent(**values)


def _settings(raw: object) -> dict[str, bool | int | float | str]:
    if not isinstance(raw, dict):
        raise ValueError("\"settings\" must be an object")
    defaults = settings_defaults()
    settings: dict[str, bool | int | float | str] = {}
    for name, value in raw.items():
        if name not in defaults:
            raise ValueError(f"\"settings\": unknown setting {name!r} (one of {', '.join(sorted(defaults))})")
        default = defaults[name]
        if isinstance(default, bool) or isinstance(default, str):
            ok = type(value) is type(default)
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = _number(value)
            value = float(value) if ok else value
        if not ok:
            kind = {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}[type(default)]
            raise ValueError(f"\"settings\": {name!r} must be {kind}, got {value!r}")
        settings[name] = value
    return settings


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _int(raw: Mapping[str, object], key: str, default: int | None = None) -> int:
    value = raw.get(key, default)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"{key!r} must be a whole number" if key in raw else f"{key!r} is missing")
    return value


def _str(raw: Mapping[str, object], key: str) -> str:
    value = raw.get(key)
    if not isinstance(value, str):
        raise ValueError(f"{key!r} must be a string" if key in raw else f"{key!r} is missing")
    return value


def _optional_str(raw: Mapping[str, object], key: str) -> str | None:
    value = raw.get(key)
    if value is not None and not isinstance(value, str):
        raise ValueError(f"{key!r} must be a string")
    return value
