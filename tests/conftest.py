"""Shared helpers of the tests: running the workflow on a config in a temporary workdir."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def synthetic_source(name: str, scenes: list[str], split: str, n_frames: int, width: int, height: int) -> dict:
    """A ``sources`` entry of the synthetic kind."""
    return {
        "name": name,
        "kind": "synthetic",
        "scenes": scenes,
        "split": split,
        "options": {"n_frames": n_frames, "width": width, "height": height},
    }


# The tiny synthetic build that several test files read (tiny_build): two training
# rooms, a validation and a test room, one or two frame sets each.
TINY = {
    "seed": 3,
    "device": "cpu",
    "sources": [
        synthetic_source("syn", ["room_000", "room_001"], "train", 14, 320, 240),
        synthetic_source("synval", ["room_002"], "val", 13, 320, 240),
        synthetic_source("syntest", ["room_003"], "test", 13, 320, 240),
    ],
    "frameset": {"neighbours": 3, "stride": 2, "target_step": 1},
    "resize": 128,
    "patches": {"count": 6, "size": 64, "max_missing": 0.15, "filter_on": "gt"},
}


# The tiny enhancement build (tiny_report): a training, a validation and a test room at
# 160x120, the filter methods only (no training).
TINY_ENHANCE = {
    "seed": 1,
    "device": "cpu",
    "sources": [
        synthetic_source("syn", ["room_000"], "train", 10, 160, 120),
        synthetic_source("synval", ["room_002"], "val", 8, 160, 120),
        synthetic_source("syntest", ["room_003"], "test", 8, 160, 120),
    ],
    "frameset": {"neighbours": 1, "stride": 2, "target_step": 2},
    "resize": 64,
    "patches": {"count": 4, "size": 32, "max_missing": 0.2, "filter_on": "gt"},
    "enhance": {
        "train": {"epochs": 1, "batch_size": 4, "lr": 0.001, "max_batches_per_epoch": 2},
        "rde": {"voxel_m": 0.04, "frame_step": 1, "backend": "torch", "max_missing": 0.5},
    },
    "evaluation": {"methods": ["input", "rgf"], "figure_frames_per_scene": 1},
}


def count_synthetic_reads(monkeypatch) -> list[int]:
    """The positions of every frame a synthetic scene reads from now on, in order (a list
    filled in place): a test of a batch's frame caches asserts each is read once."""
    from depthgt.sources import synthetic

    reads: list[int] = []
    real_read = synthetic.SyntheticScene.read

    def counting_read(self, i):
        reads.append(i)
        return real_read(self, i)

    monkeypatch.setattr(synthetic.SyntheticScene, "read", counting_read)
    return reads


def _snakemake_command(workdir: Path, *args: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(REPO / "Snakefile"),
        "-d",
        str(workdir),
        "--cores",
        "2",
        "--rerun-incomplete",
        *args,
    ]


def _failed(proc) -> AssertionError:
    return AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}")


def snakemake(workdir: Path, *args: str, check: bool = True, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(_snakemake_command(workdir, *args), capture_output=True, text=True, env=env, **kw)
    if check and proc.returncode != 0:
        raise _failed(proc)
    return proc


def planned_jobs(workdir: Path, *args: str) -> dict[str, int]:
    """rule -> number of jobs a dry run of ``args`` would run (Snakemake's job table)."""
    return jobs_table(snakemake(workdir, "-n", *args).stdout)


def jobs_table(text: str) -> dict[str, int]:
    """rule -> number of jobs in a dry run's output ``text`` (Snakemake's job table)."""
    if "Nothing to be done" in text:
        return {}
    table = text[text.index("Job stats:") :]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)$", table, re.M) if m.group(1) != "total"}


def make_workdir(path: Path, config: dict) -> Path:
    (path / "config").mkdir(parents=True)
    (path / "config" / "config.yaml").write_text(yaml.safe_dump(config))
    return path


