"""The ``depthgt`` command: the jobs people do by hand, over the Snakemake workflow.

    depthgt build [TARGET ...]        run the workflow (default target: everything)
    depthgt rebuild DATASET SCENE     build one scene's frame sets again
    depthgt show DATASET SCENE TARGET statistics of one frame set and a PNG panel
    depthgt extract DATASET SCENE TARGET DEST   one frame set's files into a folder
    depthgt export DEST [--format png16|exr]    the dataset as plain files (PNG/EXR + index)
    depthgt evaluate PRED_DIR         score a folder of predictions of the test frames (Tables 2/3)
    depthgt verify [DIR]              check a built dataset or an export against its card
    depthgt report [--out FILE]       Snakemake's HTML report (tables and figures)
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

from depthgt import runlock
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


def snakemake_command(args: argparse.Namespace, *extra: str) -> list[str]:
    """``python -m snakemake`` with the workflow, working directory and shared options."""
    snakefile = Path(args.snakefile) if args.snakefile else repo_root() / "Snakefile"
    cmd = [sys.executable, "-m", "snakemake", "-s", str(snakefile), "-d", str(Path(args.directory).resolve())]
    if getattr(args, "cores", None) is not None:
        cmd += ["--cores", str(args.cores)]
    if getattr(args, "profile", None):
        cmd += ["--profile", args.profile]
    cmd += list(extra)
    # --configfile takes several values: it goes last, after the targets (Snakemake 9)
    if getattr(args, "configfile", None):
        _check_yaml_files([Path(c) for c in args.configfile])
        cmd += ["--configfile", *[str(Path(c).resolve()) for c in args.configfile]]
    return cmd


def _check_yaml_files(paths: Sequence[Path]) -> None:
    """Each config file exists and parses, named with its line (Snakemake's own message
    names neither the file nor the line); the settings are checked by the workflow."""
    import json

    import yaml

    for path in paths:
        if not path.is_file():
            raise DepthGTError(f"--configfile {path}: file not found")
        try:  # as Snakemake reads it: JSON first, then YAML (FullLoader), UTF-8
            text = path.read_text(encoding="utf-8")
            try:
                doc = json.loads(text)
            except json.JSONDecodeError:
                doc = yaml.load(text, Loader=yaml.FullLoader)
        except (UnicodeDecodeError, yaml.YAMLError) as err:
            mark = getattr(err, "problem_mark", None)
            where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
            problem = getattr(err, "problem", None) or str(err)
            raise DepthGTError(f"--configfile {where}: not valid YAML ({problem})") from None
        if doc is not None and not isinstance(doc, dict):
            raise DepthGTError(f"--configfile {path}: must hold a mapping of config keys, got {type(doc).__name__}")


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


def _check_not_running(args: argparse.Namespace) -> None:
    """Refuse at once when a live run holds the working directory (depthgt.runlock; the
    workflow itself takes the lock when its jobs start)."""
    if not args.dry_run:
        runlock.check(args.directory)


def _cmd_build(args: argparse.Namespace) -> int:
    _check_not_running(args)
    extra = list(args.targets)
    if args.dry_run:
        extra.append("-n")
    _run(snakemake_command(args, *extra))
    return 0


def _cmd_rebuild(args: argparse.Namespace) -> int:
    _check_not_running(args)
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
    results = _results(args)
    present = [n for n in store.FRAMESET_FILES if (Path(args.dest) / n).exists()]
    if present and not args.force:
        raise DepthGTError(f"{args.dest} already holds {', '.join(present)}: pick another folder or pass --force")
    for p in store.extract_frameset(results, args.dataset, args.scene, args.target, args.dest):
        print(p)
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from depthgt.data import export_dataset  # torch: only for this command

    results = Path(args.directory) / "results"
    index = export_dataset(results, args.dest, fmt=args.format, splits=args.split, kind=args.kind, workers=args.workers)
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
    # Snakemake's report needs every file marked for it: say what to run instead of
    # Snakemake's "marked for report but does not exist"
    if not (Path(args.directory) / "results").is_dir():  # before Snakemake creates .snakemake/ there
        raise DepthGTError(
            f"{Path(args.directory).resolve()} holds no build (no results/): check -d, or run `depthgt build`"
        )
    plan = subprocess.run(snakemake_command(args, "-n", "--quiet", "all"), capture_output=True, text=True)
    if plan.returncode != 0 or "Nothing to be done" not in plan.stdout + plan.stderr:
        raise DepthGTError(
            f"the build in {Path(args.directory).resolve()} is not finished (or its config fails): "
            "run `depthgt build` first, then `depthgt report`"
        )
    _run(snakemake_command(args, "--report", str(Path(args.out).resolve())))
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


def _parser() -> argparse.ArgumentParser:
    """The command line: one sub-parser per command (long because argparse declares each
    command and each of its options with a call of its own, one entry of the help each)."""
    p = argparse.ArgumentParser(
        prog="depthgt", description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-d", "--directory", default=".", help="working directory with config/config.yaml and results/ (default: .)"
    )
    common.add_argument("--snakefile", help="the workflow (default: the Snakefile of depthgt's checkout)")
    run = argparse.ArgumentParser(add_help=False)
    run.add_argument("--cores", type=int, help="cores for Snakemake (default: the profile's)")
    run.add_argument("--profile", help="a Snakemake profile (e.g. profiles/slurm)")
    run.add_argument("--configfile", nargs="+", help="config files over config/config.yaml")
    run.add_argument("-n", "--dry-run", action="store_true", help="show the jobs, run none")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    b = sub.add_parser(
        "build",
        parents=[common, run],
        help="run the workflow",
        description="Run the workflow on the working directory's config.",
    )
    b.add_argument("targets", nargs="*", help="targets (rules or files; default: all)")
    b.set_defaults(func=_cmd_build)

    r = sub.add_parser(
        "rebuild",
        parents=[common, run],
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
        help="one frame set's files into a folder",
        description="Write one built frame set's files (gt.exr, input.exr, rgb.webp, poses.json, "
        "patches.npz, frameset.json) into DEST.",
    )
    e.add_argument("dest")
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
        nargs="+",
        choices=SPLITS,
        default=list(SPLITS),
        help="splits to export (default: all)",
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
        parents=[common],
        help="Snakemake's HTML report",
        description="Write Snakemake's report (tables, figures) of a finished build.",
    )
    rep.add_argument("--out", default="report.html", help="HTML file (default: report.html)")
    rep.set_defaults(func=_cmd_report)

    be = sub.add_parser(
        "bench", help="run a benchmark of bench/", description="Run bench/NAME.py with ARGS (see bench/README.md)."
    )
    be.add_argument("name", help="the benchmark, e.g. bench_render")
    be.add_argument("args", nargs=argparse.REMAINDER, help="its arguments")
    be.set_defaults(func=_cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
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
