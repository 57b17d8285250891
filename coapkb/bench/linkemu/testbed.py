"""The testbed: namespaces, bridge, shapers and loss rules for a set of hosts.

This module is its lifecycle (set up, change, tear down, even on SIGTERM)
and the processes run in its hosts; the parts are :mod:`.hosts` (names and
addresses), :mod:`.topology` (namespaces and wiring), :mod:`.link_control`
(shapers, loss rules, delay line) and :mod:`.counters`.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import os
import re
import secrets
import signal
import subprocess
import threading
from collections.abc import Iterable, Mapping, Sequence
from types import FrameType, TracebackType
from typing import Any

from .counters import read_counters
from .hosts import Host, check_host_names, links_per_host, plan_hosts
from .link_control import LinkControl, require_delay_tools
from .netns import DEFAULT_PREFIX, _delete_netns, _kill_netns_processes, _list_netns
from .spec import LinkCounters, LinkEmulationError, LinkSpec
from .topology import add_netns, wire_hosts

__all__ = ["Testbed"]


def _sigterm_to_exit(signum: int, frame: FrameType | None) -> None:
    """SIGTERM handler: unwind like an exception so ``finally``/``__exit__`` clean up."""
    raise SystemExit(128 + signum)


class Testbed:
    """Namespaces, bridge, shapers and loss rules for a set of hosts.

    Use as a context manager (``with`` or ``async with``); teardown always
    runs -- after exceptions, Ctrl-C, SIGTERM (turned into ``SystemExit``
    while the testbed lives, if nothing else handles SIGTERM) and at
    interpreter exit (``atexit``).  Only SIGKILL escapes; for that, names
    carry the owner's pid and :func:`cleanup_stale` removes them later.

    Example::

        ok, why = available()
        if not ok:
            sys.exit(f"no link emulation: {why}")
        with Testbed(["robot1", "central"], LinkSpec(rate_kbit=128, loss_pct=10)) as tb:
            server = tb.popen("central", [sys.executable, "server.py", tb["central"].address])
            before = tb.counters()
            tb.run("robot1", [sys.executable, "client.py", tb.address("central")], check=True)
            used = tb.counters()["robot1"] - before["robot1"]
            tb.set_link("robot1", LinkSpec(rate_kbit=35))   # next run, same testbed

    Setup and teardown run synchronously (about 20 ms per host); the async
    context manager runs them in-line too, since they are not hot paths and
    a teardown that cannot be interrupted half-way is the point.
    """

    __test__ = False  # not a pytest test class despite the name

    def __init__(
        self,
        hosts: Iterable[str],
        links: LinkSpec | Mapping[str, LinkSpec] | None = None,
        *,
        subnet: str = "10.77.0.0/24",
        prefix: str = DEFAULT_PREFIX,
        kill_grace_s: float = 2.0,
    ) -> None:
        names = list(hosts)
        check_host_names(names)
        if not re.match(r"^[a-z]{1,8}$", prefix):
            raise ValueError(f"prefix must be 1-8 lowercase letters (the pid follows it), got {prefix!r}")
        specs = links_per_host(names, links)

        self.run_id = f"{prefix}{os.getpid()}-{secrets.token_hex(2)}"
        self.bridge_netns = self.run_id
        self._kill_grace_s = kill_grace_s
        self._hosts: dict[str, Host] = plan_hosts(names, subnet, self.run_id)
        self._links = LinkControl(self.bridge_netns, self._hosts, specs)
        self._created: list[str] = []
        self._popen: list[subprocess.Popen[Any]] = []
        self._aproc: list[asyncio.subprocess.Process] = []
        self._state = "new"  # new -> up -> closed
        self._prev_sigterm: Any = None
        self._installed_sigterm = False
        self._owner_pid = os.getpid()

    # ---- lookup -----------------------------------------------------------

    @property
    def hosts(self) -> Mapping[str, Host]:
        """The hosts by name, in the order given."""
        return dict(self._hosts)

    def __getitem__(self, name: str) -> Host:
        return self.host(name)

    def host(self, name: str) -> Host:
        try:
            return self._hosts[name]
        except KeyError:
            raise KeyError(f"no host {name!r} in this testbed (hosts: {', '.join(self._hosts)})") from None

    def address(self, name: str) -> str:
        """The host's IPv4 address on the emulated link."""
        return self.host(name).address

    def link(self, name: str) -> LinkSpec:
        """The link spec currently applied to ``name``."""
        self.host(name)
        return self._links.spec(name)

    @property
    def namespaces(self) -> list[str]:
        """Every namespace this testbed owns (bridge first)."""
        return [self.bridge_netns, *(h.netns for h in self._hosts.values())]

    def __repr__(self) -> str:
        return f"Testbed({self.run_id!r}, hosts={list(self._hosts)}, state={self._state})"

    # ---- lifecycle --------------------------------------------------------

    def __enter__(self) -> Testbed:
        self.setup()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    async def __aenter__(self) -> Testbed:
        self.setup()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    def setup(self) -> None:
        """Build everything; on any failure remove what was built and re-raise."""
        if self._state != "new":
            raise LinkEmulationError(f"testbed {self.run_id} was already set up")
        if os.geteuid() != 0:
            raise LinkEmulationError("link emulation needs root; see coapkb.bench.linkemu.available()")
        self._state = "up"
        atexit.register(self.close)
        self._install_sigterm()
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def _install_sigterm(self) -> None:
        # Only the main thread may set handlers; only take over SIGTERM when
        # nobody else handles it (an asyncio app's loop.add_signal_handler or
        # a benchmark's own handler stays in charge).
        if threading.current_thread() is not threading.main_thread():
            return
        current = signal.getsignal(signal.SIGTERM)
        if current is signal.SIG_DFL:
            self._prev_sigterm = current
            signal.signal(signal.SIGTERM, _sigterm_to_exit)
            self._installed_sigterm = True

    def _restore_sigterm(self) -> None:
        if not self._installed_sigterm:
            return
        self._installed_sigterm = False
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGTERM) in (_sigterm_to_exit, signal.SIG_IGN):
                signal.signal(signal.SIGTERM, self._prev_sigterm)

    def _build(self) -> None:
        require_delay_tools(self._links.spec(name) for name in self._hosts)
        add_netns(self.bridge_netns, self._created)
        hosts = list(self._hosts.values())
        for h in hosts:
            add_netns(h.netns, self._created)
        wire_hosts(self.bridge_netns, hosts, {h.index: self._links.spec(h.name) for h in hosts})
        self._links.install()

    def set_link(self, name: str, spec: LinkSpec) -> None:
        """Change ``name``'s link in place (between runs; counters keep counting).

        The loss rule is swapped atomically; the shapers are replaced, so
        packets queued in them at that moment are discarded.
        """
        if not isinstance(spec, LinkSpec):
            raise ValueError(f"spec must be a LinkSpec, got {spec!r}")
        h = self.host(name)
        self._require_up()
        self._links.set_link(h, spec)

    def _require_up(self) -> None:
        if self._state != "up":
            raise LinkEmulationError(f"testbed {self.run_id} is {self._state}, not set up")

    def close(self) -> None:
        """Kill the hosts' processes and delete every namespace. Idempotent.

        Raises :class:`LinkEmulationError` only if something could not be
        removed (after trying to remove everything else).
        """
        if self._state == "closed" or os.getpid() != self._owner_pid:
            return  # a forked child (inheriting atexit hooks) must not tear down its parent's testbed
        self._state = "closed"
        if self._installed_sigterm and threading.current_thread() is threading.main_thread():
            # A second SIGTERM must not cut the teardown short.
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            atexit.unregister(self.close)
            for p in self._popen:
                if p.poll() is None:
                    try:
                        p.terminate()
                    except ProcessLookupError:
                        pass
            for ap in self._aproc:
                if ap.returncode is None:
                    try:
                        ap.terminate()
                    except ProcessLookupError:
                        pass
            self._links.close()
            mine = self._owned_namespaces()
            survivors = _kill_netns_processes(mine, self._kill_grace_s)
            for p in self._popen:
                try:
                    p.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    p.kill()
            problems = [f"processes {survivors} survived SIGKILL"] if survivors else []
            # Hosts first, the bridge namespace last.
            for ns in sorted(mine, key=lambda n: n == self.bridge_netns):
                try:
                    _delete_netns(ns)
                except LinkEmulationError as e:
                    problems.append(str(e))
            if problems:
                raise LinkEmulationError(f"teardown of {self.run_id} incomplete: {'; '.join(problems)}")
        finally:
            self._popen.clear()
            self._restore_sigterm()

    async def aclose(self) -> None:
        """Async teardown: lets the event loop reap :meth:`spawn`'ed processes first."""
        if self._state == "closed":
            return
        live = [p for p in self._aproc if p.returncode is None]
        for p in live:
            try:
                p.terminate()
            except ProcessLookupError:
                pass
        if live:
            await asyncio.wait(
                [asyncio.ensure_future(p.wait()) for p in live], timeout=self._kill_grace_s
            )
        for p in live:
            if p.returncode is None:
                try:
                    p.kill()
                except ProcessLookupError:
                    pass
        self.close()
        for p in live:
            if p.returncode is None:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(2.0):
                        await p.wait()
        self._aproc.clear()

    def _owned_namespaces(self) -> list[str]:
        """What we created plus anything carrying our run id (partial setups)."""
        names = list(dict.fromkeys(self._created))
        for ns in _list_netns():
            if (ns == self.run_id or ns.startswith(self.run_id + "-")) and ns not in names:
                names.append(ns)
        return names

    # ---- processes --------------------------------------------------------

    def exec_args(self, name: str, argv: Sequence[str]) -> list[str]:
        """``argv`` prefixed so that it runs inside host ``name``'s namespace."""
        if isinstance(argv, str):
            raise TypeError("argv must be a sequence of arguments, not a string")
        return ["ip", "netns", "exec", self.host(name).netns, *argv]

    def popen(self, name: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` in host ``name``; it is killed at teardown if still running.

        ``ip netns exec`` execs the command, so the returned process *is* the
        command (same pid), not a wrapper.
        """
        self._require_up()
        p = subprocess.Popen(self.exec_args(name, argv), **kwargs)
        self._popen.append(p)
        return p

    def run(self, name: str, argv: Sequence[str], **kwargs: Any) -> subprocess.CompletedProcess[Any]:
        """``subprocess.run`` of ``argv`` inside host ``name``."""
        self._require_up()
        return subprocess.run(self.exec_args(name, argv), **kwargs)

    async def spawn(self, name: str, argv: Sequence[str], **kwargs: Any) -> asyncio.subprocess.Process:
        """Async :meth:`popen` (``asyncio.create_subprocess_exec``); killed at teardown."""
        self._require_up()
        p = await asyncio.create_subprocess_exec(*self.exec_args(name, argv), **kwargs)
        self._aproc.append(p)
        return p

    # ---- counters ---------------------------------------------------------

    def counters(self) -> dict[str, LinkCounters]:
        """Per-host link counters since setup (subtract two readings for a run)."""
        self._require_up()
        return read_counters(self.bridge_netns, self._hosts.values(), self._links.delay_stats)

    async def acounters(self) -> dict[str, LinkCounters]:
        """:meth:`counters` off the event loop (it runs a few short commands per host)."""
        return await asyncio.to_thread(self.counters)
