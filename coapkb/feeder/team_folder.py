"""A team of robots each started by hand (``coapkb agent --config
DIR/RobotN.toml``), as the feeder learns it: from the same TOML files.

Every ``*.toml`` in the folder is one robot's configuration.  Their
``[team]`` tables are the clusters (a robot's table lists its cluster, this
robot included) and their ``bind`` the endpoints the feeder posts to; their
``[security]`` sections name the team's key directory, where the feeder
takes its own key (member ``feeder``, as ``coapkb keys`` makes it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..agent.task_assigner import robot_sort_key
from ..config import RobotConfig, load_config
from .channel import FeederSettings
from .roster import Roster
from .security import feeder_security
from .tasks import FeederError


@dataclass(frozen=True)
class TeamFolder:
    folder: Path
    #: Robot id -> its TOML file.
    files: dict[str, Path]
    #: Robot id -> its configuration, as read from that file.
    configs: dict[str, RobotConfig]
    roster: Roster
    settings: FeederSettings
    #: The team's key directory (``coapkb keys``), or None for an insecure team.
    credentials: Path | None

    def security(self) -> Any:
        """The feeder's client side for these robots (None for an insecure team)."""
        expected = {e.hostport: r for r, e in self.roster.endpoints.items()}
        return feeder_security(self.settings.transport, self.credentials, expected)

    def start_command(self, robot_id: str) -> str:
        return f"coapkb agent --config {self.files[robot_id]}"


def read_team_folder(folder: str | Path, task_timeout_s: float = 120.0) -> TeamFolder:
    """The team whose robots' TOML files are in ``folder``; one
    :class:`FeederError` (or ConfigError, naming the file) per mistake."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FeederError(f"no such team folder {folder}")
    paths = sorted(folder.glob("*.toml"))
    if not paths:
        raise FeederError(f"no robot configuration (*.toml) in {folder}")
    configs: dict[str, RobotConfig] = {}
    files: dict[str, Path] = {}
    for path in paths:
        config = load_config(path)  # a ConfigError names the file and the field
        if config.robot_id in configs:
            raise FeederError(f"{path} and {files[config.robot_id]} are both {config.robot_id}")
        if config.discovery.method != "static":
            raise FeederError(f"{path}: coapkb feed reads the clusters from the [team] tables "
                              f"(discovery method static), not from a Resource Directory")
        configs[config.robot_id] = config
        files[config.robot_id] = path
    ids = sorted(configs, key=robot_sort_key)
    first = configs[ids[0]]
    clusters: list[list[str]] = []
    for robot_id in ids:
        config = configs[robot_id]
        where = files[robot_id]
        if config.transport != first.transport:
            raise FeederError(f"{where}: {config.transport} robot, but {files[first.robot_id]} uses {first.transport}")
        for mate_id, mate in config.team.items():
            if mate_id not in configs:
                raise FeederError(f"{where} lists {mate_id} in its team, but {folder} has no TOML file for it")
            if mate.endpoint != configs[mate_id].bind:
                raise FeederError(f"{where} expects {mate_id} at {mate.endpoint}, "
                                  f"but {files[mate_id]} binds {configs[mate_id].bind}")
        cluster = sorted(config.team, key=robot_sort_key)
        if cluster not in clusters:
            overlapping = [c for c in clusters if set(c) & set(cluster)]
            if overlapping:
                raise FeederError(f"{where}: its team {', '.join(cluster)} differs from its teammates' "
                                  f"({', '.join(overlapping[0])}); every robot of a cluster lists the same team")
            clusters.append(cluster)
    secured = {r: c.security.credentials.resolve() for r, c in configs.items() if c.security is not None}
    if secured and len(secured) != len(configs):
        plain = next(r for r in ids if r not in secured)
        raise FeederError(f"{files[plain]} has no [security] section, but its teammates do")
    if len(set(secured.values())) > 1:
        raise FeederError(f"the robots name different key directories: {', '.join(sorted(map(str, set(secured.values()))))}")
    settings = FeederSettings(
        transport=first.transport,
        task_timeout_s=task_timeout_s,
        query_timeout_s=max(c.query_timeout_s for c in configs.values()),
        lease_s=max(c.lease_s for c in configs.values()),
        link_kbps=first.link_kbps,
    )
    roster = Roster({r: configs[r].bind for r in ids}, clusters)
    credentials = next(iter(secured.values())) if secured else None
    return TeamFolder(folder, files, configs, roster, settings, credentials)