def _normalised(name: str, data: bytes) -> bytes:
    """poses.json without its timings (wall-clock and CPU seconds); the dataset card
    without the checksums of the shards (their poses.json hold the timings)."""
    if name.endswith("poses.json"):
        doc = json.loads(data)
        doc.pop("timings_s", None)
        doc.pop("cpu_s", None)
        return json.dumps(doc, sort_keys=True).encode()
    if name == "card.json":
        doc = json.loads(data)
        doc["files"] = {k: v for k, v in doc["files"].items() if not k.endswith(".zip")}
        return json.dumps(doc, sort_keys=True).encode()
    return data


def digest_outputs(workdir: Path) -> dict[str, str]:
    """sha256 of every result file, and of every member of a zip archive (frame-set
    shards, RDE frames); poses.json without its timings. Temporary frame caches are not
    results."""
    out = {}
    for p in sorted((workdir / "results").rglob("*")):
        if not p.is_file() or p.parent.name == "frames":
            continue
        rel = str(p.relative_to(workdir))
        if p.suffix == ".zip":
            with zipfile.ZipFile(p) as z:
                for name in sorted(z.namelist()):
                    out[f"{rel}/{name}"] = hashlib.sha256(_normalised(name, z.read(name))).hexdigest()
            continue
        out[rel] = hashlib.sha256(_normalised(p.name, p.read_bytes())).hexdigest()
    return out


# ------------------------------------------------------------------------------ early runs
# A workflow run whose result the tests only read can start with the test session: on 2
# cores it then overlaps with the other tests instead of waiting for its turn. Such a run
# is declared where it is defined, as a session fixture (@early); the session starts the
# ones its selected tests use (_early_runs).

#: the early runs' live workflow processes, killed when the session ends before they do
_LIVE: set[subprocess.Popen] = set()
_STOP = threading.Event()


