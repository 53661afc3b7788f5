"""Faults in one line: a full disk (before the first job when the plan does not fit, and
while a job writes), a job over its memory, and failures a job explains, never a
traceback (issue 42)."""

from __future__ import annotations

import atexit
import errno
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from conftest import (
    REPO,
    _snakemake_command,
    commands_in_background,
    depthgt_command,
    early,
    make_workdir,
    synthetic_source,
)

from depthgt.errors import DepthGTError
from depthgt.gt import space
from depthgt.jobs.common import failure_line, logging_to
from depthgt.jobs.outcome import end_of_run_lines, memory_failures

# one scene, two frame sets of one batch each at 64x64: two shards of ~25 kB
SMALL = {
    "seed": 0,
    "device": "cpu",
    "resize": 64,
    "sources": [synthetic_source("syn", ["room_000"], "train", 14, 160, 120)],
    "frameset": {"neighbours": 3, "stride": 2, "target_step": 1, "batch_size": 1},
    "patches": {"count": 2, "size": 32, "max_missing": 0.5},
}
PLAN = [space.PlannedShard("results/framesets/syn/room_000/000006-000006.zip", 1, True)] * 2


def test_a_failure_a_job_explains_is_one_line(tmp_path):
    job = SimpleNamespace(rule="train_model", resources=SimpleNamespace(mem_mb=16000))
    line = failure_line(OSError(errno.ENOSPC, "No space left on device"), job)
    assert line.startswith(f"depthgt: error: no space left on the device of {Path('results').absolute()}: ")
    assert " free" in line
    assert failure_line(OSError("Error writing bytes to file. Detail: [errno 28] No space left on device"), job)
    exr = RuntimeError('Failed to write pixel data to image file "results/x/.gt.exr.tmp.exr". No space left on device.')
    assert failure_line(exr, job).startswith("depthgt: error: no space left on the device of ")  # OpenEXR's writer
    assert failure_line(RuntimeError("something else"), job) is None
    line = failure_line(MemoryError(), job)
    assert "job train_model ran out of memory (mem_mb=16000)" in line
    assert "--set-resources train_model:mem_mb=32000" in line
    assert failure_line(DepthGTError("x.png: truncated"), job) == "depthgt: error: x.png: truncated"
    assert failure_line(ValueError("a bug"), job) is None

    def fill():
        with logging_to(tmp_path / "job.log"):
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(SystemExit) as ended:
        fill()
    assert ended.value.code == 1
    text = (tmp_path / "job.log").read_text()
    assert "no space left on the device" in text and "Traceback" not in text and len(text.splitlines()) == 1
    logging.getLogger().handlers[:] = [h for h in logging.getLogger().handlers if h.level != logging.CRITICAL + 1]


def test_space_check_figures(tmp_path, monkeypatch):
    assert space.frameset_bytes(256, False) == 235_000  # the measured size of a real frame set
    monkeypatch.setattr(space, "free_bytes", lambda path: 30_000)
    need = space.space_need(tmp_path, PLAN, 64)
    assert need.framesets == 2 and need.needed == 2 * space.frameset_bytes(64, True) and not need.fits
    with pytest.raises(DepthGTError) as err:
        space.check_space(tmp_path, PLAN, 64)
    assert str(err.value).startswith(
        f"not enough space for the planned frame sets: {tmp_path / 'results'} has 30.0 kB (30000 bytes) free; "
        f"the rest of the build needs about 60.1 kB (60124 bytes) (2 frame sets still to build"
    )
    assert "dataset.check_space: false" in str(err.value)
    assert space.check_space(tmp_path, PLAN, 64, refuse=False).startswith("depthgt: warning: not enough space")
    shard = tmp_path / PLAN[0].path  # a built shard is not needed again
    shard.parent.mkdir(parents=True)
    shard.write_bytes(b"")
    assert space.space_need(tmp_path, PLAN[:1], 64).framesets == 0


