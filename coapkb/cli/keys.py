"""``coapkb keys``: a team's key material."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .common import Parser, UserError


def add_keys(sub: argparse._SubParsersAction[Parser]) -> None:
    p = sub.add_parser("keys", help="make a team's key material: EDHOC credentials, CurveZMQ keys, TLS certificates, trust list")
    p.add_argument("--team-dir", required=True, metavar="DIR", help="a new directory (never overwritten)")
    p.add_argument("--robots", type=int, default=3, help="Robot1..RobotN")
    p.add_argument("--member", action="append", default=[], metavar="NAME:ROLE",
                   help="another member (role robot, feeder, server or client); repeatable")
    p.add_argument("--aiocoap-client", nargs=3, metavar=("IDENTITY", "PEER", "URI"),
                   help="instead: print an aiocoap-client --credentials file (.diag) for IDENTITY to talk to "
                        "member PEER at URI, from the existing --team-dir")
    p.set_defaults(run=_keys)


def unignored_in_work_tree(directory: Path) -> Path | None:
    """The git work tree holding ``directory`` if git would track it (not
    ignored), else None (no git, no work tree, or ignored)."""
    import shutil
    import subprocess

    git = shutil.which("git")
    if git is None:
        return None
    directory = directory.resolve()
    try:
        top = subprocess.run([git, "-C", str(directory), "rev-parse", "--show-toplevel"],
                             capture_output=True, text=True, timeout=10)
        if top.returncode != 0:
            return None
        ignored = subprocess.run([git, "-C", str(directory), "check-ignore", "-q", str(directory / "team.json")],
                                 capture_output=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return None if ignored.returncode == 0 else Path(top.stdout.strip())


async def _keys(args: argparse.Namespace) -> int:
    from ..security import generate_team
    from ..security.keys import ROLES, aiocoap_client_credentials, default_members

    if args.aiocoap_client:
        sys.stdout.write(aiocoap_client_credentials(args.team_dir, *args.aiocoap_client))
        return 0
    if args.robots < 0:
        raise UserError("--robots must not be negative")
    members = default_members(args.robots)
    for text in args.member:
        name, sep, role = text.partition(":")
        if not sep or role not in ROLES:
            raise UserError(f"--member {text!r}: expected NAME:ROLE with ROLE one of {', '.join(ROLES)}")
        members.append((name, role))
    trust = generate_team(args.team_dir, members)
    exposed = unignored_in_work_tree(Path(args.team_dir))
    if exposed is not None:
        print(f"coapkb: warning: {args.team_dir} holds private keys inside the git work tree {exposed}, and git "
              f"does not ignore it: one `git add -A` would commit them. Keep keys outside the work tree, or add "
              f"{args.team_dir.rstrip('/')}/ to .gitignore", file=sys.stderr)
    # Names and roles only: the keys stay in their 0600 files.
    robots = sum(1 for m in trust.members if m.role == "robot")
    others = len(trust.members) - robots
    print(f"{robots} robot{'' if robots == 1 else 's'} and {others} other member{'' if others == 1 else 's'} "
          f"in {args.team_dir}: " + ", ".join(f"{m.name} ({m.role})" for m in trust.members))
    print(f"give each member its {Path(args.team_dir) / 'NAME.key'}, NAME.curve, NAME.tls.key, NAME.tls.pem, team.json and team-ca.pem; "
          "a robot's TOML names the directory: [security] credentials = \"DIR\"")
    return 0
