"""The workflow profile profiles/default: Snakemake 9 finds it beside the Snakefile (also
when it is started elsewhere with -s/-d), and its settings make the README's promise hold:
a run killed with SIGKILL while a job runs finishes when the same command is run again,
with the outputs of an uninterrupted run; a second run in the same directory
is refused while the first is alive (depthgt.runlock)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO, TINY, digest_outputs, make_workdir


def plain_command(workdir: Path, *args: str) -> list[str]:
    """The command a user types, without --cores, --rerun-incomplete or --unlock: all of
    that must come from the workflow profile."""
    return [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(workdir), *args]


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=900)


def test_default_profile_is_found_beside_the_snakefile(tmp_path):
    """Started from another folder with -s/-d and no --cores: the profile beside the
    Snakefile supplies the cores; without it Snakemake refuses to run."""
    wd = make_workdir(tmp_path / "wd", TINY)
    target = "results/report/config.yaml"
    without = run(plain_command(wd, "--workflow-profile", "none", target), cwd=tmp_path)
    assert without.returncode != 0
    assert "cores have to be specified" in without.stderr
    with_profile = run(plain_command(wd, target), cwd=tmp_path)
    assert with_profile.returncode == 0, with_profile.stderr[-3000:]
    assert f"workflow specific profile {REPO / 'profiles' / 'default'}" in with_profile.stderr
    assert (wd / target).is_file()


def hold_env(hold: Path, at: str = "*") -> dict:
    """Environment of a build whose jobs stop at the pause point ``at`` (depthgt.testhook)
    until the test releases or kills them."""
    return dict(os.environ, OMP_NUM_THREADS="1", DEPTHGT_TEST_HOLD_DIR=str(hold), DEPTHGT_TEST_HOLD_AT=at)


def wait_held(hold: Path, proc: subprocess.Popen, timeout: float = 300) -> list[Path]:
    """The pause points reached, once a job of ``proc`` has reached one."""
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        held = sorted(hold.glob("*.held"))
        if held:
            return held
        time.sleep(0.05)
    raise AssertionError(f"no job reached a pause point (build exit code {proc.poll()})")


@pytest.mark.slow
def test_one_run_per_directory_and_kill9_then_same_command_finishes(tiny_build, tmp_path):
    """Killed while a scene's summary job runs (its frame sets are built; the job waits at
    its start, depthgt.testhook, until the kill), then the same command again: the files
    of the session's uninterrupted build of the same config in another folder
    (conftest.tiny_build, built with explicit --cores and --rerun-incomplete), so this is
    also the check that a second build is identical."""
    reference = tiny_build
    assert not (reference / ".snakemake/depthgt-run.lock").exists()  # released at the end

    wd = make_workdir(tmp_path / "killed", TINY)
    hold = tmp_path / "hold"
    proc = subprocess.Popen(
        plain_command(wd, "dataset"),
        cwd=tmp_path,
        env=hold_env(hold, "job:logs/scenes/*/summary.log"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        # the first job waits at its start until the build is killed: a job is running
        wait_held(hold, proc)
        lock = json.loads((wd / ".snakemake/depthgt-run.lock").read_text())
        assert lock["pid"] == proc.pid
        # a second run in the same directory is refused, naming the first
        second = run(plain_command(wd, "dataset"), cwd=tmp_path)
        assert second.returncode != 0
        assert "another run is using this working directory" in second.stderr
        assert f"PID {proc.pid} on {lock['host']}, started {lock['started']}" in second.stderr
        cli = subprocess.run(
            [sys.executable, "-m", "depthgt.cli", "build", "-d", str(wd), "dataset"],
            capture_output=True,
            text=True,
            cwd=tmp_path,
        )
        assert cli.returncode == 2 and f"PID {proc.pid}" in cli.stderr, cli.stderr[-2000:]
        # a dry run neither takes nor is refused by the lock
        dry = run(plain_command(wd, "dataset", "-n"), cwd=tmp_path)
        assert dry.returncode == 0, dry.stderr[-3000:]
        assert json.loads((wd / ".snakemake/depthgt-run.lock").read_text())["pid"] == proc.pid
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert any((wd / ".snakemake" / "incomplete").glob("*")), "no job was running when the build was killed"
    assert list((wd / "results").rglob("*.zip")), "no frame set was built before the kill"
    assert not (wd / "results/dataset/summary.json").exists(), "the build finished before it could be killed"

    # the same command again: the killed run's lock is stale, no --unlock needed
    again = run(plain_command(wd, "dataset"), cwd=tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    assert not (wd / ".snakemake/depthgt-run.lock").exists()
    assert digest_outputs(wd) == digest_outputs(reference)
