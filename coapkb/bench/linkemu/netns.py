"""Network-namespace plumbing: setup commands, teardown, stale cleanup, the
capability probe, and moving a thread into a namespace (``enter_netns``)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator, Sequence

from .spec import LinkEmulationError

__all__ = ["DEFAULT_PREFIX", "available", "cleanup_stale", "enter_netns"]

#: Prefix of every namespace this package creates: ``<prefix><pid>-<tok>[-host]``.
DEFAULT_PREFIX = "ckb"


# --------------------------------------------------------------------------
# Small command helpers
# --------------------------------------------------------------------------


def _run(
    argv: Sequence[str],
    *,
    input: str | None = None,
    check: bool = True,
    timeout: float = 30.0,
) -> subprocess.CompletedProcess[str]:
    """Run one setup command; failures become :class:`LinkEmulationError` with stderr."""
    try:
        cp = subprocess.run(
            list(argv), input=input, capture_output=True, text=True, timeout=timeout, check=False
        )
    except FileNotFoundError as e:
        raise LinkEmulationError(f"{argv[0]!r} not found ({e}); install iproute2 and nftables") from e
    except subprocess.TimeoutExpired as e:
        raise LinkEmulationError(f"`{shlex.join(argv)}` timed out after {timeout} s") from e
    if check and cp.returncode != 0:
        detail = (cp.stderr or cp.stdout).strip()
        raise LinkEmulationError(f"`{shlex.join(argv)}` failed (exit {cp.returncode}): {detail}")
    return cp


def _list_netns() -> list[str]:
    """Names of all named network namespaces (``ip netns list``)."""
    cp = _run(["ip", "netns", "list"], check=False)
    if cp.returncode != 0:
        return []
    return [line.split()[0] for line in cp.stdout.splitlines() if line.strip()]


def _netns_pids(ns: str) -> list[int]:
    """Processes living in namespace ``ns`` (zombies are not listed)."""
    cp = _run(["ip", "netns", "pids", ns], check=False)
    if cp.returncode != 0:
        return []
    me = os.getpid()
    return [int(tok) for tok in cp.stdout.split() if tok.isdigit() and int(tok) != me]


def _kill_netns_processes(namespaces: Iterable[str], grace_s: float) -> list[int]:
    """SIGTERM everything in ``namespaces``, SIGKILL what survives ``grace_s``.

    Returns the pids still alive at the end (normally none).
    """
    namespaces = list(namespaces)

    def alive() -> list[int]:
        return [pid for ns in namespaces for pid in _netns_pids(ns)]

    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        pids = alive()
        if not pids:
            return []
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            time.sleep(0.05)
            if not alive():
                return []
    return alive()


def _delete_netns(ns: str) -> None:
    cp = _run(["ip", "netns", "delete", ns], check=False)
    if cp.returncode != 0 and ns in _list_netns():
        raise LinkEmulationError(f"could not delete namespace {ns}: {cp.stderr.strip()}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:
        return False
    return True


def _stale_re(prefix: str) -> re.Pattern[str]:
    return re.compile(rf"^{re.escape(prefix)}(\d+)-[0-9a-f]{{4}}(?:-.+)?$")


def cleanup_stale(prefix: str = DEFAULT_PREFIX, *, grace_s: float = 1.0) -> list[str]:
    """Remove namespaces left behind by crashed runs (e.g. after SIGKILL).

    A namespace is stale when its name has the form ``<prefix><pid>-<tok>...``
    and process ``pid`` no longer exists.  Namespaces of live runs are kept.
    Processes still running inside a stale namespace are killed first.
    (A pid reused by an unrelated process keeps its namespaces until that
    process exits too; that errs on the safe side.)  Returns the names removed.
    """
    if os.geteuid() != 0:
        return []
    pattern = _stale_re(prefix)
    stale = [
        ns
        for ns in _list_netns()
        if (m := pattern.match(ns)) is not None and not _pid_alive(int(m.group(1)))
    ]
    if not stale:
        return []
    _kill_netns_processes(stale, grace_s)
    removed = []
    for ns in stale:
        try:
            _delete_netns(ns)
        except LinkEmulationError:
            continue
        removed.append(ns)
    return removed


def available() -> tuple[bool, str]:
    """Whether namespace link emulation can run here, with the reason if not.

    Checks root, the tools (``ip``, ``tc``, ``bridge``, ``nft``) and then
    actually builds a throw-away namespace with a veth pair, a tbf shaper and
    an nftables bridge table using ``numgen`` -- the kernel features the
    testbed needs -- and removes it again.  Takes ~50 ms.
    """
    if not sys.platform.startswith("linux"):
        return False, f"link emulation needs Linux network namespaces (this is {sys.platform})"
    if os.geteuid() != 0:
        return False, "link emulation needs root (network namespaces, tc and nftables need CAP_NET_ADMIN)"
    missing = [tool for tool in ("ip", "tc", "bridge", "nft") if shutil.which(tool) is None]
    if missing:
        return False, (
            f"missing {', '.join(missing)}: install the Debian packages iproute2 (ip, tc, bridge) "
            "and nftables (nft)"
        )
    ns = f"{DEFAULT_PREFIX}{os.getpid()}-{secrets.token_hex(2)}-probe"
    steps: list[tuple[str, list[str], str | None]] = [
        ("create a network namespace", ["ip", "netns", "add", ns], None),
        ("create a bridge", ["ip", "-n", ns, "link", "add", "br0", "type", "bridge"], None),
        (
            "create a veth pair",
            ["ip", "-n", ns, "link", "add", "pa", "type", "veth", "peer", "name", "pb"],
            None,
        ),
        (
            "add a tbf shaper (CONFIG_NET_SCH_TBF)",
            ["tc", "-n", ns, "qdisc", "add", "dev", "pa", "root", "tbf", "rate", "35kbit",
             "burst", "2048", "limit", "100000"],
            None,
        ),
        (
            "load an nftables bridge table with numgen (CONFIG_NF_TABLES_BRIDGE, CONFIG_NFT_NUMGEN)",
            ["ip", "netns", "exec", ns, "nft", "-f", "-"],
            "table bridge ckbprobe {\n chain forward {\n  type filter hook forward priority 0; policy accept;\n"
            "  numgen random mod 10000 < 1 counter drop\n }\n}\n",
        ),
    ]
    try:
        for what, argv, stdin in steps:
            try:
                _run(argv, input=stdin, timeout=10)
            except LinkEmulationError as e:
                return False, f"cannot {what}: {e}"
        return True, "network namespaces, veth, bridge, tbf and nftables bridge loss are available"
    finally:
        if ns in _list_netns():
            _run(["ip", "netns", "delete", ns], check=False)


# --------------------------------------------------------------------------
# Running code of *this* process inside a host's namespace
# --------------------------------------------------------------------------

#: ``CLONE_NEWNET`` from <sched.h>: the namespace type argument of setns(2).
CLONE_NEWNET = 0x40000000


def _setns(fd: int, what: str) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise LinkEmulationError(f"setns into {what} failed: {os.strerror(err)}")


@contextlib.contextmanager
def enter_netns(name: str) -> Iterator[None]:
    """Move the **calling thread** into network namespace ``name`` (as listed
    by ``ip netns``, e.g. ``testbed["feeder"].netns``) and back on exit.

    Why: a benchmark's task feeder runs in the benchmark process itself
    (:meth:`coapkb.harness.team.Team.run`), yet its traffic must cross an emulated
    link like every other host's.  A socket belongs to the namespace of the
    thread that *creates* it, for its whole life, so code that opens its
    sockets inside this block talks from ``name`` even while an event loop
    interleaves it with other work; sockets created before stay where they
    were.  Threads started inside the block (a ZeroMQ context's I/O threads,
    executor threads) inherit ``name`` and keep it after the block ends.

    The original namespace is the calling thread's own
    (``/proc/thread-self/ns/net``, not ``/proc/self``, which is the main
    thread's), kept open as a file descriptor so the way back works even if
    ``name`` is deleted meanwhile.  Needs ``CAP_SYS_ADMIN``; failures raise
    :class:`LinkEmulationError`.
    """
    if "/" in name or not name:
        raise ValueError(f"not a namespace name: {name!r}")
    try:
        original = os.open("/proc/thread-self/ns/net", os.O_RDONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise LinkEmulationError(f"cannot open this thread's network namespace: {exc.strerror}") from None
    try:
        try:
            target = os.open(f"/run/netns/{name}", os.O_RDONLY | os.O_CLOEXEC)
        except OSError as exc:
            raise LinkEmulationError(f"no network namespace {name!r}: {exc.strerror}") from None
        try:
            _setns(target, f"namespace {name!r}")
        finally:
            os.close(target)
        try:
            yield
        finally:
            _setns(original, "the original namespace")
    finally:
        os.close(original)
