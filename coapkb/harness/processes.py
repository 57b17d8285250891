"""The team's OS processes: each started as ``python -m coapkb ...`` where
its :class:`~.placement.Placement` puts it and awaited until it says it is
ready, its output read so that it never blocks on a full pipe (and kept in
a log under ``coapkb bench --trace``); later killed, frozen, let go on,
started again with the same command line, and stopped at the end.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
from pathlib import Path

from .placement import Placement
from .team_spec import TeamError

log = logging.getLogger(__name__)


class TeamProcesses:
    """Every process of one team by name: the robots and the central server."""

    def __init__(self, placement: Placement, log_dir: Path | None = None) -> None:
        self.placement = placement
        #: Where each process's log goes (TeamSpec.log_dir), or None.
        self.log_dir = log_dir
        self.by_name: dict[str, asyncio.subprocess.Process] = {}
        self._stderr_tails: dict[str, list[str]] = {}
        self._argv: dict[str, list[str]] = {}
        #: Stopped robots let go on again: alive, though the team has them down.
        self.resumed: set[str] = set()

    async def spawn(self, name: str, argv: list[str], ready_prefix: str) -> str:
        """Start process ``name`` with ``argv`` (``coapkb``'s arguments) and
        return its first line once it begins with ``ready_prefix``."""
        self._argv[name] = argv
        self.placement.starting(name)
        log_file: Path | None = None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            log_file = self.log_dir / f"{name}.log"
            argv = ["-v", *argv]
        proc = await asyncio.create_subprocess_exec(
            *self.placement.command(name, [sys.executable, "-m", "coapkb", *argv]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.by_name[name] = proc
        assert proc.stdout is not None and proc.stderr is not None
        tail: list[str] = []
        self._stderr_tails[name] = tail
        asyncio.create_task(_drain(proc.stderr, tail, log_file), name=f"stderr-{name}")
        try:
            async with asyncio.timeout(60):
                line = (await proc.stdout.readline()).decode().strip()
        except TimeoutError:
            line = ""
        if not line.startswith(ready_prefix):
            await proc.wait() if proc.returncode is not None else None
            # The robot's own "coapkb: error: ..." line, without its prefix:
            # this one is said as "coapkb: ..." too.
            said = line or " ".join(t.removeprefix("coapkb: ").removeprefix("error: ") for t in tail[-3:])
            raise TeamError(f"{name} did not start: {said or 'no output'}")
        asyncio.create_task(_drain(proc.stdout, []), name=f"stdout-{name}")
        return line

    def pause(self, name: str, stop: bool = True) -> None:
        """Freeze process ``name`` (SIGSTOP: cut off, its state intact) or
        let it go on (SIGCONT); a resumed one is kept in :attr:`resumed`."""
        with contextlib.suppress(ProcessLookupError):
            self.by_name[name].send_signal(signal.SIGSTOP if stop else signal.SIGCONT)
        if not stop:
            self.resumed.add(name)

    async def kill(self, name: str) -> None:
        """SIGKILL process ``name`` and wait until it is gone."""
        proc = self.by_name[name]
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGKILL)
        await proc.wait()

    async def restart(self, name: str, ready_prefix: str) -> None:
        """Start process ``name`` again with the same command line, once it
        has said it is ready (its old process must be gone)."""
        await self.spawn(name, self._argv[name], ready_prefix)

    def dead(self, name: str) -> bool:
        """Whether process ``name`` has exited (its death may not be seen by the team yet)."""
        return self.by_name[name].returncode is not None

    def crashed(self) -> list[str]:
        """Every process that exited, with its exit code and last lines."""
        return [f"{n} (exit {p.returncode}): {' '.join(self._stderr_tails[n][-2:])}"
                for n, p in self.by_name.items() if p.returncode is not None]

    async def stop(self) -> None:
        """Let go of the ports still held for processes that never started,
        then SIGTERM every process (SIGKILL one that does not stop in 10 s)."""
        self.placement.close()
        for proc in self.by_name.values():
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
                    proc.send_signal(signal.SIGCONT)  # a stopped robot must run to take SIGTERM
        for name, proc in self.by_name.items():
            try:
                async with asyncio.timeout(10):
                    await proc.wait()
            except TimeoutError:
                log.warning("%s did not stop on SIGTERM; killing it", name)
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()


async def _drain(stream: asyncio.StreamReader, tail: list[str], log_file: Path | None = None, keep: int = 20) -> None:
    """Read a child's output so it never blocks on a full pipe; keep the last
    lines, and all of them in ``log_file`` (appended: a restart continues it)."""
    with contextlib.ExitStack() as closing:
        out = closing.enter_context(log_file.open("ab")) if log_file is not None else None
        while line := await stream.readline():
            if out is not None:
                out.write(line)
            tail.append(line.decode(errors="replace").rstrip())
            del tail[:-keep]