def in_background(workdir: Path, *args: str) -> Callable[[], Path]:
    """The part of an early run (:func:`early`) that runs in the background: the workflow
    on ``workdir`` with ``args`` in a subprocess, in the environment of now (a test may
    change ``os.environ`` for a moment while it runs); returns ``workdir``. A session that
    ends first (``-x``, Ctrl-C) kills it rather than waiting for it."""
    env = dict(os.environ, OMP_NUM_THREADS="1")

    def run() -> Path:
        if _STOP.is_set():
            raise RuntimeError(f"the test session ended before the early run in {workdir} started")
        proc = subprocess.Popen(
            _snakemake_command(workdir, *args),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,  # its own process group: the jobs die with it
        )
        _LIVE.add(proc)
        try:
            out, err = proc.communicate()
        finally:
            _LIVE.discard(proc)
        if proc.returncode != 0:
            raise _failed(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
        return workdir

    return run


def depthgt_command(*args: str) -> list[str]:
    """The ``depthgt`` command line of this checkout (``python -m depthgt.cli``)."""
    return [sys.executable, "-m", "depthgt.cli", *args]


def commands_in_background(
    commands: list[list[str]], env: dict[str, str] | None = None, cwd: Path | None = None
) -> Callable[[], list[subprocess.CompletedProcess]]:
    """Like :func:`in_background`, for runs whose failure the test reads: ``commands``
    one after another in subprocesses (in the environment of now, ``env`` added),
    returning each one's CompletedProcess (output captured) whatever its exit status."""
    full_env = dict(os.environ, OMP_NUM_THREADS="1", **(env or {}))

    def run() -> list[subprocess.CompletedProcess]:
        done = []
        for cmd in commands:
            if _STOP.is_set():
                raise RuntimeError(f"the test session ended before {' '.join(cmd)} started")
            proc = subprocess.Popen(
                cmd,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=full_env,
                cwd=cwd,
                start_new_session=True,
            )
            _LIVE.add(proc)
            try:
                out, err = proc.communicate()
            finally:
                _LIVE.discard(proc)
            done.append(subprocess.CompletedProcess(cmd, proc.returncode, out, err))
        return done

    return run


class _Declared(NamedTuple):
    prepare: Callable[[Path], Callable[[], object]]
    module: str  # the declaring module: its tests see the fixture (every test for conftest)
    lane: str


#: the early fixtures, by name (a fixture's name is its function's)
_DECLARED: dict[str, _Declared] = {}


def early(*, lane: str = "workflow") -> Callable[[Callable[[Path], Callable[[], object]]], object]:
    """Declares an early run: ``@early()`` on ``def NAME(folder) -> run`` makes NAME a
    session fixture whose value is what ``run()`` returns.

    ``NAME(folder)`` prepares the run's inputs in an empty folder, in the main thread, and
    returns ``run``: a function of no arguments that only runs subprocesses
    (:func:`in_background`, :func:`commands_in_background`) and copies files, taking an
    earlier run's result with :func:`earlier_run`; nothing of the library runs in the
    background, since tests monkeypatch it in-process. When a selected test uses NAME (also through another
    fixture), the session prepares it at its start and calls ``run`` in the background
    thread of its ``lane``, the lane's runs one after another in the order the tests
    that need them are reached (:func:`_in_order_reached`); the fixture waits for the
    result. A workflow run is mostly one job process at a
    time, so on 2 cores the ``workflow`` lane overlaps with the other tests; a run that
    mostly waits (a SLURM cluster's) takes a lane of its own. A ``run`` with a ``stop()``
    method has it called when the session ends. A failed preparation fails the fixture's
    tests, not the session."""

    def declare(prepare: Callable[[Path], Callable[[], object]]):
        name = prepare.__name__
        known = _DECLARED.get(name)
        if known is not None and known.module != prepare.__module__:
            raise ValueError(f"two early fixtures named {name}: in {known.module} and {prepare.__module__}")
        _DECLARED[name] = _Declared(prepare, prepare.__module__, lane)

        def fixture(_early_runs: EarlyRuns):
            return _early_runs.value(name)

        fixture.__doc__ = prepare.__doc__
        return pytest.fixture(scope="session", name=name)(fixture)

    return declare


class EarlyRuns:
    """The early runs of one test session (:func:`early`): prepared at its start, run in
    one background thread per lane, their results handed to their fixtures."""

    def __init__(self, tmp_path_factory, names: list[str], shared: _Shared | None = None):
        self._tmp = tmp_path_factory
        self._shared = shared
        self._jobs: dict[str, Callable[[], object]] = {}
        self._done: dict[str, tuple[bool, object]] = {}
        self._t0 = time.monotonic()
        #: (name, lane, start s, end s) of each finished run, seconds from the session's start
        self.times: list[tuple[str, str, float, float]] = []
        self._cond = threading.Condition()
        lanes: dict[str, list[str]] = {}
        for name in names:
            self._jobs[name] = self._prepared(name)
            lanes.setdefault(_DECLARED[name].lane, []).append(name)
        self._threads = [threading.Thread(target=self._run, args=(lane,), daemon=True) for lane in lanes.values()]
        self._lanes_left = len(self._threads)
        if shared is not None and not self._threads:
            shared.lanes_ended(self.times)
        for thread in self._threads:
            thread.start()

    def _prepared(self, name: str) -> Callable[[], object]:
        return _prepared(self._tmp, name)

    def _run(self, names: list[str]) -> None:
        for name in names:
            start = time.monotonic() - self._t0
            try:
                out = (True, self._jobs[name]())
            except BaseException as e:  # handed to the fixture, which raises it
                out = (False, e)
            self.times.append((name, _DECLARED[name].lane, start, time.monotonic() - self._t0))
            if self._shared is not None:
                self._shared.publish(name, out)
            with self._cond:
                self._done[name] = out
                self._cond.notify_all()
        with self._cond:
            self._lanes_left -= 1
            last = self._lanes_left == 0
        if last and self._shared is not None:
            self._shared.lanes_ended(self.times)

    def earlier(self, name: str):
        """For a run: the result of ``name``, a run before it in its lane (raises if
        ``name`` has not ended: waiting for a later run of the same lane would never end)."""
        with self._cond:
            if name not in self._done:
                raise RuntimeError(f"the early run {name} has not ended: declare its tests first")
            ok, value = self._done[name]
        if not ok:
            raise value
        return value

    def value(self, name: str, timeout: float = 1800):
        """The result of ``name``'s run, waited for; a run no selected test asked for at
        the session's start (a fixture requested on the fly) runs here and now."""
        if name not in self._jobs:
            self._jobs[name] = self._prepared(name)
            return self._jobs[name]()
        with self._cond:
            if not self._cond.wait_for(lambda: name in self._done, timeout=timeout):
                pytest.fail(f"the early run {name} did not end within {timeout} s")
            ok, value = self._done[name]
        if not ok:
            raise value
        return value

    def running(self) -> bool:
        """Whether a lane still has runs to finish."""
        return any(thread.is_alive() for thread in self._threads)

    def stop(self) -> None:
        """Kills the workflow runs still going (a session ended early: their tests will not
        read them), waits for the lanes, then stops the runs that have a ``stop()``. Under
        xdist it first waits for the other workers' sessions to end: their tests may still
        read the runs (a cluster that a ``stop()`` shuts down, runs not yet finished)."""
        if self._shared is not None:
            self._shared.wait_for_workers()
        _STOP.set()
        for proc in list(_LIVE):
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for thread in self._threads:
            thread.join(timeout=900)
        for job in self._jobs.values():
            if hasattr(job, "stop"):
                job.stop()


def _prepared(tmp_path_factory, name: str) -> Callable[[], object]:
    """The run of ``name``, prepared in a folder of its own; or a run that raises the
    preparation's error (its tests fail, the session goes on)."""
    try:
        return _DECLARED[name].prepare(tmp_path_factory.mktemp(name))
    except Exception as e:
        err = e

        def failed():
            raise err

        return failed


class _Shared:
    """The early runs of a session spread over pytest-xdist workers: the first worker
    (gw0, the owner) runs them in its lanes and writes each result, pickled, into a folder
    beside the workers' temporary folders; the other workers read it from there. The owner
    stops the runs (a cluster's ``stop()``) only once every other worker's session has
    ended, or its process is gone."""

    def __init__(self, folder: Path, worker: str):
        self.folder, self.worker = folder, worker
        self.owner = worker == "gw0"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"started-{worker}").write_text(str(os.getpid()))

    @classmethod
    def of(cls, tmp_path_factory) -> _Shared | None:
        """This worker's share; None outside xdist (one process runs everything)."""
        worker = os.environ.get("PYTEST_XDIST_WORKER")
        if not worker:
            return None
        # each worker's basetemp is a folder popen-gwN in the session's basetemp (xdist)
        return cls(Path(tmp_path_factory.getbasetemp()).parent / "early", worker)

    def _write(self, name: str, data: bytes) -> None:
        part = self.folder / f"{name}.part"
        part.write_bytes(data)
        os.replace(part, self.folder / name)  # whole or not there: a reader never sees half

    def publish(self, name: str, out: tuple[bool, object]) -> None:
        try:
            data = pickle.dumps(out)
        except Exception as e:  # a result that cannot leave its process fails its tests elsewhere
            why = f"the early run {name} ran in worker {self.worker}; its result cannot be passed on: {e!r}"
            data = pickle.dumps((False, RuntimeError(why)))
        self._write(f"{name}.pickle", data)

    def result(self, name: str, timeout: float) -> tuple[bool, object] | None:
        """The owner's result of ``name``, waited for; None after ``timeout`` seconds."""
        path = self.folder / f"{name}.pickle"
        deadline = time.monotonic() + timeout
        while not path.exists():
            if time.monotonic() > deadline:
                return None
            time.sleep(0.2)
        try:
            return pickle.loads(path.read_bytes())
        except Exception as e:
            return False, RuntimeError(f"the early run {name}'s result cannot be read in worker {self.worker}: {e!r}")

    def lanes_ended(self, times: list[tuple[str, str, float, float]]) -> None:
        self._write("times.json", json.dumps(times).encode())
        self._write("lanes.ended", b"")

    def lanes_running(self) -> bool:
        return not (self.folder / "lanes.ended").exists()

    def ended(self) -> None:
        (self.folder / f"ended-{self.worker}").write_text("")

    def wait_for_workers(self, timeout: float = 3600) -> None:
        """Until every other worker that started has ended its session or died."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            waiting = []
            for started in self.folder.glob("started-*"):
                worker = started.name.removeprefix("started-")
                if worker == self.worker or (self.folder / f"ended-{worker}").exists():
                    continue
                try:
                    os.kill(int(started.read_text()), 0)
                except (ProcessLookupError, ValueError):
                    continue  # crashed: xdist reports it
                waiting.append(worker)
            if not waiting:
                return
            time.sleep(0.5)

    @staticmethod
    def times(config) -> list[tuple[str, str, float, float]]:
        """In the xdist controller: the owner's record of when each run ran."""
        factory = getattr(config, "_tmp_path_factory", None)  # pytest's tmp_path_factory (no public handle in hooks)
        path = factory.getbasetemp() / "early" / "times.json" if factory is not None else None
        return json.loads(path.read_text()) if path is not None and path.exists() else []