def test_the_space_check_lists_each_scene_folder_once_and_stats_no_shard(tmp_path, monkeypatch):
    """The shards not built yet come from one listing per scene folder (ScanNet plans
    ~9,000 shards in ~1,500 folders), not one stat per shard, with Path.is_file's answers:
    a link to a shard counts as built, a folder or a dangling link does not; and a failed
    run's full-disk line lists each folder once."""
    plan = [
        space.PlannedShard(f"results/framesets/syn/{scene}/{a:06d}-{a:06d}.zip", 1, True)
        for scene in ("room_000", "room_001", "room_002")
        for a in range(6, 12)
    ]
    room0 = tmp_path / "results/framesets/syn/room_000"
    room0.mkdir(parents=True)
    (room0 / "000006-000006.zip").write_bytes(b"")  # built
    (tmp_path / "elsewhere.zip").write_bytes(b"")
    (room0 / "000007-000007.zip").symlink_to(tmp_path / "elsewhere.zip")  # a link to a file: built
    (room0 / "000008-000008.zip").mkdir()  # a folder of the shard's name: not built
    (room0 / "000009-000009.zip").symlink_to(tmp_path / "gone.zip")  # dangling: not built
    (room0 / "000010-000010.zip.tmp").write_bytes(b"")  # a half-written shard: not built
    room1 = tmp_path / "results/framesets/syn/room_001"
    room1.mkdir()
    (room1 / "000011-000011.zip").write_bytes(b"")
    # room_002 has no folder yet
    expected = [s for s in plan if not (tmp_path / s.path).is_file()]  # what a stat per shard decides
    assert len(expected) == len(plan) - 3

    listed, stats = [], []
    real_scandir, real_stat = os.scandir, os.stat
    monkeypatch.setattr(os, "scandir", lambda path=".": listed.append(Path(path)) or real_scandir(path))

    def stat(path, *args, **kwargs):
        stats.append(str(path))
        return real_stat(path, *args, **kwargs)

    monkeypatch.setattr(os, "stat", stat)
    assert space.missing_shards(tmp_path, plan) == expected
    assert sorted(listed) == [tmp_path / "results/framesets/syn" / r for r in ("room_000", "room_001", "room_002")]
    assert not [p for p in stats if ".zip" in p], stats  # the links are followed by the listing's entries

    listed.clear()
    monkeypatch.setattr(space, "free_bytes", lambda path: 1_000)
    log = tmp_path / "run.log"
    log.write_text("Error in rule frameset_batch:\nOSError: [Errno 28] No space left on device\n")
    lines = end_of_run_lines(tmp_path, [], plan, 64, log, {}, failed=True)
    assert f"({len(expected)} frame sets still to build" in lines[0], lines
    assert len(listed) == 3, listed  # each scene folder listed once at the run's end


