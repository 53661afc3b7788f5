"""The GT on real Kinect recordings: the real-data tuning protocol.

Real recordings have no clean depth; what they can measure (per pose mode):

* ``kept``: neighbours the renderer fuses (of 6 per frame set): not failed by the
  registration's checks and not left out whole by the frame-agreement check;
* ``kept_px``: share of the neighbours' samples next to the target's own that the
  renderer keeps (a neighbour may be kept in part: ``render.agreement_tiles``);
* ``gt_completeness`` against the input's (``input_completeness``), 256x256;
* ``lto_mae_mm``: leave-target-out MAE, the neighbours fused alone against the target's
  raw valid depth (where both have depth), as the workflow's ``leave_target_out``;
* ``lto_edge_mm`` / ``lto_flat_mm`` / ``lto_edge_gross``: that error split by whether a
  depth edge or hole of the target lies within 2 px (inverse depth range in the 5x5 window
  beyond 2 % of it plus 0.01 /m), and the share of the edge pixels off by more than 30 cm;
* ``patches_kept``: patch pairs of the frame set kept by the 5 %-missing filter (drawn as
  the workflow draws them, seed 0), of 6;
* with ``--selection coverage`` (``frameset.selection``, :mod:`depthgt.gt.coverage`):
  ``added`` views per frame set, ``lto_all_mae_mm`` the leave-target-out MAE of the core
  and the added views fused together (``lto_mae_mm`` stays the core's; the core's own
  where no view was fused), ``lto_all_minus_core_mm`` their difference per frame set with
  its 95 % bootstrap interval over the frame sets (``_lo``, ``_hi``), ``lto_added_mae_mm``
  that check where the core's neighbours alone have no depth (the added views' own
  accuracy, ``lto_added_px`` such pixels per frame set) and
  ``cov_cpu_s`` the CPU seconds of the coverage step (candidates read through a frame
  cache as a batch job does, selection, the added views' registration, the render);
* ``--ceiling``: in place of the above, the most completeness any choice of views could
  give (:func:`ceiling`): the share of the target's 256x256 pixels that its own valid
  depth or a valid sample of some other frame (reference poses, nearest pixel, in front)
  reaches, with the frames of the core window, of +-``coverage_span`` and of the whole
  recording; ``_d1``: also counting pixels within 1 px of such a sample (a generous bound);
* ``added_rot_deg`` / ``added_trans_cm`` (coverage): the fused added views' poses against
  the reference poses, median and 90th percentile over the views;
* ``reg_rot_deg`` / ``reg_trans_cm``: the mode's poses against the reference poses (the
  recording's own: motion capture for TUM, KinectFusion for 7-Scenes), median and 90th
  percentile over the neighbours;
* where frames disagree: the share of compared samples that disagree with the target, in
  the image's centre, middle ring and border (by distance from the image centre, as a
  fraction of the half-diagonal: < 0.4, 0.4-0.7, > 0.7).

Data (tests and tuning only; never copied into the repository):

* ``tum``: ``../shared/data/tum-fr1-xyz-0-239`` (240 frames of TUM fr1/xyz, motion-capture
  poses, colour and depth not synchronised), targets every ``--tum-step`` frames;
* ``7scenes``: ``../shared/data/7scenes-kitchen`` (60 frames, KinectFusion poses), targets
  every ``--7scenes-step`` frames.

Both are TUNING data: defaults chosen by looking at these numbers are reported on other
recordings (later frames of fr1/xyz, other sequences) and on the synthetic evaluation set
of ``bench_gt_protocol.py``.

Usage::

    python3 bench/bench_real.py                              # both recordings, modes given, refine, fast
    python3 bench/bench_real.py --data tum --modes given --tum-option camera=ros_default
    python3 bench/bench_real.py --data tum --set min_frame_agreement=0.9 --modes given
    python3 bench/bench_real.py --modes given refine --selection window coverage --fs coverage_views=4
    python3 bench/bench_real.py --modes fast --selection window coverage   # overfit: the views chained through the core
"""

from __future__ import annotations

import argparse
import ast
import functools
import hashlib
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F

from depthgt.errors import FrameError
from depthgt.eval.bootstrap import bootstrap_means
from depthgt.eval.metrics import pose_errors
from depthgt.gt.build import quality_statistics
from depthgt.gt.cache import ResizedScene
from depthgt.gt.coverage import add_coverage_views, fill_maps
from depthgt.gt.patches import make_patches
from depthgt.gt.planning import coverage_candidates, stable_seed
from depthgt.gt.render import fuse
from depthgt.jobs.common import open_source_scene
from depthgt.registration import align, load_frameset, poses_from_source
from depthgt.settings import FrameSetSettings, PatchSettings, RenderSettings, registration_settings