class _RunsOfTheOwner:
    """A worker's early runs when another worker (the owner, :class:`_Shared`) runs them:
    their results read as they come. A run that no selected test asked for at the
    session's start runs here, when a test asks for it (as in :meth:`EarlyRuns.value`)."""

    times: list[tuple[str, str, float, float]] = []

    def __init__(self, tmp_path_factory, names: list[str], shared: _Shared):
        self._tmp, self._names, self._shared = tmp_path_factory, set(names), shared
        self._here: dict[str, Callable[[], object]] = {}

    def value(self, name: str, timeout: float = 1800):
        if name not in self._names:
            self._here.setdefault(name, _prepared(self._tmp, name))
            return self._here[name]()
        out = self._shared.result(name, timeout)
        if out is None:
            pytest.fail(f"the early run {name} did not end within {timeout} s (run by worker gw0)")
        ok, value = out
        if not ok:
            raise value
        return value

    def earlier(self, name: str):
        raise RuntimeError(f"the early run {name} runs in worker gw0: an early run's run() runs there")

    def running(self) -> bool:
        return self._shared.lanes_running()

    def stop(self) -> None:
        for job in self._here.values():
            if hasattr(job, "stop"):
                job.stop()
        self._shared.ended()


def _in_order_reached(session) -> list[pytest.Item]:
    """The selected tests in the order the session reaches them: with pytest-xdist's
    ``loadfile`` the files with the most tests first (its default ``--loadscope-reorder``;
    equal counts in collection order), else the collection order. The lanes start their
    runs in this order, so that a run's tests find it finished rather than wait."""
    dist, reorder = getattr(session.config, "workerinput", {}).get("depthgt_dist", ("no", False))
    if dist != "loadfile" or not reorder:
        return list(session.items)
    files: dict[str, list[pytest.Item]] = {}
    for item in session.items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)
    return [item for tests in sorted(files.values(), key=len, reverse=True) for item in tests]  # a stable sort


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node) -> None:
    """pytest-xdist's hook, in the controller: tells each worker how the tests are handed
    out (a worker's own options say ``--dist no``), for :func:`_in_order_reached`."""
    option = node.config.option
    node.workerinput["depthgt_dist"] = (option.dist, bool(getattr(option, "loadscopereorder", True)))