def test_the_space_check_imports_neither_opencv_nor_torch():
    """The workflow's onstart imports depthgt.gt.space before the first job: the
    format's measured sizes come from depthgt.gt.sizes, not from the shard writer (which
    imports OpenCV, ~0.2 s)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]))
    code = (
        "import sys, depthgt.gt.space as s; "
        "assert s.__file__.startswith(sys.argv[1]), s.__file__; "
        "heavy = [m for m in ('cv2', 'torch', 'numpy', 'OpenEXR', 'depthgt.gt.store') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(REPO / "src")], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    from depthgt.gt import sizes, store

    assert store.MEASURED_FRAMESET_BYTES is sizes.MEASURED_FRAMESET_BYTES  # one definition, the writer's name kept


def test_memory_failures_name_the_rule_and_the_memory_to_ask():
    log = (
        "[Fri Nov 27 15:27:34 2026]\nError in rule train_model:\n    jobid: 3\n"
        "    message: SLURM-job '17' failed, SLURM status is: 'OUT_OF_MEMORY'\n"
        "[Fri Nov 27 15:27:35 2026]\nError in rule tables:\n    jobid: 4\n    exit status 1\n"
    )
    assert memory_failures(log, {"train_model": 16000}) == [
        "depthgt: error: job train_model was killed, most likely over its memory (mem_mb=16000): raise it, "
        "e.g. --set-resources train_model:mem_mb=32000 (or set-resources in the profile; on a cluster a job asks "
        "SLURM for exactly this), then run the same command again"
    ]


def _mount_tmpfs(path: Path, size: str) -> str | None:
    """Mount a tmpfs of ``size`` at ``path`` (unmounted when the session ends, at the
    latest); the reason when that is impossible here."""
    if os.geteuid() != 0:
        return "mounting a small tmpfs needs root"
    path.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if proc.returncode != 0:
        return f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}"
    atexit.register(subprocess.run, ["umount", str(path)], capture_output=True)
    return None


@early()
def full_disk_runs(folder: Path):
    """results/ on a 64 kB tmpfs: ``depthgt build`` of 8 frame sets, then of 2 (an early
    run)."""
    wd = make_workdir(folder / "wd", dict(SMALL, sources=[dict(SMALL["sources"][0], options={"n_frames": 20})]))
    results = wd / "results"
    why = _mount_tmpfs(results, "64k")
    if why:
        return lambda: (wd, why, [], [])
    two = folder / "two.yaml"
    two.write_text(yaml.safe_dump({"sources": SMALL["sources"]}))
    build = ["build", "-d", str(wd), "--cores", "2", "dataset"]
    run = commands_in_background([depthgt_command(*build), depthgt_command(*build, "--configfile", str(two))])

    def runs():
        try:
            done = run()
            return wd, None, done, sorted(str(p) for p in results.rglob("*.zip*"))  # shards left there
        finally:
            subprocess.run(["umount", str(results)], capture_output=True)

    return runs


@pytest.mark.slow
def test_a_full_disk_is_announced_before_work_and_is_one_line_when_it_happens(full_disk_runs):
    """results/ on a 64 kB file system: a plan of 8 frame sets (~240 kB estimated) is
    refused before any job, with the figures; two frame sets (~60 kB estimated) pass the
    check and fail writing their shards beside their work files, each job in one line,
    and the run ends with the folder, the bytes free and the bytes the rest needs."""
    wd, why, runs, shards = full_disk_runs
    if why:
        pytest.skip(why)
    refused, failed = runs
    results = wd / "results"
    assert refused.returncode != 0
    assert (
        f"depthgt: error: not enough space for the planned frame sets: {results} has 65.5 kB (65536 bytes) free; "
        "the rest of the build needs about 240.5 kB (240496 bytes) (8 frame sets still to build" in refused.stderr
    ), refused.stderr[-3000:]
    assert "Traceback" not in refused.stdout + refused.stderr
    said = failed.stdout + failed.stderr
    assert failed.returncode != 0 and "Traceback" not in said, said[-4000:]
    # the estimate (~60 kB) fit the 64 kB: no warning; the shards and their work files did not
    assert "not enough space for the planned frame sets" not in failed.stderr
    last = [line for line in failed.stderr.splitlines() if line.startswith("depthgt: error: no space left")][-1]
    assert last.startswith(f"depthgt: error: no space left on the device of {results}: {results} has ")
    assert "the rest of the build needs about" in last and "frame sets still to build" in last
    assert shards == []  # no torn shard, no temporary file left taking the space


@early()
def killed_job_run(folder: Path):
    """A frame-set job killed with SIGKILL while it runs (an early run): the workflow
    started, the job's process killed once it holds (depthgt.testhook)."""
    wd = make_workdir(folder / "wd", SMALL)
    hold = folder / "hold"
    env = dict(
        os.environ, OMP_NUM_THREADS="1", DEPTHGT_TEST_HOLD_DIR=str(hold), DEPTHGT_TEST_HOLD_AT="job:logs/framesets/*"
    )

    def run() -> subprocess.CompletedProcess:
        proc = subprocess.Popen(
            _snakemake_command(wd, "framesets"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        try:
            deadline = time.time() + 600
            while time.time() < deadline and proc.poll() is None and not list(hold.glob("*.held")):
                time.sleep(0.05)
            held = list(hold.glob("*.held"))
            if held:
                os.kill(int(held[0].name.split(".")[-2]), signal.SIGKILL)
            (hold / "release").write_text("")  # the other job goes on
            out, err = proc.communicate(timeout=600)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)

    return run


@pytest.mark.slow
def test_a_job_killed_for_its_memory_names_the_rule_and_mem_mb(killed_job_run):
    """A frame-set job killed with SIGKILL (what the kernel's OOM killer does) while it
    runs: the run ends with the rule and the mem_mb to raise."""
    proc = killed_job_run
    assert proc.returncode != 0
    assert (
        "depthgt: error: job frameset_batch was killed, most likely over its memory (mem_mb=2000): raise it, "
        "e.g. --set-resources frameset_batch:mem_mb=4000" in proc.stderr
    ), proc.stderr[-4000:]


def test_end_of_run_lines_of_a_failed_run_without_a_plan_to_build(tmp_path):
    (tmp_path / "results").mkdir()
    assert end_of_run_lines(tmp_path, [], [], 64, None, {}, failed=True) == []


def test_a_gpu_out_of_memory_is_not_a_mem_mb_to_raise():
    log = (
        "[Fri Nov 27 15:27:34 2026]\nError in rule train_model:\n    jobid: 3\n"
        "torch.OutOfMemoryError: CUDA out of memory. Tried to allocate 2.00 GiB\n"
    )
    assert memory_failures(log, {"train_model": 16000}) == []


def test_a_failed_run_on_a_tight_disk_is_not_called_a_full_disk(tmp_path, monkeypatch):
    """The plan would not fit, but the job failed for another reason: no 'no space left'
    line (the log shows no full disk); with the system's message in the log, the line."""
    (tmp_path / "results").mkdir()
    monkeypatch.setattr(space, "free_bytes", lambda path: 1_000)
    log = tmp_path / "run.log"
    log.write_text("Error in rule tables:\n    jobid: 4\nValueError: something else\n")
    lines = end_of_run_lines(tmp_path, [], PLAN, 64, log, {}, failed=True)
    assert not any("no space left" in line for line in lines), lines
    log.write_text("Error in rule frameset_batch:\nOSError: [Errno 28] No space left on device\n")
    lines = end_of_run_lines(tmp_path, [], PLAN, 64, log, {}, failed=True)
    assert [line for line in lines if "no space left" in line][0].startswith(
        f"depthgt: error: no space left on the device of {tmp_path / 'results'}"
    ), lines