REPO = Path(__file__).resolve().parents[1]
SHARED = next(
    (p for p in (REPO.parent / "shared", REPO.parents[1] / "shared", Path("/work/shared")) if p.is_dir()),
    REPO.parent / "shared",
)
SIZE = (256, 256)
DATA = {
    "tum": {"kind": "tum", "root": str(SHARED / "data/tum-fr1-xyz-0-239"), "scene": "."},
    "7scenes": {"kind": "sevenscenes", "root": str(SHARED / "data/7scenes-kitchen"), "scene": "7scenes-kitchen"},
}
#: pose modes: registration config sections
MODES = {
    "given": {"method": "given"},
    "refine": {"method": "refine"},
    "fast": {"method": "overfit", "preset": "fast"},
}
BANDS = ((0.0, 0.4, "centre"), (0.4, 0.7, "middle"), (0.7, 9.0, "border"))


def _digest(*parts) -> str:
    return hashlib.sha1(repr(parts).encode()).hexdigest()[:12]


@functools.cache
def library_digest() -> str:
    """A digest of the depthgt sources this process imports: part of a cached registration's
    key, so that a run of other code (another checkout, a change) never reads it back."""
    import depthgt

    h = hashlib.sha1()
    for path in sorted(Path(depthgt.__file__).resolve().parent.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def _band_masks(hw: tuple[int, int]) -> list[torch.Tensor]:
    h, w = hw
    y, x = torch.meshgrid(torch.arange(h) + 0.5 - h / 2, torch.arange(w) + 0.5 - w / 2, indexing="ij")
    r = torch.sqrt(x * x + y * y) / (0.5 * (h * h + w * w) ** 0.5)
    return [(r >= lo) & (r < hi) for lo, hi, _ in BANDS]


def run(
    data: str,
    mode: str,
    step: int,
    render: RenderSettings,
    options: dict,
    reg_over: dict,
    limit: int | None,
    cache: Path,
    selection: str = "window",
    fs_over: dict | None = None,
) -> list[dict]:
    spec = DATA[data]
    source = {"name": data, "kind": spec["kind"], "root": spec["root"], "options": options}
    scene = open_source_scene(source, spec["scene"])
    fs = FrameSetSettings(**{**(fs_over or {}), "selection": selection})
    # the coverage candidates are read through a frame cache, as a batch job reads them
    reg = registration_settings({**MODES[mode], **reg_over})
    resized = ResizedScene(scene, SIZE, keep=2 * fs.coverage_span + 2, need_pose=reg.uses_source_poses)
    splits = np.full(len(scene), "train", dtype=object)
    targets = list(range(fs.reach, len(scene) - fs.reach, step))[:limit]
    bands = _band_masks(SIZE)
    library = library_digest()
    rows = []
    for t in targets:
        try:
            data_fs = load_frameset(scene, [t + o for o in fs.offsets], SIZE, True, torch.device("cpu"))
        except FrameError as err:
            print(f"{data} target {t}: skipped: {err}")
            continue
        key = cache / f"{data}-{mode}-{t}-{_digest(options, reg_over, step, library)}.pt"
        cached = None
        if key.is_file():
            try:
                cached = torch.load(key, weights_only=False)
            except Exception as err:  # a cache written by another code version: recompute it
                print(f"{key.name}: cache not readable ({type(err).__name__}: {err}); registering again")
        if cached is not None:
            al, sec = cached
        else:
            t0 = time.perf_counter()
            al = align(data_fs, fs.offsets, reg, seed=t)
            sec = time.perf_counter() - t0
            torch.save((al, sec), key)
        fusion = fuse(data_fs, al.T_j_to_t, render, members=al.fused, leave_target_out=True)
        core_fusion, extra = fusion, {}
        if selection == "coverage":
            c0 = time.process_time()
            members = [t + o for o in fs.offsets]
            cov = add_coverage_views(
                resized,
                t,
                coverage_candidates(splits, t, members, fs),
                data_fs,
                al,
                fusion,
                fs,
                reg,
                render,
                core_offsets=fs.offsets,
            )
            extra = dict(
                cov_cpu_s=time.process_time() - c0,
                added=sum(v.get("filled_px", 0) > 0 and v["status"] == "ok" for v in cov.record["added"]),
                added_failed=sum(v["status"] != "ok" for v in cov.record["added"]),
                lto_all_mae_mm=1000 * float(cov.statistics.get("leave_target_out_all_views", {}).get("mae_m", np.nan)),
                lto_added_mae_mm=1000 * float(cov.statistics.get("leave_target_out_added", {}).get("mae_m", np.nan)),
                lto_added_px=int(cov.statistics.get("leave_target_out_added", {}).get("n_both_px", 0)),
            )
            # the added views' poses against the recording's own (as reg_rot/reg_trans for the core)
            fused_added = sorted(int(o) for o in cov.T_j_to_t)
            if fused_added:
                T_t = np.asarray(resized.read(t).T_world_cam, dtype=np.float64)
                ref_added = np.stack(
                    [np.linalg.inv(T_t) @ np.asarray(resized.read(t + o).T_world_cam, np.float64) for o in fused_added]
                )
                e = pose_errors(np.stack([np.asarray(cov.T_j_to_t[o], np.float64) for o in fused_added]), ref_added)
                extra.update(added_rot=e.rot_err_deg.tolist(), added_trans=np.asarray(e.trans_err_cm).tolist())
            fusion = cov.render
        gt = fusion.gt
        gt_np = gt.depth[0, 0].numpy()
        depth_in = data_fs.depth_m[0, 0].numpy()
        rgb8 = (data_fs.rgb[0].permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
        rng = np.random.default_rng(stable_seed(0, data, scene.name, t, "patches"))
        patches = make_patches(depth_in, gt_np, rgb8, PatchSettings(), rng, gt_sigma_m=gt.sigma[0, 0].numpy())
        agree = gt.agreement[0].numpy() if gt.agreement.numel() else np.full(len(al.fused), np.nan)
        dropped = np.zeros(len(fs.offsets), bool)
        for k, m in enumerate(al.fused):
            if m > 0 and np.isfinite(agree[k]) and agree[k] < render.min_frame_agreement:
                dropped[m] = True
        kept = sum(1 for m in al.fused if m > 0 and not dropped[m])
        stats = quality_statistics(data_fs, al, gt_np, render, core_fusion)
        lto = stats.get("leave_target_out", {})
        inp = data_fs.depth_m[0, 0]
        ref = poses_from_source(data_fs)
        err = pose_errors(al.T_j_to_t.numpy(), ref.numpy())
        extra.update(_all_views(extra, 1000 * float(lto.get("mae_m", np.nan))))
        row = dict(
            data=data,
            mode=mode,
            selection=selection,
            target=t,
            kept=kept,
            sec=sec,
            patches_kept=int(patches["kept"].sum()),
            **extra,
            gt_completeness=float((gt.depth[0, 0] > 0).float().mean()),
            input_completeness=float((inp > 0).float().mean()),
            lto_mae_mm=1000 * float(lto.get("mae_m", np.nan)),
            **_edge_split(core_fusion.left_out, data_fs.depth_m[0, 0]),
            agreement_median=float(np.nanmedian(agree[1:])) if np.isfinite(agree[1:]).any() else np.nan,
            rot=err.rot_err_deg.tolist(),
            trans=np.asarray(err.trans_err_cm).tolist(),
        )
        if getattr(gt, "disagreement", None) is not None:
            dis = gt.disagreement[0]  # (2, H, W): compared, disagreeing samples of the neighbours
            for mask, (_, _, name) in zip(bands, BANDS):
                n = float(dis[0][mask].sum())
                row[f"disagree_{name}"] = float(dis[1][mask].sum()) / n if n else np.nan
            n = float(dis[0].sum())
            row["kept_px"] = float(dis[2].sum()) / n if n else np.nan
        rows.append(row)
    return rows


def ceiling(
    scene, data: str, step: int, limit: int | None, fs: FrameSetSettings, size: tuple[int, int] = SIZE
) -> list[dict]:
    """Per target of ``scene``: the completeness bound of the core window, of
    +-``coverage_span`` and of every frame of the recording (see the module docstring,
    ``--ceiling``), at ``size``. Frames the source cannot read or place are left out, named."""
    resized = ResizedScene(scene, size, keep=len(scene) + 1, need_pose=True)
    usable = []
    for j in range(len(scene)):
        try:
            resized.read(j)
            usable.append(j)
        except FrameError as err:
            print(f"{data} frame {j}: left out of the bound: {err}")
    rows = []
    for t in list(range(fs.reach, len(scene) - fs.reach, step))[:limit]:
        if t not in usable:
            continue
        others = [j for j in usable if j != t]
        d = load_frameset(resized, [t, *others], size, True, torch.device("cpu"))
        empty = d.depth_m[0, 0] <= 0
        # one (H*W,) hit map per other frame: loops over frames, not pixels
        hits = fill_maps(d.depth_m[1:], d.K.float(), poses_from_source(d).float(), empty)
        hits = hits.reshape(len(others), 1, *size).float()
        row = dict(data=data, target=t, input_completeness=float((~empty).float().mean()))
        sets = {
            "core": [k for k, j in enumerate(others) if j - t in fs.offsets],
            "span": [k for k, j in enumerate(others) if abs(j - t) <= fs.coverage_span],
            "all": list(range(len(others))),
        }
        for name, ks in sets.items():
            hit = hits[ks].amax(dim=0, keepdim=True) if ks else torch.zeros(1, 1, *size)
            near = F.max_pool2d(hit, 3, stride=1, padding=1)[0, 0] > 0
            row[f"ceiling_{name}"] = float(((~empty) | (hit[0, 0] > 0)).float().mean())
            row[f"ceiling_{name}_d1"] = float(((~empty) | near).float().mean())
        rows.append(row)
    return rows


def _all_views(extra: dict, core_mm: float) -> dict:
    """A frame set where coverage fused no view: its all-views check is the core's (its
    GT is the core's), not a missing value; dropping it would compare the all-views
    mean over fewer frame sets with the core's over all of them."""
    if "lto_all_mae_mm" in extra and not np.isfinite(extra["lto_all_mae_mm"]):
        return {"lto_all_mae_mm": core_mm}
    return {}


def _edge_split(left_out, target: torch.Tensor) -> dict:
    """Leave-target-out errors (metres -> mm) at the target's depth edges and holes and away
    from them; the per-pixel errors are kept for the pooled means of :func:`summarise`."""
    if left_out is None:
        return dict(edge_err=[], flat_err=[])
    lto = left_out.depth[0, 0]
    iz = torch.where(target > 0, 1 / target.clamp_min(1e-6), torch.nan)[None, None]
    hi = F.max_pool2d(torch.nan_to_num(iz, nan=float("inf")), 5, 1, 2)
    lo = -F.max_pool2d(-torch.nan_to_num(iz, nan=-float("inf")), 5, 1, 2)
    edge = ((hi - lo) > 0.02 * iz.nan_to_num(0) + 0.01)[0, 0]
    both = (lto > 0) & (target > 0)
    err = 1000 * (lto - target)
    return dict(edge_err=err[both & edge].tolist(), flat_err=err[both & ~edge].tolist())


def summarise(df: pd.DataFrame) -> pd.DataFrame:
    out = []
    for (data, mode, selection), g in df.groupby(["data", "mode", "selection"], sort=False):
        rot = np.concatenate(g.rot.tolist())
        edge, flat = (np.concatenate([np.asarray(e, float) for e in g[c]]) for c in ("edge_err", "flat_err"))
        trans = np.concatenate(g.trans.tolist())
        r = dict(
            data=data,
            mode=mode,
            selection=selection,
            framesets=len(g),
            kept=g.kept.mean(),
            kept_px=g.kept_px.mean() if "kept_px" in g else np.nan,
            gt_completeness=g.gt_completeness.mean(),
            input_completeness=g.input_completeness.mean(),
            lto_mae_mm=g.lto_mae_mm.mean(),
            lto_edge_mm=np.abs(edge).mean() if edge.size else np.nan,
            lto_flat_mm=np.abs(flat).mean() if flat.size else np.nan,
            lto_edge_gross=(np.abs(edge) > 300).mean() if edge.size else np.nan,
            agreement_median=g.agreement_median.median(),
            reg_rot_deg_med=np.median(rot),
            reg_rot_deg_p90=np.percentile(rot, 90),
            reg_trans_cm_med=np.median(trans),
            reg_trans_cm_p90=np.percentile(trans, 90),
            sec_per_set=g.sec.mean(),
            patches_kept=int(g.patches_kept.sum()),
            patches_drawn=PatchSettings().count * len(g),
        )
        for col in ("added", "added_failed", "lto_all_mae_mm", "lto_added_px", "cov_cpu_s"):
            if col in g:
                r[col] = g[col].mean()
        if "lto_all_mae_mm" in g:  # all views minus the core, paired per frame set, 95 % bootstrap
            m = bootstrap_means((g.lto_all_mae_mm - g.lto_mae_mm).to_numpy(dtype=float))
            r.update(lto_all_minus_core_mm=m.mean[0], lto_all_minus_core_lo=m.low[0], lto_all_minus_core_hi=m.high[0])
        if "lto_added_px" in g and g.lto_added_px.sum() > 0:  # pooled over pixels: a few per frame set
            r["lto_added_mae_mm"] = float((g.lto_added_mae_mm.fillna(0) * g.lto_added_px).sum() / g.lto_added_px.sum())
        if "added_rot" in g:
            a_rot = np.concatenate([np.asarray(x, float) for x in g.added_rot if isinstance(x, list)] or [[np.nan]])
            a_trans = np.concatenate([np.asarray(x, float) for x in g.added_trans if isinstance(x, list)] or [[np.nan]])
            r.update(
                added_rot_deg_med=np.nanmedian(a_rot),
                added_rot_deg_p90=np.nanpercentile(a_rot, 90),
                added_trans_cm_med=np.nanmedian(a_trans),
                added_trans_cm_p90=np.nanpercentile(a_trans, 90),
            )
        for _, _, name in BANDS:
            if f"disagree_{name}" in g:
                r[f"disagree_{name}"] = g[f"disagree_{name}"].mean()
        out.append(r)
    return pd.DataFrame(out)


def _literal(pairs: list[str]) -> dict:
    out = {}
    for kv in pairs:
        k, _, v = kv.partition("=")
        try:
            out[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            out[k] = v
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", nargs="+", default=list(DATA), choices=list(DATA))
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--tum-step", type=int, default=6)
    ap.add_argument("--7scenes-step", dest="sevenscenes_step", type=int, default=4)
    ap.add_argument("--limit", type=int, default=None, help="only the first N frame sets of each recording")
    ap.add_argument("--set", nargs="*", default=[], help="RenderSettings overrides key=value")
    ap.add_argument("--reg", nargs="*", default=[], help="registration overrides key=value")
    ap.add_argument("--tum-option", nargs="*", default=[], help="tum source options key=value")
    ap.add_argument(
        "--selection",
        nargs="+",
        default=["window"],
        choices=["window", "coverage"],
        help="frameset.selection: each one runs on the same registrations",
    )
    ap.add_argument("--fs", nargs="*", default=[], help="FrameSetSettings overrides key=value (coverage_span, ...)")
    ap.add_argument(
        "--ceiling",
        action="store_true",
        help="only the completeness bound of the core, +-coverage_span and every frame (reference poses)",
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--cache",
        type=Path,
        default=Path("/tmp/depthgt_real"),
        help="registrations are cached here (by recording, mode, target, options and the library's source digest)",
    )
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_real.csv"))
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    a.cache.mkdir(parents=True, exist_ok=True)
    render = RenderSettings(**{"leave_target_out_stride": 1, **_literal(a.set)})  # the full check: every pixel
    print(f"command: python3 bench/bench_real.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    rows = []
    for data in a.data:
        if not Path(DATA[data]["root"]).is_dir():
            print(f"{data}: {DATA[data]['root']} not found, skipped")
            continue
        options = _literal(a.tum_option) if data == "tum" else {}
        step = a.tum_step if data == "tum" else a.sevenscenes_step
        if a.ceiling:
            source = {"name": data, "kind": DATA[data]["kind"], "root": DATA[data]["root"], "options": options}
            scene = open_source_scene(source, DATA[data]["scene"])
            rows += ceiling(scene, data, step, a.limit, FrameSetSettings(**_literal(a.fs)))
            continue
        for mode in a.modes:
            for selection in a.selection:
                rows += run(
                    data, mode, step, render, options, _literal(a.reg), a.limit, a.cache, selection, _literal(a.fs)
                )
    df = pd.DataFrame(rows)
    df.to_pickle(a.out.with_suffix(".pkl"))
    if a.ceiling:
        if df.empty:
            print("no usable target: nothing to bound")
            return
        s = df.groupby("data").agg(framesets=("target", "size"), **{c: (c, "mean") for c in df.columns[2:]})
        s.to_csv(a.out)
        print(s.reset_index().to_markdown(index=False, floatfmt=".4f"))
        return
    s = summarise(df)
    s.to_csv(a.out, index=False)
    pd.set_option("display.width", 250)
    print(s.to_markdown(index=False, floatfmt=".4g"))


if __name__ == "__main__":
    main()