def _xdist_controller(config) -> bool:
    """Whether this process hands tests to pytest-xdist workers (and runs none itself)."""
    return not hasattr(config, "workerinput") and getattr(config.option, "dist", "no") != "no"


def pytest_collection_finish(session) -> None:
    """After collection, the early fixtures (:func:`early`) that the selected tests use,
    in the order the tests need them, each seen only by the tests of the module that
    declares it (conftest's: every test). In a hook, not a fixture: every xdist worker
    takes part, also one that is handed no test."""
    config = session.config
    if config.option.collectonly or _xdist_controller(config):
        return
    _STOP.clear()
    names = []
    for item in _in_order_reached(session):
        module = getattr(getattr(item, "module", None), "__name__", None)  # doctests have none
        for name in getattr(item, "fixturenames", ()):
            declared = _DECLARED.get(name)
            if declared is not None and declared.module in ("conftest", module) and name not in names:
                names.append(name)
    if names:  # the workflow lane compiles the kernels first (compiled_kernels), once
        names = ["compiled_kernels", *(n for n in names if n != "compiled_kernels")]
    factory = config._tmp_path_factory  # the session's tmp_path_factory (no public handle in hooks)
    shared = _Shared.of(factory)
    if shared is None or shared.owner:
        runs = EarlyRuns(factory, names, shared)
    else:
        runs = _RunsOfTheOwner(factory, names, shared)
    _SESSION_RUNS[:] = [runs]


