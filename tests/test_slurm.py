"""The workflow on a real SLURM cluster.

cluster/slurm-local.sh starts a single-node SLURM cluster on this machine (installing
Debian's slurmctld, slurmd, slurm-client and munge when they are missing; the test is
skipped, with the script's reason, where that is impossible). The tiny synthetic workflow
then runs through snakemake-executor-plugin-slurm with profiles/slurm, and the test
checks, without sacct, that SLURM ran every non-local job (the job completion record of
the cluster) and that each sbatch request is what the job's rule declares: memory, time
limit, cores, and a GPU exactly when the job asks for one (config `device: cuda`).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from conftest import REPO, TINY, digest_outputs, early, make_workdir

pytestmark = pytest.mark.slow

SCRIPT = REPO / "cluster" / "slurm-local.sh"

# conftest.TINY's first training room and its test room: two scenes, three frame sets
TINY = {**TINY, "sources": [dict(TINY["sources"][0], scenes=["room_000"]), TINY["sources"][2]]}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SlurmRuns:
    """The single-node cluster and this file's three runs: ``cpu``, TINY to ``dataset``;
    ``cuda``, its test scene to ``framesets`` with ``device: cuda``; ``killed``, TINY to
    ``dataset`` again, with one frame-set job cancelled (``scancel``) while it runs
    (:meth:`_cancel_held_job`). An early run in a lane of its own (:func:`slurm_runs`):
    most of a run's time is the executor waiting between job-state checks, so they
    overlap with the other test files and with each other."""

    def __init__(self, folder: Path):
        state = folder / "state"
        state.mkdir()
        self.env = dict(
            os.environ,
            DEPTHGT_SLURM_STATE=str(state),
            DEPTHGT_SLURMCTLD_PORT=str(free_port()),
            DEPTHGT_SLURMD_PORT=str(free_port()),
            DEPTHGT_SLURM_GPUS="2",
        )
        self.hold = folder / "hold"
        self.hold.mkdir()
        self.cancelled: str | None = None  # the SLURM job id cancelled, or why none was
        self.workdirs = {
            "killed": make_workdir(folder / "killed", TINY),
            "cpu": make_workdir(folder / "cpu", TINY),
            "cuda": make_workdir(  # one scene, one frame set
                folder / "cuda", dict(TINY, sources=TINY["sources"][1:], device="cuda")
            ),
        }
        self.start: subprocess.CompletedProcess | None = None
        self.procs: dict[str, subprocess.Popen] = {}
        #: each run's workdir and its output, once it has ended
        self.results: dict[str, tuple[Path, subprocess.CompletedProcess]] = {}

    def __getstate__(self) -> dict:
        """Pickled (handed to another xdist worker, conftest._Shared) without the processes."""
        return {k: v for k, v in self.__dict__.items() if k != "procs"}

    def __call__(self) -> SlurmRuns:
        """Starts the cluster, then the three runs, cancels the ``killed`` run's held job
        and waits for the runs (:func:`finished`)."""
        self.start = subprocess.run(
            ["bash", str(SCRIPT), "start"], env=self.env, capture_output=True, text=True, timeout=900
        )
        if self.start.returncode == 0:
            env = self.cluster()
            held = dict(env, DEPTHGT_TEST_HOLD_DIR=str(self.hold), DEPTHGT_TEST_HOLD_AT=KILLED_JOB)
            self.procs = {
                "killed": snakemake_on_slurm(self.workdirs["killed"], held, "dataset"),
                "cpu": snakemake_on_slurm(self.workdirs["cpu"], env, "dataset"),
                "cuda": snakemake_on_slurm(self.workdirs["cuda"], env, "framesets"),
            }
            self._cancel_held_job(env)
            self.results = {
                name: (self.workdirs[name], finished(proc, self.workdirs[name])) for name, proc in self.procs.items()
            }
        return self

    def _cancel_held_job(self, env: dict[str, str]) -> None:
        """Wait until the frame-set job :data:`KILLED_JOB` of the ``killed`` run holds (it
        has started, depthgt.testhook), cancel its SLURM job with ``scancel`` and let
        every later pass go on (the retry, submitted by the profile's ``retries``)."""
        deadline = time.time() + 600
        try:
            while time.time() < deadline and self.procs["killed"].poll() is None:
                held = list(self.hold.glob("*.held"))
                if held:
                    pid = held[0].name.split(".")[-2]
                    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
                    job = dict(e.decode().split("=", 1) for e in environ if b"=" in e)["SLURM_JOB_ID"]
                    subprocess.run(["scancel", job], env=env, check=True, capture_output=True, timeout=60)
                    self.cancelled = job
                    return
                time.sleep(0.2)
            self.cancelled = f"no held job (run exit status {self.procs['killed'].poll()})"
        except (OSError, KeyError, subprocess.SubprocessError) as err:
            self.cancelled = f"cannot cancel the held job: {type(err).__name__}: {err}"
        finally:
            (self.hold / "release").write_text("")

    def cluster(self) -> dict[str, str]:
        """The running cluster's environment (SLURM_CONF set); skips where the script
        cannot set one up."""
        if self.start.returncode == 3:  # the script's code for "SLURM cannot be installed or set up here"
            pytest.skip(f"no SLURM cluster on this machine: {self.start.stderr.strip()}")
        assert self.start.returncode == 0, (
            f"cluster/slurm-local.sh start failed ({self.start.returncode}):\n{self.start.stderr}"
        )
        return dict(self.env, SLURM_CONF=str(Path(self.env["DEPTHGT_SLURM_STATE"]) / "slurm.conf"), OMP_NUM_THREADS="1")

    def stop(self) -> None:
        """At the session's end: the runs killed if still going, the cluster stopped."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        subprocess.run(["bash", str(SCRIPT), "stop"], env=self.env, capture_output=True, text=True, timeout=300)


# the frame-set job of the ``killed`` run that is cancelled while it runs (its start, depthgt.testhook)
KILLED_JOB = "job:logs/framesets/syn/room_000/*"


@early(lane="slurm")
def slurm_runs(folder: Path) -> SlurmRuns:
    """The cluster and its three runs, started with the test session (an early run)."""
    return SlurmRuns(folder)


@pytest.fixture(scope="module")
def slurm(slurm_runs) -> dict[str, str]:
    """Environment of the running single-node cluster (stopped when the session ends)."""
    return slurm_runs.cluster()


def snakemake_on_slurm(workdir: Path, env: dict[str, str], target: str, *args: str) -> subprocess.Popen:
    """Start the cluster command of README.md and docs/cluster.md, plus what this
    accounting-free test cluster needs: job states from squeue, no account, and a short
    first status check. Its output goes to workdir/snakemake.out and .err (:func:`finished`)."""
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        target,
        "-s",
        str(REPO / "Snakefile"),
        "-d",
        str(workdir),
        "--profile",
        str(REPO / "profiles" / "slurm"),
        "--executor",
        "slurm",
        "--slurm-status-command",
        "squeue",
        "--slurm-no-account",
        "--slurm-init-seconds-before-status-checks",
        "2",
        *args,
    ]
    with open(workdir / "snakemake.out", "w") as out, open(workdir / "snakemake.err", "w") as err:
        return subprocess.Popen(cmd, cwd=workdir, stdout=out, stderr=err, text=True, env=env)


def finished(proc: subprocess.Popen, workdir: Path) -> subprocess.CompletedProcess:
    """Wait for a run of :func:`snakemake_on_slurm` and collect its output."""
    try:
        proc.wait(timeout=900)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    out, err = ((workdir / f"snakemake.{s}").read_text() for s in ("out", "err"))
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.fixture(scope="module")
def runs(slurm_runs, slurm) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """The runs of :class:`SlurmRuns`, ended."""
    return slurm_runs.results


def submitted_jobs(log: str) -> list[dict]:
    """Snakemake's record of each job it ran: rule, local or not, threads, resources, and
    the SLURM job id it was submitted as (None for local jobs)."""
    # the logs of failed jobs that Snakemake echoes (show-failed-logs) hold their own
    # job records: leave them out
    log = re.sub(r"^Logfile [^\n]*:\n={80}\n.*?^={80}$", "", log, flags=re.M | re.S)
    jobs = {}
    for block in re.split(r"\n(?=(?:local)?(?:rule|checkpoint) \w+:\n)", log)[1:]:
        head = re.match(r"(local)?(?:rule|checkpoint) (\w+):", block)
        jobid = re.search(r"^\s+jobid: (\d+)$", block, re.M)
        resources = re.search(r"^\s+resources: (.*)$", block, re.M)
        threads = re.search(r"^\s+threads: (\d+)$", block, re.M)
        jobs[jobid.group(1)] = {
            "rule": head.group(2),
            "local": head.group(1) is not None,
            "threads": int(threads.group(1)) if threads else 1,
            "resources": dict(kv.split("=", 1) for kv in resources.group(1).split(", ")) if resources else {},
            "slurm_id": None,
        }
    for jobid, slurm_id in re.findall(r"Job (\d+) has been submitted with SLURM jobid (\d+)", log):
        jobs[jobid]["slurm_id"] = slurm_id
    return list(jobs.values())


def completion_records(state_env: dict[str, str]) -> dict[str, dict[str, str]]:
    """The cluster's job completion log (jobcomp/filetxt), by SLURM job id."""
    path = Path(state_env["DEPTHGT_SLURM_STATE"]) / "jobcomp.txt"
    records = [dict(re.findall(r"(\w+)=(\S*)", line)) for line in path.read_text().splitlines() if line.strip()]
    return {r["JobId"]: r for r in records}


def slurm_job(slurm_id: str, env: dict[str, str]) -> dict[str, str]:
    """slurmctld's record of a job (kept MinJobAge = 1 h after it ends: the runs start with the session)."""
    out = subprocess.run(
        ["scontrol", "show", "job", "-o", slurm_id], env=env, capture_output=True, text=True, check=True
    ).stdout
    return dict(re.findall(r"(\w+)=(\S*)", out))


def test_tiny_workflow_runs_through_slurm(slurm, runs):
    wd, proc = runs["cpu"]
    assert proc.returncode == 0, f"{proc.stdout[-2000:]}\n{proc.stderr[-8000:]}"

    for split in ("train", "test"):
        assert len(pd.read_parquet(wd / f"results/dataset/{split}.parquet")) > 0
    fs = pd.read_parquet(wd / "results/dataset/framesets.parquet")
    assert (fs["status"] == "ok").sum() == 3  # targets 6 and 7 of room_000, 6 of room_003

    jobs = submitted_jobs(proc.stderr)
    remote = [j for j in jobs if not j["local"]]
    # at least the frame-set work and the dataset assembly ran as SLURM jobs
    assert len(remote) >= 2 and all(j["slurm_id"] for j in remote), jobs
    assert all(j["slurm_id"] is None for j in jobs if j["local"])
    done = completion_records(slurm)
    for job in remote:
        record = done[job["slurm_id"]]
        assert record["JobState"] == "COMPLETED" and record["WorkDir"] == str(wd), record
        # one job, one request: what the rule declares, never a group's sum
        tres = dict(kv.split("=") for kv in record["Tres"].split(","))
        assert tres["mem"] == f"{job['resources']['mem_mb']}M", (job, record)
        assert int(tres["cpu"]) == job["threads"] and tres["node"] == "1", (job, record)
        assert int(record["TimeLimit"]) == int(job["resources"]["runtime"]), (job, record)
        assert "gpu" not in slurm_job(job["slurm_id"], slurm).get("TresPerJob", ""), job


def test_cuda_config_requests_a_gpu_per_torch_job(slurm, runs):
    """With `device: cuda` the jobs that run torch ask SLURM for one GPU each, the others
    for none. (This machine's GPU may be a placeholder: only the requests are checked.)"""
    _, proc = runs["cuda"]
    jobs = [j for j in submitted_jobs(proc.stderr) if j["slurm_id"]]
    assert any(j["resources"].get("gpu") == "1" for j in jobs), (jobs, proc.stderr[-4000:])
    for job in jobs:
        per_job = slurm_job(job["slurm_id"], slurm).get("TresPerJob", "")
        assert (per_job == "gres:gpu:1") == (job["resources"].get("gpu", "0") == "1"), (job, per_job)


def test_a_cancelled_job_is_retried_and_the_outputs_equal_an_uninterrupted_runs(slurm, runs, slurm_runs):
    """A frame-set job cancelled with scancel while it runs is submitted again by the
    profile's `retries`; the build completes with every result (each shard member, the
    manifests, the card) equal to the uninterrupted run's, timings aside."""
    wd, proc = runs["killed"]
    assert slurm_runs.cancelled and slurm_runs.cancelled.isdigit(), slurm_runs.cancelled
    assert proc.returncode == 0, f"{proc.stdout[-2000:]}\n{proc.stderr[-8000:]}"
    assert f"SLURM-job '{slurm_runs.cancelled}' failed, SLURM status is: 'CANCELLED'" in proc.stderr, proc.stderr[
        -6000:
    ]
    submissions = re.findall(r"Job (\d+) has been submitted with SLURM jobid (\d+)", proc.stderr)
    (jobid,) = [j for j, slurm_id in submissions if slurm_id == slurm_runs.cancelled]
    again = [slurm_id for j, slurm_id in submissions if j == jobid and slurm_id != slurm_runs.cancelled]
    assert len(again) == 1, submissions  # the same Snakemake job, submitted once more
    records = completion_records(slurm)
    assert records[slurm_runs.cancelled]["JobState"] == "CANCELLED" and records[again[0]]["JobState"] == "COMPLETED"
    clean_wd, clean = runs["cpu"]
    assert clean.returncode == 0
    assert digest_outputs(wd) == digest_outputs(clean_wd)
