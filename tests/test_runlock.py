"""depthgt.runlock: one live run per working directory; a dead owner's lock is stale."""

from __future__ import annotations

import json
import os
import socket
import subprocess

import pytest

from depthgt import runlock


def _lock_for(workdir, pid: int, host: str | None = None) -> None:
    path = runlock.lock_path(workdir)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps(
            {
                "pid": pid,
                "host": host or socket.gethostname(),
                "started": "2026-01-01T00:00:00Z",
                "proc_start": runlock._proc_start(pid),
                "command": "snakemake dataset",
            }
        )
    )


def test_live_owner_refuses_dead_owner_is_taken_over(tmp_path):
    other = subprocess.Popen(["sleep", "60"])
    try:
        _lock_for(tmp_path, other.pid)
        with pytest.raises(
            runlock.RunLockError, match=rf"PID {other.pid} on .*started 2026-01-01T00:00:00Z: snakemake"
        ):
            runlock.acquire(tmp_path)
        with pytest.raises(runlock.RunLockError, match="another run"):
            runlock.check(tmp_path)
        runlock.release(tmp_path)  # not ours: left alone
        assert runlock.holder(tmp_path).pid == other.pid
    finally:
        other.kill()
        other.wait()
    runlock.check(tmp_path)  # the owner is gone: stale, no error
    me = runlock.acquire(tmp_path)
    assert me.pid == os.getpid() and runlock.holder(tmp_path) == me
    assert runlock.acquire(tmp_path) == me  # taking it again is a no-op
    runlock.release(tmp_path)
    assert runlock.holder(tmp_path) is None


def test_reused_pid_and_other_host(tmp_path):
    # this test's own PID but another process start time: a reused PID, the lock is stale
    _lock_for(tmp_path, os.getppid())
    doc = json.loads(runlock.lock_path(tmp_path).read_text())
    doc["proc_start"] = "1"
    runlock.lock_path(tmp_path).write_text(json.dumps(doc))
    assert runlock.acquire(tmp_path).pid == os.getpid()
    # a run on another host cannot be checked: refused, with what to do
    _lock_for(tmp_path, 1, host="elsewhere.example")
    with pytest.raises(runlock.RunLockError, match="on another host: remove the file"):
        runlock.acquire(tmp_path)
    runlock.lock_path(tmp_path).write_text("garbage")
    with pytest.raises(runlock.RunLockError, match="not a depthgt run lock"):
        runlock.holder(tmp_path)
