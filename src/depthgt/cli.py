"""The ``depthgt`` command: the jobs people do by hand, over the Snakemake workflow.

    depthgt build [TARGET ...]        run the workflow (default target: everything)
    depthgt rebuild DATASET SCENE     build one scene's frame sets again
    depthgt show DATASET SCENE TARGET statistics of one frame set and a PNG panel
    depthgt extract DATASET SCENE TARGET DEST   one frame set's files into a folder
    depthgt export DEST [--format png16|exr]    the dataset as plain files (PNG/EXR + index)
    depthgt evaluate PRED_DIR         score a folder of predictions of the test frames (Tables 2/3)
    depthgt verify [DIR]              check a built dataset or an export against its card
    depthgt report [--out FILE]       an HTML page of the build (summary, frame sets to look at, tables)
    depthgt bench NAME [ARGS ...]     one of the benchmarks in bench/

Snakemake runs in a child process (``python -m snakemake``) rather than through its
Python API: the API changes between Snakemake majors while the command line is stable,
and a child keeps Snakemake's global state (logging, locks, signal handlers) out of
this process. Every subcommand works on a working directory (``-d``, default: the
current one) that holds ``config/config.yaml`` and gets ``results/``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from depthgt import buildconfig, runlock
from depthgt.errors import DepthGTError
from depthgt.gt import store
from depthgt.gt.settings import SPLITS

__all__ = ["main", "repo_root", "snakemake_command", "scene_outputs"]


def panel_formats() -> set[str]:
    """The file suffixes matplotlib writes here (``depthgt show --out``)."""
    from matplotlib.figure import Figure

    return set(Figure().canvas.get_supported_filetypes())


def repo_root() -> Path:
    """The checkout holding the Snakefile and bench/ (the package is installed from it
    in editable mode: src/depthgt/cli.py -> the repository root)."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "Snakefile").is_file():
        raise DepthGTError(
            f"no Snakefile at {root}: depthgt's command needs the checkout it was installed from "
            "(pip install -e <checkout>); pass --snakefile to name the workflow"
        )
    return root


def _snakefile(args: argparse.Namespace) -> Path:
    return Path(args.snakefile).absolute() if args.snakefile else repo_root() / "Snakefile"


def snakemake_command(args: argparse.Namespace, *extra: str) -> list[str]:
    """``python -m snakemake`` with the workflow, working directory and shared options."""
    cmd = [sys.executable, "-m", "snakemake", "-s", str(_snakefile(args)), "-d", str(Path(args.directory).resolve())]
    if getattr(args, "cores", None) is not None:
        cmd += ["--cores", str(args.cores)]
    if getattr(args, "profile", None):
        cmd += ["--profile", args.profile]
    cmd += list(extra)
    # --configfile takes several values in Snakemake: it goes last, after the targets
    if getattr(args, "configfile", None):
        cmd += ["--configfile", *[str(Path(c).resolve()) for c in args.configfile]]
    return cmd


def build_config(args: argparse.Namespace, check_sources: bool = True) -> buildconfig.Layers:
    """The config the command runs with in its working directory (the base, the build's
    remembered --configfile layer, this command's --configfile files;
    :mod:`depthgt.buildconfig`), checked before Snakemake starts: a file that does not
    parse or holds no config key, a missing source root, or a --configfile that changes
    keys of an existing build without --reconfigure (``depthgt report``: at all) are
    refused in one line."""
    from depthgt.settings import TOP_LEVEL_KEYS  # torch-free

    layers = buildconfig.layered_config(
        Path(args.directory).resolve(),
        _snakefile(args).parent / "config" / "config.yaml",
        [Path(c) for c in getattr(args, "configfile", None) or []],
        reconfigure=bool(getattr(args, "reconfigure", False)),
        check_sources=check_sources,
        config_keys=TOP_LEVEL_KEYS,
        command="report" if getattr(args, "command", None) == "report" else "build",
    )
    if getattr(args, "reconfigure", False):
        os.environ[buildconfig.RECONFIGURE_ENV] = "1"  # the child Snakemake applies the change too
    return layers


