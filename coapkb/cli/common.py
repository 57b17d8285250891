"""What several ``coapkb`` subcommands share: the user-error type, the
stop signals, endpoint parsing and the team credentials options."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn, TypeVar

from ..errors import CoapkbError
from ..transport import ClientSecurity, Endpoint, ServerSecurity, registry

if TYPE_CHECKING:
    from ..kb.client import KBClient

T = TypeVar("T")


class UserError(CoapkbError):
    """A mistake the user can fix; printed as one line."""


class Parser(argparse.ArgumentParser):
    """A usage mistake in one line, with where to read the usage (not the
    usage block: it hides the one line that matters)."""

    #: Where the usage is read, if not ``PROG --help``: the top-level parser
    #: reports a subcommand's unknown options, whose usage is the subcommand's.
    help_hint: str | None = None

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.help_hint or self.prog + ' --help'})\n")


def require_folder_of(path: Path, option: str) -> None:
    """``option``'s output file ``path`` goes into a folder that exists: said
    before any work, not after it."""
    if not path.parent.is_dir():
        raise UserError(f"{option}: no folder {path.parent}")


@contextlib.contextmanager
def stop_signals() -> Iterator[asyncio.Event]:
    """An event SIGINT and SIGTERM set, from the moment this is entered, so a
    server shuts down cleanly either way.  A command prints its ready line
    inside it: a supervisor (or a test) that signals on that line, before
    the handlers were in place, stopped the process with a KeyboardInterrupt
    and status 130 (seen on a busy machine, the line read and acted on
    before the next statement ran)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        yield stop
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


async def until_signalled(ready: str) -> None:
    """Print the command's ready line, then wait for SIGINT or SIGTERM, the
    handlers in place before the line (:func:`stop_signals`)."""
    with stop_signals() as stopped:
        print(ready, flush=True)
        await stopped.wait()


def parse_endpoint(hostport: str, scheme: str) -> Endpoint:
    """``[SCHEME://]HOST[:PORT]``; without a port, the scheme's own (CoAP's
    5683, RFC 7252 section 6.1)."""
    try:
        return registry.parse_endpoint(hostport, default_scheme=scheme)
    except ValueError as exc:
        error = UserError(str(exc))
    with_port = _with_default_port(hostport, scheme)
    if with_port is None:
        raise error
    try:
        return registry.parse_endpoint(with_port, default_scheme=scheme)
    except ValueError:
        raise error from None


def _with_default_port(text: str, scheme: str) -> str | None:
    from ..transport.registry import transport_for

    given, sep, rest = text.partition("://")
    if not sep:
        given, rest = scheme, text
    if not rest or ":" in rest.rpartition("]")[2]:
        return None  # a port is there (bad or not): the first error stands
    try:
        port = transport_for(given).default_port
    except (KeyError, ValueError):
        return None
    return f"{given}://{rest}:{port}"


def add_robot_client(p: argparse.ArgumentParser, *, timeout_s: float) -> None:
    """What a command asking one robot takes: ``--timeout``, the
    credentials (as the operator) and ``--peer``."""
    p.add_argument("--timeout", type=float, default=timeout_s, metavar="SECONDS", help="give up after this long")
    add_credentials(p, "operator")
    p.add_argument("--peer", metavar="NAME", help="the team member serving at URI (needed over zmq; checked over coap)")


def add_credentials(p: argparse.ArgumentParser, identity: str) -> None:
    p.add_argument("--credentials", metavar="DIR",
                   help="team key directory (coapkb keys): OSCORE keyed by EDHOC with the team's members")
    p.add_argument("--identity", default=identity, metavar="NAME",
                   help=f"whose key in --credentials to use (default {identity})")


def client_security(args: argparse.Namespace, peer: Endpoint) -> ClientSecurity | None:
    if getattr(args, "credentials", None) is None:
        return None
    from ..security import load_identity, mechanism_for

    mechanism = mechanism_for(peer.scheme)
    if mechanism.needs_server_name and not args.peer:
        raise UserError(f"--credentials over {peer.scheme}: name the member serving there with --peer "
                        f"({mechanism.title} needs its key)")
    # Otherwise the handshake finds who serves there; --peer also insists on who it is.
    return mechanism.client(load_identity(args.credentials, args.identity),
                            {peer.hostport: args.peer} if args.peer else None)


def server_security(args: argparse.Namespace) -> ServerSecurity | None:
    if args.credentials is None:
        return None
    from ..security import load_identity, server_security

    # A KB server takes queries from every member; tasks and decisions are robots' business.
    return server_security(args.transport, load_identity(args.credentials, args.identity))


async def ask_robot(args: argparse.Namespace, peer: Endpoint, call: Callable[[KBClient], Awaitable[T]]) -> T | None:
    """``call`` with a :class:`~coapkb.kb.client.KBClient` to ``peer`` (the
    command's credentials and ``--timeout``); a refusal or an unreachable
    robot is printed as one line and gives None."""
    from ..kb.client import KBClient, QueryFailed
    from ..transport import TransportError, open_client

    transport = await open_client(peer.scheme, security=client_security(args, peer))
    try:
        return await call(KBClient(transport, timeout=args.timeout))
    except QueryFailed as exc:
        print(f"coapkb: {peer} answered {exc}", file=sys.stderr)
    except TransportError as exc:
        print(f"coapkb: {exc}", file=sys.stderr)
    finally:
        await transport.aclose()
    return None
