"""Shared helpers of the tests: running the workflow on a config in a temporary workdir."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import zipfile
from collections.abc import Callable
from pathlib import Path

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


# the early runs' live workflow processes, killed when the session ends before they do
_LIVE: set[subprocess.Popen] = set()
_STOP = threading.Event()


def in_background(workdir: Path, *args: str) -> Callable[[], Path]:
    """The part of an early run (:class:`EarlyRuns`) that runs in the background: the
    workflow on ``workdir`` with ``args`` in a subprocess, in the environment of now (a
    test may change ``os.environ`` for a moment while it runs); returns ``workdir``. A
    session that ends first (``-x``, Ctrl-C) kills it rather than waiting for it."""
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


def _tiny_build(folder: Path) -> Callable[[], Path]:
    return in_background(make_workdir(folder, TINY), "dataset")


def _tiny_report(folder: Path) -> Callable[[], Path]:
    return in_background(make_workdir(folder, TINY_ENHANCE), "report")


# session fixtures whose builds start early (EarlyRuns) when a selected test uses them
EARLY_FIXTURES = {"tiny_build": _tiny_build, "tiny_report": _tiny_report}


def _early_or_now(name: str, tmp_path_factory) -> Path:
    if _EARLY is not None and name in _EARLY.names():
        return _EARLY.result(name)
    return EARLY_FIXTURES[name](tmp_path_factory.mktemp(name))()


@pytest.fixture(scope="session")
def tiny_build(tmp_path_factory) -> Path:
    """TINY built to the ``dataset`` target once per test session, shared by the test
    files that only read it (test_workflow, test_data, test_profiles): a test that
    changes a build works on a copy or a build of its own. Started early (EarlyRuns)."""
    return _early_or_now("tiny_build", tmp_path_factory)


@pytest.fixture(scope="session")
def tiny_report(tmp_path_factory) -> Path:
    """TINY_ENHANCE built to the ``report`` target once per test session, shared by
    test_workflow_enhance (which reads it) and test_train_resume (which copies it).
    Started early (EarlyRuns)."""
    return _early_or_now("tiny_report", tmp_path_factory)


class EarlyRuns:
    """The workflow runs of selected tests (a module's ``EARLY_RUNS``: test name -> a
    function of an empty folder), started at the session's start. Each function prepares
    its inputs there at once, in the main thread, and returns the rest: a function of no
    arguments that only runs subprocesses (:func:`in_background`) and returns what the test
    reads. Those run one after another in one background thread. A workflow run is mostly
    one job process at a time, so on 2 cores it overlaps with the other tests rather than
    waiting for its turn; the test then asserts on the result (:func:`early_run`). Nothing
    in-process runs in the background: tests monkeypatch the library (a frame reader
    counting its calls saw the frames an early run generated)."""

    def __init__(self, tmp_path_factory, runs: list[tuple[str, Callable[[Path], Callable[[], object]]]]):
        self._runs = [(name, self._prepared(fn, tmp_path_factory.mktemp(name[:40]))) for name, fn in runs]
        self._done: dict[str, tuple[bool, object]] = {}
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    @staticmethod
    def _prepared(fn: Callable[[Path], Callable[[], object]], folder: Path) -> Callable[[], object]:
        """``fn(folder)``, or a job that raises its error: a failed preparation fails its
        own test (:meth:`result`), not the session."""
        try:
            return fn(folder)
        except Exception as e:
            err = e

            def failed():
                raise err

            return failed

    def _run(self) -> None:
        for name, job in self._runs:
            try:
                out = (True, job())
            except BaseException as e:  # handed to the test, which raises it
                out = (False, e)
            with self._cond:
                self._done[name] = out
                self._cond.notify_all()

    def names(self) -> set[str]:
        return {name for name, _ in self._runs}

    def result(self, name: str, timeout: float = 1800):
        with self._cond:
            if not self._cond.wait_for(lambda: name in self._done, timeout=timeout):
                pytest.fail(f"the early run of {name} did not end within {timeout} s")
            ok, value = self._done[name]
        if not ok:
            raise value
        return value

    def stop(self) -> None:
        """Kills the runs still going (a session ended early: their tests will not read
        them) and waits for the thread."""
        _STOP.set()
        for proc in list(_LIVE):
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self._thread.join(timeout=60)


_EARLY: EarlyRuns | None = None


@pytest.fixture(scope="session", autouse=True)
def _started_early(request, tmp_path_factory):
    """At the session's start: a selected test module that defines
    ``start_early(tmp_path_factory)`` has it called (and the object it returns ``stop()``-ed
    at the end): test_slurm's runs spend most of their time waiting for the executor's
    job-state checks, so they start before every other test and overlap with them. And the
    ``EARLY_RUNS`` of the selected tests and the builds of the ``EARLY_FIXTURES`` they use
    start in :class:`EarlyRuns`, in the order the tests need them."""
    global _EARLY
    _STOP.clear()
    items = request.session.items
    modules = {getattr(item, "module", None) for item in items}  # doctests have none
    modules = sorted((m for m in modules if hasattr(m, "start_early")), key=lambda m: m.__name__)
    started = [m.start_early(tmp_path_factory) for m in modules]
    runs, seen = [], set()  # in the order the tests need them
    for item in items:
        wanted = [(f, EARLY_FIXTURES[f]) for f in EARLY_FIXTURES if f in getattr(item, "fixturenames", ())]
        fn = getattr(getattr(item, "module", None), "EARLY_RUNS", {}).get(getattr(item, "originalname", None))
        if fn is not None:
            wanted.append((item.originalname, fn))
        for name, fn in wanted:
            if name not in seen:
                seen.add(name)
                runs.append((name, fn))
    if runs:
        _EARLY = EarlyRuns(tmp_path_factory, runs)
        started.append(_EARLY)
    yield
    for s in started:
        s.stop()
    _EARLY = None


@pytest.fixture
def early_run(request, tmp_path):
    """What the test's entry in its module's ``EARLY_RUNS`` returned (:class:`EarlyRuns`),
    waited for; run here in ``tmp_path`` when it was not started early."""
    name = request.node.originalname
    if _EARLY is not None and name in _EARLY.names():
        return _EARLY.result(name)
    return request.module.EARLY_RUNS[name](tmp_path)()


@pytest.fixture(autouse=True)
def _torch_threads(request):
    """Torch's intra-op threads for each test: the module's ``TORCH_THREADS`` (default 2,
    the machine's cores). A module-level ``torch.set_num_threads`` would hold for the whole
    session from the last module collected; the modules whose in-process trainings ran
    several-fold slower with two threads beside other work (test_slurm's runs, a build) ask
    for one."""
    if "torch" in sys.modules:
        module = getattr(request.node, "module", None)  # a doctest has none
        sys.modules["torch"].set_num_threads(getattr(module, "TORCH_THREADS", 2))
    yield