def _run(cmd: Sequence[str], capture: bool = False) -> subprocess.CompletedProcess:
    print("+ " + " ".join(cmd), file=sys.stderr)
    proc = subprocess.run(list(cmd), text=True, capture_output=capture)
    if proc.returncode != 0:
        if capture:
            sys.stderr.write(proc.stdout[-4000:] + proc.stderr[-4000:])
        raise SystemExit(proc.returncode)
    return proc


def scene_outputs(summary: str, dataset: str, scene: str) -> list[str]:
    """The files of one scene in the text of ``snakemake --summary``: every output whose
    path has ``<dataset>/<scene>`` as two consecutive folders (frame sets, summaries, RDE).

    >>> s = "output_file\\tdate\\nresults/scenes/a/r0/framesets.parquet\\t-\\nresults/scenes/a/r1/x\\t-\\n"
    >>> scene_outputs(s, "a", "r0")
    ['results/scenes/a/r0/framesets.parquet']
    """
    out = []
    for line in summary.splitlines()[1:]:
        path = line.split("\t", 1)[0].strip()
        parts = Path(path).parts
        if any(parts[i : i + 2] == (dataset, scene) for i in range(len(parts) - 1)):
            out.append(path)
    return out


def check_targets(args: argparse.Namespace) -> None:
    """Refuse a target that is a config file: ``depthgt build --configfile a.yaml
    b.yaml`` (depthgt's --configfile takes one file, Snakemake's several) would make
    b.yaml a target, which no rule builds, and leave it out of the config. A target
    ending in .yaml/.yml that names an existing file (from the current folder or the
    working directory) outside the build's results/ and holds a mapping is one.

    Raises:
        DepthGTError: naming the target and the command line meant.
    """
    wd = Path(args.directory).resolve()
    for target in getattr(args, "targets", None) or []:
        if Path(target).suffix.lower() not in (".yaml", ".yml"):
            continue
        for path in dict.fromkeys((Path(target).expanduser().absolute(), wd / target)):
            if not path.is_file() or path.resolve().is_relative_to(wd / "results"):
                continue  # the workflow's outputs are all under results/
            try:
                buildconfig.load_config_file(path)
            except DepthGTError:
                continue  # not a config: Snakemake names a target no rule builds
            files = [*(getattr(args, "configfile", None) or []), target]
            raise DepthGTError(
                f"target {target} is a config file ({path}), not an output of the workflow: depthgt's --configfile "
                "takes one file, repeat it for several ("
                + " ".join(f"--configfile {f}" for f in files)
                + "); targets are rules or files under results/"
            )


def _check_not_running(args: argparse.Namespace) -> None:
    """Refuse at once when a live run holds the working directory (depthgt.runlock; the
    workflow itself takes the lock when its jobs start)."""
    if not args.dry_run:
        runlock.check(args.directory)


def _cmd_build(args: argparse.Namespace) -> int:
    check_targets(args)
    _check_not_running(args)
    layers = build_config(args)
    extra = list(args.targets)
    if args.dry_run:
        extra.append("-n")
    _run(snakemake_command(args, *extra))
    if not args.dry_run:  # also when Snakemake had nothing to do (it then calls no onstart)
        buildconfig.remember(Path(args.directory).resolve(), layers)
    return 0


