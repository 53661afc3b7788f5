"""CPU per frame set, per stage, of the frame-set job on real-format files.

    python3 bench/bench_pipeline.py                       # 7-Scenes fixture and TUM tuning frames, given / refine / fast
    python3 bench/bench_pipeline.py --data synthetic --modes given --framesets 8
    python3 bench/bench_pipeline.py --data 7scenes --modes given --selection window coverage --repeats 2

As a frame-set batch does it: the scene is wrapped in the batch's frame cache
(``depthgt.gt.cache.ResizedScene``: each frame read, checked and resized once), then
``depthgt.gt.build.process_frameset`` runs on consecutive targets, one torch thread (as
each job uses). Stages are those ``process_frameset`` records in ``poses.json``
(``cpu_s``: process CPU seconds): ``load_resize`` (decode, checks, resize; a frame is
decoded once per batch, so this is the batch's decode cost spread over its sets),
``align`` (registration: nothing for given poses), ``render`` (the GT), ``quality``
(leave-target-out render or errors against the truth), ``patches``, ``write``, and with
``--selection coverage`` ``coverage`` (the added views: candidates checked, selection,
their registration, the render with the core). The first frame set is left out of the
means (warm-up: imports, first allocations). ``--selection window coverage`` alternates
the two per (recording, mode), ``--repeats`` times.

Data: the 7-Scenes fixture (640x480 JPEG/PNG) and the TUM tuning frames (640x480 PNG) in
``../shared/data``, and the default synthetic scene (``--data synthetic``).

Side by side with another commit (issue 20's acceptance): ``--against DIR`` runs the same
frame sets with ``DIR/src`` (e.g. ``git worktree add /tmp/base b0fc1da``) in a second
process after each (recording, mode) of this checkout, and prints both totals and their
ratio. A checkout older than the per-stage timings reports its total only.

    python3 bench/bench_pipeline.py --modes given fast --against /tmp/base
    python3 bench/bench_pipeline.py --modes given fast --against /tmp/base --repeats 3   # alternating runs
    python3 bench/bench_pipeline.py --modes refine --selection coverage --against /tmp/base --repeats 2

On a shared machine the CPU time of the same work moves by +-5 % from minute to minute;
``--repeats`` alternates the two checkouts and prints the spread of the per-pair ratios.

Where a frame set's time goes, per function: ``--profile N`` runs cProfile over the
measured sets (not the warm-up) and prints, per (recording, mode), the N functions with
the most own time and the N depthgt functions with the most cumulative time, in ms per
frame set of cProfile's clock (the wall clock: profile on a quiet machine). cProfile adds
its own cost to every Python call (compiled kernels and C functions are one call each), so
the stage totals printed with it run high; time without it.

    python3 bench/bench_pipeline.py --data 7scenes tum --modes given --profile 25
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__" and "--src" in sys.argv:  # run another checkout's library (see --against)
    sys.path.insert(0, sys.argv[sys.argv.index("--src") + 1])

import pandas as pd
import torch
import yaml

from depthgt.errors import FrameError
from depthgt.gt.cache import ResizedScene
from depthgt.jobs.common import open_source_scene
from depthgt.settings import settings_from_config

try:
    from depthgt.gt.build import FrameSetOutputs, process_frameset
except ImportError:  # a checkout from before the gt.frameset -> gt.build rename
    from depthgt.gt.frameset import FrameSetOutputs, process_frameset

ROOT = Path(__file__).resolve().parents[1]
SHARED = next((p for p in (ROOT.parent / "shared", ROOT.parents[1] / "shared") if p.is_dir()), ROOT.parent / "shared")
MODES = {"given": {"method": "given"}, "refine": {"method": "refine"}, "fast": {"method": "overfit", "preset": "fast"}}


def sources(config: dict) -> dict[str, tuple[dict, str]]:
    default = config["sources"][0]
    return {
        "7scenes": (
            {"name": "7scenes", "kind": "sevenscenes", "root": str(SHARED / "data/7scenes-kitchen")},
            "7scenes-kitchen",
        ),
        "tum": ({"name": "tum", "kind": "tum", "root": str(SHARED / "data/tum-fr1-xyz-0-239")}, "."),
        "synthetic": (default, default["scenes"][0]),
    }


def run(
    source: dict,
    scene_name: str,
    mode: str,
    n: int,
    config: dict,
    selection: str | None = None,
    profiler: cProfile.Profile | None = None,
) -> pd.DataFrame:
    """The frame sets of ``n + 1`` consecutive targets, one row each (the first row is the
    warm-up); ``profiler`` runs over the sets after it."""
    if selection is not None:
        config = {**config, "frameset": {**config.get("frameset", {}), "selection": selection}}
    settings = settings_from_config({**config, "registration": MODES[mode], "sources": [source]})
    fs = settings.frameset
    need = getattr(settings.registration, "uses_source_poses", settings.registration.method == "given")
    span = max(fs.reach, fs.coverage_span) if selection == "coverage" else fs.reach  # as the batch job keeps them
    scene = ResizedScene(
        open_source_scene(source, scene_name, need_poses=need), settings.size_hw, keep=2 * span + 2, need_pose=need
    )
    rows = []
    try:  # the batch's per-frame cache (absent in older checkouts)
        from depthgt.framecache import FrameCache

        shared = {"cache": FrameCache(keep=2 * span + 2)}
    except ImportError:
        shared = {}
    with tempfile.TemporaryDirectory() as tmp:
        for t in range(fs.reach, min(len(scene) - fs.reach, fs.reach + n + 1)):  # consecutive targets, as a batch
            members = [t + o for o in fs.offsets]
            out = FrameSetOutputs.in_dir(Path(tmp) / f"{t:06d}")
            measured = profiler is not None and len(rows) > 0  # the first set run is the warm-up
            c0 = time.process_time()
            try:
                if measured:
                    profiler.enable()
                process_frameset(scene, source["name"], t, members, "train", out, settings, **shared)
            except FrameError as err:  # a frame without a pose etc.: the batch records it; here it is skipped
                print(f"{source['name']} target {t}: skipped ({err})")
                continue
            finally:
                if measured:
                    profiler.disable()
            total = time.process_time() - c0
            cpu = json.loads(out.poses.read_text()).get("cpu_s", {})  # per stage (absent in older checkouts)
            rows.append(
                dict(data=source["name"], mode=mode, selection=selection or "window", target=t, total=total, **cpu)
            )
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", nargs="+", default=["7scenes", "tum"], choices=["7scenes", "tum", "synthetic"])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--framesets", type=int, default=9, help="consecutive targets per recording (the first is warm-up)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (a frame-set job uses one)")
    ap.add_argument("--config", default=str(ROOT / "config/config.yaml"))
    ap.add_argument("--against", help="another checkout (its src/ is used) run on the same frame sets, side by side")
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="with --against: runs of both checkouts, alternating (this, other, this, ...), per (recording, mode)",
    )
    ap.add_argument(
        "--selection",
        nargs="+",
        default=None,
        choices=["window", "coverage"],
        help="frameset.selection, alternating per (recording, mode) and repeat (one value with --against)",
    )
    ap.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="cProfile the measured sets; print the N functions with the most own and cumulative time per set",
    )
    ap.add_argument("--src", help=argparse.SUPPRESS)  # internal: the library this process runs (see --against)
    ap.add_argument("--csv", help=argparse.SUPPRESS)  # internal: write the per-set rows here
    a = ap.parse_args(argv)
    if a.against and a.selection and len(a.selection) > 1:
        # the side by side compares each checkout's sets of one selection
        ap.error(f"--against takes one --selection (both checkouts run it), got {' '.join(a.selection)}")
    if a.profile < 0:
        ap.error(f"--profile takes the number of functions to print (0: no profile), got {a.profile}")
    if a.profile and a.against:
        ap.error("--profile does not go with --against: cProfile's own cost would enter one side only")
    torch.set_num_threads(a.threads)
    config = yaml.safe_load(Path(a.config).read_text())
    config["device"] = "cpu"
    import depthgt

    try:  # as the frame-set batch job does (absent in older checkouts)
        from depthgt.device import keep_freed_memory

        keep_freed_memory()
    except ImportError:
        pass
    frames, other, profiles = [], [], []
    for data in a.data:
        source, scene = sources(config)[data]
        for mode in a.modes:
            for rep in range(a.repeats if a.against or a.selection else 1):
                for selection in a.selection or [None]:
                    prof = cProfile.Profile() if a.profile else None
                    rows = run(source, scene, mode, a.framesets, config, selection, prof)
                    frames.append(rows.iloc[1:].assign(rep=rep))  # first: warm-up
                    if prof is not None:
                        profiles.append(((data, mode, selection or "window", rep), prof, len(rows) - 1))
                if a.against:  # the other checkout right after, on the same frames (same machine load)
                    other.append(_run_other(Path(a.against), data, mode, a).assign(rep=rep))
    df = pd.concat(frames)
    stages = [c for c in df.columns if c not in ("data", "mode", "selection", "target", "rep")]
    if a.csv:
        df.to_csv(a.csv, index=False)
        return
    print(f"command: python3 bench/bench_pipeline.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    print(f"library: {Path(depthgt.__file__).parent}")
    print(
        f"CPU seconds per frame set (process CPU, {a.threads} torch thread(s)), means over {a.framesets} sets after a warm-up"
    )
    print(df.groupby(["data", "mode", "selection"], sort=False)[stages].mean().to_markdown(floatfmt=".3f"))
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    for key, prof, n_sets in profiles:
        print(
            f"\nprofile of {key[:3]} (repeat {key[3]}), {n_sets} sets: wall ms per frame set, with cProfile's own cost"
        )
        print(profile_table(prof, n_sets, a.profile))
    if a.against:
        base = pd.concat(other)
        side = pd.DataFrame(
            {
                "this": df.groupby(["data", "mode"], sort=False)["total"].mean(),
                "against": base.groupby(["data", "mode"], sort=False)["total"].mean(),
            }
        )
        side["against / this"] = side["against"] / side["this"]
        if a.repeats > 1:  # the ratio of each alternating pair of runs: how much the machine's load moved it
            per = (
                base.groupby(["data", "mode", "rep"], sort=False)["total"].mean()
                / df.groupby(["data", "mode", "rep"], sort=False)["total"].mean()
            ).groupby(["data", "mode"], sort=False)
            side["ratio min"], side["ratio max"] = per.min(), per.max()
        print(
            f"side by side, total CPU per frame set: this checkout vs {a.against}/src "
            f"({a.repeats} alternating run(s) of each, {a.framesets} frame sets per run, "
            f"frameset.selection {a.selection[0] if a.selection else 'from the config'})"
        )
        print(side.to_markdown(floatfmt=".3f"))


def _in_package(path: str, package: Path) -> bool:
    """Whether a profiled file lies in the depthgt package at ``package`` (its folder), not
    merely under a folder of that name (a checkout is often called depthgt too)."""
    return path != "~" and Path(path).is_relative_to(package)


def _name(key: tuple[str, int, str], package: Path) -> str:
    """A profiled function's name: ``depthgt/path.py:line function`` within the package at
    ``package``, the file's name elsewhere, the interpreter's own name for built-ins."""
    path, line, func = key
    if path == "~":
        return func
    where = Path(path).relative_to(package.parent).as_posix() if _in_package(path, package) else Path(path).name
    return f"{where}:{line} {func}"


def profile_table(prof: cProfile.Profile, n_sets: int, top: int, package: Path | None = None) -> str:
    """The ``top`` functions of ``prof`` with the most own time, then the ``top`` functions
    of the depthgt package at ``package`` (default: the one imported) with the most
    cumulative time, as ms (and calls) per frame set over ``n_sets``."""
    import depthgt

    package = Path(depthgt.__file__).parent if package is None else Path(package)
    st = pstats.Stats(prof).stats  # (file, line, function) -> (primitive calls, calls, own s, cumulative s, callers)
    df = pd.DataFrame(
        [
            dict(
                function=_name(k, package),
                depthgt=_in_package(k[0], package),
                calls=v[1],
                own=v[2],
                cumulative=v[3],
            )
            for k, v in st.items()
        ]
    )
    per = n_sets if n_sets > 0 else 1
    df["calls"] = df["calls"] / per
    df[["own", "cumulative"]] = df[["own", "cumulative"]] * 1000.0 / per
    cols = ["function", "calls", "own", "cumulative"]
    own = df.nlargest(top, "own")[cols].rename(columns={"own": "own ms", "cumulative": "cumulative ms"})
    # comprehensions repeat their function's cumulative time: left out of the tree's view
    cum = df[df["depthgt"] & ~df["function"].str.contains(r" <(?:listcomp|genexpr|dictcomp|setcomp|lambda)>$")]
    cum = cum.nlargest(top, "cumulative")[cols]
    cum = cum.rename(columns={"own": "own ms", "cumulative": "cumulative ms"})
    return (
        f"most own time:\n{own.to_markdown(index=False, floatfmt='.1f')}\n"
        f"depthgt's functions, most cumulative time:\n{cum.to_markdown(index=False, floatfmt='.1f')}"
    )


def _run_other(checkout: Path, data: str, mode: str, a: argparse.Namespace) -> pd.DataFrame:
    """The same (recording, mode) with ``checkout/src`` and its own default config, in a fresh process; its rows."""
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "rows.csv"
        cmd = [
            sys.executable,
            __file__,
            "--src",
            str(checkout / "src"),
            "--data",
            data,
            "--modes",
            mode,
            "--framesets",
            str(a.framesets),
            "--threads",
            str(a.threads),
            "--config",
            str(checkout / "config/config.yaml"),
            "--csv",
            str(csv),
            *(["--selection", *a.selection] if a.selection else []),
        ]
        env = {**os.environ, "PYTHONPATH": str(checkout / "src")}
        subprocess.run(cmd, check=True, env=env, cwd=str(checkout))
        return pd.read_csv(csv)


if __name__ == "__main__":
    main()
