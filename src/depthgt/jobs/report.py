"""Entry points of the report jobs: evaluation of one method, the tables, the figures.

Each Snakemake script calls one of these with its rule's paths (every output path
explicitly) and the config sections of its stage (:data:`depthgt.settings.STAGES`);
nothing heavy (torch) is imported at module level.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from depthgt.device import keep_freed_memory, resolve_device
from depthgt.eval import figures
from depthgt.settings import stage_settings
from depthgt.status import Status

__all__ = ["run_evaluate", "run_tables", "run_figures"]

log = logging.getLogger("depthgt")


def run_evaluate(
    method: str,
    config: Mapping[str, Any],
    framesets: str,
    out_table: str,
    pred_dir: str,
    checkpoint: str | None = None,
    threads: int = 1,
    reference_tables: list[str] = (),
) -> None:
    """Run the registry method ``method`` on the ``evaluation.split`` frame sets and
    score it against depthgt's GT, where present the clean truth, and for real frames
    the references built apart (``neighbours``, ``tsdf``:
    :mod:`depthgt.gt.references`) (:func:`depthgt.eval.evaluate.evaluate_frames`).
    Writes the tidy long table ``out_table`` and the predictions under ``pred_dir``.

    Args:
        checkpoint: the trained model of a learned method.
        reference_tables: the real scenes' reference tables
            (:func:`depthgt.gt.references.scene_references`).
    """
    # heavy (torch): only this job needs them
    import torch

    from depthgt.eval.evaluate import evaluate_frames, method_spec
    from depthgt.gt.references import REFERENCES, read_reference_table

    keep_freed_memory()  # a process of its own: no page faults for each frame's tensors
    torch.set_num_threads(max(1, int(threads)))
    settings = stage_settings(config, "evaluate")
    spec = method_spec(method, checkpoint, device=str(resolve_device(settings.device)) if checkpoint else None)
    split = settings.evaluation.split
    table = evaluate_frames(
        framesets,
        {method: spec},
        references=("gt", "truth", *REFERENCES),
        split=split,
        pred_dirs={method: pred_dir},
        reference_files=read_reference_table(list(reference_tables)),
    )
    Path(pred_dir).mkdir(parents=True, exist_ok=True)
    Path(out_table).parent.mkdir(parents=True, exist_ok=True)
    table.to_parquet(out_table, index=False)
    log.info("evaluated %s on the %s frame sets: %d rows", method, split, len(table))


TABLES = ("table1", "table2", "table3", "table2_paired", "table3_paired", "quality")


def run_tables(
    eval_tables: list[str],
    framesets: str,
    rde_framesets: str,
    gt_quality: str,
    kinds: Mapping[str, str],
    outputs: Mapping[str, str],
) -> None:
    """Tables 1-3, the paired comparisons of Tables 2 and 3 and the GT-quality table as
    CSV + Markdown.

    Args:
        kinds: dataset -> source kind (Table 2: real sources, Table 3: synthetic).
        outputs: for each key of :data:`TABLES` the Markdown path under that key and the
            CSV path under ``{key}_csv``.
    """
    from depthgt.eval import tables  # heavy: the structure metrics import torch

    evals = [pd.read_parquet(p) for p in eval_tables]
    ev = pd.concat(evals, ignore_index=True) if evals else pd.DataFrame()
    rde = pd.read_parquet(rde_framesets)
    built = {
        "table1": (tables.table1(tables.gt_vs_input_long(pd.read_parquet(framesets), rde)), tables.TABLE1_CAPTION),
        "table2": (table2 := tables.table2(ev, kinds), tables.table2_caption(tables.references_in(table2))),
        "table3": (tables.table3(ev, kinds), tables.TABLE3_CAPTION),
        "table2_paired": (
            paired := tables.table2_paired(ev, kinds),
            tables.table2_caption(tables.references_in(paired), paired=True),
        ),
        "table3_paired": (tables.table3_paired(ev, kinds), tables.TABLE3_PAIRED_CAPTION),
        "quality": (
            tables.table_gt_quality(pd.read_csv(gt_quality), tables.rde_quality_long(rde)),
            tables.GT_QUALITY_CAPTION,
        ),
    }
    for key, (table, caption) in built.items():
        tables.write_table(table, outputs[f"{key}_csv"], outputs[key], caption)


def run_figures(
    framesets: str,
    pred_dirs: Mapping[str, str],
    loss_logs: Mapping[str, str],
    out_comparison: str,
    out_curves: Mapping[str, str],
    split: str = "test",
    frames_per_scene: int = 2,
) -> None:
    """The comparison figure (rows: up to ``frames_per_scene`` frames of each scene of
    ``split``; predictions read from ``pred_dirs``: method -> folder) and one
    training-curve plot per model (``out_curves``: model -> png)."""
    table = pd.read_parquet(framesets)
    table = table[(table["split"] == split) & (table["status"] == Status.OK) & (table["frameset"] != "")]
    figures.comparison_figure(table, pred_dirs, out_comparison, frames_per_scene)
    for name, path in loss_logs.items():
        figures.training_curve(path, out_curves[name], title=name)