def _cmd_rebuild(args: argparse.Namespace) -> int:
    _check_not_running(args)
    layers = build_config(args)
    target = f"results/scenes/{args.dataset}/{args.scene}/framesets.parquet"
    # the scene's own jobs, read from the plan of all frame sets rather than hard-coded,
    # so that this follows the layout of the frame-set stage and accepts only scenes the
    # config lists; shared jobs (a pretrained encoder) are not forced
    summary = _run(snakemake_command(args, "framesets", "--summary"), capture=True).stdout
    files = scene_outputs(summary, args.dataset, args.scene)
    if not files:
        raise DepthGTError(
            f"scene {args.dataset}/{args.scene} is not in the plan: the config's `sources` "
            f"have no source {args.dataset!r} listing scene {args.scene!r}"
        )
    extra = [target, "--forcerun", *files]
    if args.dry_run:
        extra.append("-n")
    _run(snakemake_command(args, *extra))
    if not args.dry_run:
        buildconfig.remember(Path(args.directory).resolve(), layers)
    return 0


def _results(args: argparse.Namespace) -> Path:
    """The build's results folder; a working directory without one is named as such."""
    results = Path(args.directory) / "results"
    if not (results / "framesets").is_dir():
        raise DepthGTError(f"{Path(args.directory)} holds no build ({results / 'framesets'} is missing): check -d")
    return results


def _read(args: argparse.Namespace) -> store.FrameSetRecord:
    return store.read_frameset(_results(args), args.dataset, args.scene, args.target)


def frameset_statistics(rec: store.FrameSetRecord) -> dict[str, Any]:
    """The numbers of one frame set for a person: its status and split, then every
    statistic its ``frameset.json`` records, under the same names (units in the names
    and in the record's ``units``); nested tables are flattened, e.g.
    ``gt_vs_truth.mae_m`` (the GT against the truth, where the truth is known)."""
    stats: dict[str, Any] = {"status": str(rec.meta.get("status", "?")), "split": str(rec.meta.get("split", "?"))}
    for key, value in rec.meta.get("statistics", {}).items():
        if isinstance(value, dict):
            stats.update({f"{key}.{name}": v for name, v in value.items()})
        else:
            stats[key] = value
    return stats


def _cmd_show(args: argparse.Namespace) -> int:
    from depthgt.eval.figures import frameset_panel  # pandas, matplotlib: only for the panel

    rec = _read(args)
    stats = frameset_statistics(rec)
    width = max(map(len, stats))
    for key, value in stats.items():
        print(f"{key:{width}s} {value:.4f}" if isinstance(value, float) else f"{key:{width}s} {value}")
    out = Path(args.out or f"{args.dataset}_{args.scene}_{args.target:06d}.png")
    formats = panel_formats()
    if out.suffix.lower().lstrip(".") not in formats:
        raise DepthGTError(f"--out {out}: the panel is written as one of {', '.join(sorted(formats))}")
    frameset_panel(rec, out, title=f"{args.dataset}/{args.scene}/{args.target:06d}")
    print(f"panel: {out}")
    return 0