def pytest_sessionfinish(session) -> None:
    if _SESSION_RUNS:
        _SESSION_RUNS[0].stop()


@pytest.fixture(scope="session")
def _early_runs() -> EarlyRuns | _RunsOfTheOwner:
    """The session's early runs (:func:`pytest_collection_finish`)."""
    if not _SESSION_RUNS:
        pytest.fail("no early runs in this session (started by pytest_collection_finish)")
    return _SESSION_RUNS[0]


#: the session's EarlyRuns (or, in an xdist worker that does not own them, _RunsOfTheOwner)
_SESSION_RUNS: list[EarlyRuns | _RunsOfTheOwner] = []


def earlier_run(name: str):
    """In an early run's ``run``: the result of the early run ``name`` before it in its
    lane (:meth:`EarlyRuns.earlier`)."""
    return _SESSION_RUNS[0].earlier(name)


def pytest_terminal_summary(terminalreporter) -> None:
    """With ``--durations``: when each early run ran, from the session's start. A test
    that waits for a run that ends late holds up the session; this says which."""
    config = terminalreporter.config
    if config.getoption("durations", None) is None:
        return
    times = _SESSION_RUNS[0].times if _SESSION_RUNS else _Shared.times(config) if _xdist_controller(config) else []
    if not times:
        return
    terminalreporter.section("early runs (s from the session's start)")
    for name, lane, start, end in sorted(times, key=lambda t: t[2]):
        terminalreporter.write_line(f"{start:7.1f} - {end:7.1f} ({end - start:6.1f})  {lane:9s} {name}")


@early()
def compiled_kernels(folder: Path) -> Callable[[], list[subprocess.CompletedProcess]]:
    """``tests/warm_kernels.py``: the numba kernels compiled into their on-disk cache,
    first in the workflow lane whenever the session has early runs. In a fresh checkout
    the jobs and tests that start side by side would each compile them (~45 s of CPU
    apiece on the 2-core test machine); after it they load them. A kernel it leaves out is
    compiled where it is first used, as without it; test_batched checks that it ran."""
    return commands_in_background([[sys.executable, str(REPO / "tests/warm_kernels.py"), str(folder)]])


@early()
def tiny_build(folder: Path) -> Callable[[], Path]:
    """TINY built to the ``dataset`` target once per test session, shared by the test
    files that only read it (test_workflow, test_data, test_cli, test_profiles): a test
    that changes a build works on a copy or a build of its own. An early run."""
    return in_background(make_workdir(folder, TINY), "dataset")


@early()
def tiny_report(folder: Path) -> Callable[[], Path]:
    """TINY_ENHANCE built to the ``report`` target once per test session, shared by
    test_workflow_enhance (which reads it) and test_train_resume (which copies it). An
    early run."""
    return in_background(make_workdir(folder, TINY_ENHANCE), "report")


@pytest.fixture(autouse=True)
def _torch_threads(request):
    """Torch's intra-op threads for each test: the module's ``TORCH_THREADS`` if it sets
    one; else one while an early run (:func:`early`) is still going and, after, the
    machine's cores shared among the session's processes (two in one process on the
    2-core test machine, one in each of two xdist workers). A module-level
    ``torch.set_num_threads`` would hold for the whole session from the last module
    collected. Beside a running workflow, two intra-op threads ran tests 2-10x slower
    (test_batched under two busy processes: 89 s with two threads, 40 s with one)."""
    if "torch" in sys.modules:
        module = getattr(request.node, "module", None)  # a doctest has none
        busy = bool(_SESSION_RUNS) and _SESSION_RUNS[0].running()
        cores = (
            len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        )  # macOS: no affinity
        share = max(1, cores // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
        sys.modules["torch"].set_num_threads(getattr(module, "TORCH_THREADS", 1 if busy else share))
    yield
