"""One run per working directory: a lock file naming the run that holds it.

Snakemake's own directory lock cannot tell a run killed with ``kill -9`` from a live one
(the default profile turns it off with ``nolock``); this lock can. The file
``.snakemake/depthgt-run.lock`` in the working directory holds the owner's PID, host,
process start time and command line. A second run is refused while the owner lives,
with a message naming it; a lock whose owner is gone (same host, PID not running or
running another process) is stale and is taken over, so a killed run resumes with the
same command, without ``--unlock``.

The workflow takes the lock in its ``onstart`` handler and releases it in ``onsuccess``
and ``onerror``: Snakemake calls these only in the main process of a real run (not for
``--dry-run``, ``--list`` or ``--summary``, and not in the jobs it spawns, which run
with ``--no-hooks``). The ``depthgt`` command checks it before starting Snakemake.

Standard library only (the Snakefile imports it while it is parsed).
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from depthgt.errors import DepthGTError

__all__ = ["LOCK_NAME", "RunLockError", "Holder", "lock_path", "holder", "check", "acquire", "release"]

LOCK_NAME = ".snakemake/depthgt-run.lock"


class RunLockError(DepthGTError):
    """Another live run holds the working directory."""


@dataclass(frozen=True)
class Holder:
    """The run named in a lock file."""

    pid: int
    host: str
    started: str  # ISO 8601, UTC
    proc_start: str | None  # the kernel's start time of the PID (Linux), tells a reused PID
    command: str

    def describe(self) -> str:
        return f"PID {self.pid} on {self.host}, started {self.started}: {self.command}"


def lock_path(workdir: str | Path = ".") -> Path:
    return Path(workdir) / LOCK_NAME


def _proc_start(pid: int) -> str | None:
    """Field 22 of /proc/PID/stat (start time in clock ticks since boot), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _me() -> Holder:
    return Holder(
        pid=os.getpid(),
        host=socket.gethostname(),
        started=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        proc_start=_proc_start(os.getpid()),
        command=" ".join(sys.argv)[:500],
    )


def holder(workdir: str | Path = ".") -> Holder | None:
    """The run named in the working directory's lock file, None when there is none.

    Raises:
        RunLockError: the file exists but cannot be read as a lock (named in the message).
    """
    path = lock_path(workdir)
    try:
        doc = json.loads(path.read_text())
        return Holder(**doc)
    except FileNotFoundError:
        return None
    except (OSError, ValueError, TypeError) as err:
        raise RunLockError(f"{path}: not a depthgt run lock ({err}); remove it if no run is going on") from err


def _alive(h: Holder) -> bool:
    """Whether the lock's owner still runs (True when that cannot be known: another host)."""
    if h.host != socket.gethostname():
        return True
    try:
        os.kill(h.pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's live process
    now = _proc_start(h.pid)
    return not (h.proc_start is not None and now is not None and now != h.proc_start)  # a reused PID


def _refuse(path: Path, h: Holder) -> RunLockError:
    remote = " (on another host: remove the file if that run is gone)" if h.host != socket.gethostname() else ""
    return RunLockError(
        f"another run is using this working directory: {h.describe()}{remote}. "
        f"Wait for it to finish or stop it; the lock is {path}"
    )


def check(workdir: str | Path = ".") -> None:
    """Raise :class:`RunLockError` when a live run other than this process holds ``workdir``."""
    h = holder(workdir)
    if h is not None and h.pid != os.getpid() and _alive(h):
        raise _refuse(lock_path(workdir), h)


def acquire(workdir: str | Path = ".") -> Holder:
    """Take the lock of ``workdir`` for this process; a stale lock is taken over.

    Two runs that start at once decide under an exclusive ``flock`` of a guard file
    beside the lock, so exactly one of them takes it.

    Raises:
        RunLockError: a live run holds it (the message names its PID, host, start and command).
    """
    path = lock_path(workdir)
    path.parent.mkdir(parents=True, exist_ok=True)
    me = _me()
    with open(path.with_name(path.name + ".guard"), "a") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        h = holder(workdir)
        if h is not None and (h.pid, h.host) == (me.pid, me.host):
            return h
        if h is not None and _alive(h):
            raise _refuse(path, h)
        tmp = path.with_name(f"{path.name}.{me.pid}.tmp")
        tmp.write_text(json.dumps(me.__dict__))
        os.replace(tmp, path)  # a stale lock is replaced
    return me


def release(workdir: str | Path = ".") -> None:
    """Remove the lock of ``workdir`` when this process holds it (another's is left alone)."""
    path = lock_path(workdir)
    try:
        h = holder(workdir)
    except RunLockError:
        return
    if h is not None and h.pid == os.getpid() and h.host == socket.gethostname():
        path.unlink(missing_ok=True)