def _cmd_extract(args: argparse.Namespace) -> int:
    from depthgt.gt.extract import extract_plain, planned_files

    results = _results(args)
    dest = Path(args.dest).absolute()
    names = store.FRAMESET_FILES if args.raw else planned_files(args.format)
    present = [n for n in names if (dest / n).exists()]
    if present and not args.force:
        raise DepthGTError(f"{dest} already holds {', '.join(present)}: pick another folder or pass --force")
    if args.raw:
        written = store.extract_frameset(results, args.dataset, args.scene, args.target, dest)
    else:
        written = extract_plain(results, args.dataset, args.scene, args.target, dest, fmt=args.format)
    for p in written:
        print(p)
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from depthgt.data import export_dataset  # torch: only for this command

    results = Path(args.directory) / "results"
    index = export_dataset(
        results,
        args.dest,
        fmt=args.format,
        splits=args.split or list(SPLITS),
        kind=args.kind,
        workers=args.workers,
    )
    print(f"{len(index)} {args.kind} exported to {args.dest} (index.parquet, index.csv, SHA256SUMS, card.json)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import pandas as pd  # pandas and torch: only for this command

    from depthgt.eval import predictions

    pred_dir = Path(args.pred_dir)
    if not pred_dir.is_dir():
        raise DepthGTError(f"no prediction folder {pred_dir}")
    name = args.name or pred_dir.resolve().name
    if args.export:
        frames = predictions.frames_from_export(args.export)
    else:
        frames = predictions.frames_from_results(args.directory)
    compare = []
    if args.compare:
        evals = sorted((Path(args.directory) / "results" / "eval").glob("*.parquet"))
        if not evals:
            raise DepthGTError(
                f"--compare: no evaluation tables in {Path(args.directory) / 'results' / 'eval'} "
                "(run `depthgt build tables` first)"
            )
        compare = [pd.read_parquet(p) for p in evals]
    out = Path(args.out) if args.out else Path(args.directory) / f"evaluate-{name}"
    written = predictions.evaluate_folder(pred_dir, out, frames, method=name, compare=compare, progress=True)
    for key, path in written.items():
        print(f"{key}: {path}")
    return 0


def _cmd_verify(args: argparse.Namespace) -> int:
    from depthgt.gt.card import verify

    report = verify(args.folder or args.directory)
    for problem in report.problems:
        print(f"FAILED {problem}")
    print(
        f"{report.folder} ({report.kind}): {report.checked} files checked, "
        + ("all match the card" if report.ok else f"{len(report.problems)} problem(s)")
    )
    return 0 if report.ok else 1


def _cmd_report(args: argparse.Namespace) -> int:
    from depthgt.eval.report import write_report  # pandas, matplotlib: only for the report

    wd = Path(args.directory).resolve()
    if not (wd / "results" / "framesets").is_dir():  # before anything is written there
        raise DepthGTError(
            f"{wd} holds no build ({wd / 'results' / 'framesets'} is missing): check -d, or run `depthgt build`"
        )
    layers = build_config(args, check_sources=False)  # the report reads results/ only
    out = Path(args.out).resolve() if args.out else wd / "report.html"
    source = f"{layers.base}" + (
        f" with {wd / buildconfig.OVERRIDES}" if (wd / buildconfig.OVERRIDES).is_file() else ""
    )
    print(f"report: {write_report(wd, out, layers.config, config_source=source)}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    bench = repo_root() / "bench"
    names = sorted(p.stem for p in bench.glob("*.py"))
    if args.name not in names:
        raise DepthGTError(f"no benchmark {args.name!r} in {bench}; there are: {', '.join(names)}")
    proc = subprocess.run(
        [sys.executable, str(bench / f"{args.name}.py"), *args.args], env=dict(os.environ, PYTHONUNBUFFERED="1")
    )
    return proc.returncode


class _Parser(argparse.ArgumentParser):
    """argparse's parser; an argument left over is explained: every option takes one value."""

    def error(self, message: str):
        if message.startswith("unrecognized arguments"):
            message += (
                " (each option takes one value: repeat --configfile or --split for several, "
                "e.g. --split train --split test)"
            )
        super().error(message)


def _parser() -> argparse.ArgumentParser:
    """The command line: one sub-parser per command (long because argparse declares each
    command and each of its options with a call of its own, one entry of the help each)."""
    p = _Parser(
        prog="depthgt", description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-d",
        "--directory",
        default=".",
        help="working directory: gets results/ and remembers the config its first build ran with "
        f"({buildconfig.OVERRIDES}, {buildconfig.REMEMBERED}); its config/config.yaml, when present, "
        "replaces the embedded default; relative source roots there are relative to it (default: .)",
    )
    common.add_argument("--snakefile", help="the workflow (default: the Snakefile of depthgt's checkout)")
    cfg = argparse.ArgumentParser(add_help=False)
    cfg.add_argument(
        "--configfile",
        action="append",
        metavar="FILE",
        help="a config file over the working directory's config, remembered by the build (repeat the option "
        "for several; a relative source root in it is relative to its folder)",
    )
    run = argparse.ArgumentParser(add_help=False)
    run.add_argument("--cores", type=int, help="cores for Snakemake (default: the profile's)")
    run.add_argument("--profile", help="a Snakemake profile (e.g. profiles/slurm)")
    run.add_argument(
        "--reconfigure",
        action="store_true",
        help="apply a --configfile that changes keys of an existing build (otherwise refused, naming them)",
    )
    run.add_argument("-n", "--dry-run", action="store_true", help="show the jobs, run none")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    b = sub.add_parser(
        "build",
        parents=[common, cfg, run],
        help="run the workflow",
        description="Run the workflow on the working directory's config.",
    )
    b.add_argument("targets", nargs="*", help="targets (rules or files; default: all)")
    b.set_defaults(func=_cmd_build)

    r = sub.add_parser(
        "rebuild",
        parents=[common, cfg, run],
        help="build one scene again",
        description="Force one scene's jobs (frame sets, summaries) to run again.",
    )
    r.add_argument("dataset", help="a source name of the config")
    r.add_argument("scene", help="a scene of that source")
    r.set_defaults(func=_cmd_rebuild)

    fs = argparse.ArgumentParser(add_help=False)
    fs.add_argument("dataset")
    fs.add_argument("scene")
    fs.add_argument("target", type=int, help="the target frame's index")

    s = sub.add_parser(
        "show",
        parents=[common, fs],
        help="statistics and a PNG panel of one frame set",
        description="Print one built frame set's statistics and write a panel RGB | input | GT | confidence (| truth).",
    )
    s.add_argument("--out", help="PNG path (default: DATASET_SCENE_TARGET.png)")
    s.set_defaults(func=_cmd_show)

    e = sub.add_parser(
        "extract",
        parents=[common, fs],
        help="one frame set's files into a folder, readable by any tool",
        description="Write one built frame set into DEST as files other tools read: the GT depth, its "
        "expected standard deviation (confidence), the input depth and, for synthetic sources, the truth as "
        "float32 EXR in metres (channel Y; gt_depth_m.exr, ...) and/or 16-bit PNG in millimetres "
        "(gt_depth_mm.png; the deviation in 0.1 mm, gt_sigma_100um.png), 0 = no value; rgb.png; poses.json, "
        "patches.npz, frameset.json; units.json describing every file. --raw: the shard's members as stored "
        "(gt.exr in depthgt's fixed point, rgb.webp, ...), for depthgt's own readers.",
    )
    e.add_argument("dest")
    e.add_argument(
        "--format",
        choices=["exr", "png16", "both"],
        default="both",
        help="depth files: float32 EXR in metres, 16-bit PNG in mm, or both (default: both)",
    )
    e.add_argument("--raw", action="store_true", help="the shard's members as stored, not converted")
    e.add_argument("--force", action="store_true", help="overwrite those files where DEST holds them")
    e.set_defaults(func=_cmd_extract)

    x = sub.add_parser(
        "export",
        parents=[common],
        help="the dataset as plain files (PNG/EXR + index)",
        description="Write the built dataset to DEST as plain files: 16-bit PNG depth in millimetres "
        "(or float32 EXR in metres), RGB PNG, index.parquet/index.csv listing every "
        "sample, SHA256SUMS and the dataset card. Resumes an unfinished export.",
    )
    x.add_argument("dest", help="the export folder")
    x.add_argument("--format", choices=["png16", "exr"], default="png16", help="depth files (default: png16)")
    x.add_argument(
        "--split",
        action="append",
        choices=SPLITS,
        help="a split to export (repeat the option for several; default: all)",
    )
    x.add_argument(
        "--kind",
        choices=["patches", "frames"],
        default="patches",
        help="patch pairs or whole frames (default: patches)",
    )
    x.add_argument("--workers", type=int, default=0, help="processes reading the shards (default: 0, this one)")
    x.set_defaults(func=_cmd_export)

    ev = sub.add_parser(
        "evaluate",
        parents=[common],
        help="score a folder of predictions of the test frames",
        description="Score a folder of depth predictions of the test split with the tables' masks, "
        "metrics and bootstrap intervals, and write Tables 2/3 (CSV + Markdown) and the "
        "long per-frame table. PRED_DIR/{dataset}/{scene}/{target:06d}.png (16-bit, mm) "
        "or .exr (float32 m, channel Y), named like the test split of "
        "`depthgt export --kind frames`. References: the build in -d, or --export.",
    )
    ev.add_argument("pred_dir", help="the folder of predictions")
    ev.add_argument(
        "--export",
        help="read the references from this export (--kind frames, with the test split) "
        "instead of the build in -d; an exr export holds the build's exact images",
    )
    ev.add_argument("--name", help="the predictions' name in the tables (default: PRED_DIR's folder name)")
    ev.add_argument(
        "--compare",
        action="store_true",
        help="put the build's methods (results/eval/*.parquet in -d) beside the predictions and write "
        "the paired tables: the predictions minus every method, per frame",
    )
    ev.add_argument("--out", help="folder of the tables (default: evaluate-NAME in -d)")
    ev.set_defaults(func=_cmd_evaluate)

    v = sub.add_parser(
        "verify",
        parents=[common],
        help="check a dataset or an export against its card",
        description="Check every shard and manifest of a built dataset (or every file of an export) "
        "against the checksums of its dataset card; exit status 1 naming each file "
        "that differs.",
    )
    v.add_argument("folder", nargs="?", help="working directory, results folder or export (default: -d)")
    v.set_defaults(func=_cmd_verify)

    rep = sub.add_parser(
        "report",
        parents=[common, cfg],
        help="an HTML page of the build: summary, GT quality, frame sets to look at first, tables, figures",
        description="Write one self-contained HTML page of whatever the build holds: the dataset's summary, the "
        "GT-quality table, per source the frame sets to look at first (worst leave-target-out error, lowest "
        "completeness, most neighbours left out) as panels with the commands that show, extract or rebuild "
        "them, and the tables, figures and training curves when the build has them. (Snakemake's own report "
        "of a finished build: python3 -m snakemake --report report.html.)",
    )
    rep.add_argument("--out", help="HTML file (default: report.html in the working directory)")
    rep.set_defaults(func=_cmd_report)

    be = sub.add_parser(
        "bench", help="run a benchmark of bench/", description="Run bench/NAME.py with ARGS (see bench/README.md)."
    )
    be.add_argument("name", help="the benchmark, e.g. bench_render")
    be.add_argument("args", nargs=argparse.REMAINDER, help="its arguments")
    be.set_defaults(func=_cmd_bench)
    return p


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line, options and positionals in any order (``depthgt export DEST
    --split test -d wd`` and ``depthgt export -d wd --split test DEST`` alike): the
    subcommand's arguments are parsed intermixed (argparse cannot do that across
    subparsers), every list option takes one value per flag."""
    parser = _parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    if argv and argv[0] in sub.choices and argv[0] != "bench":  # bench passes the rest on as it is
        args = sub.choices[argv[0]].parse_intermixed_args(argv[1:])
        args.command = argv[0]
        return args
    return parser.parse_args(argv)


def _absolute_paths(args: argparse.Namespace) -> None:
    """Every path argument made absolute (not resolved: links kept), so that each message
    names the folder or file it means whatever the current directory."""
    for name in ("directory", "dest", "out", "pred_dir", "export", "folder", "snakefile"):
        value = getattr(args, name, None)
        if isinstance(value, str) and value:
            setattr(args, name, str(Path(value).expanduser().absolute()))


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.command != "bench":
        _absolute_paths(args)
    try:
        if args.command != "bench" and not args.snakefile:
            # the checkout the rules' conda environment installs (workflow/envs/depthgt.yaml)
            os.environ.setdefault("DEPTHGT_REPO", str(repo_root()))
        return int(args.func(args) or 0)
    except DepthGTError as exc:
        print(f"depthgt: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a destination that is a file, unwritable, on a full disk: its path is in the message
        print(f"depthgt: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
