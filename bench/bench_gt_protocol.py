"""The GT renderer's tuning protocol: a TUNING set to choose defaults on, a disjoint
EVALUATION set to report on, scored per pixel category against the synthetic truth.

Sets (frame sets of targets 8, 20, 32 of 40-frame sequences, 640x480 frames resized to
256x256 as the workflow does, the pipeline's own code path ``depthgt.gt.render.fuse``):

* ``tuning``: ``room`` family seed 0 (room_000-002) and ``varied`` family seed 0
  (varied_000-003), Kinect v1 profile. Every renderer default is chosen on these.
* ``tuning_stereo``: ``varied`` family seed 0 (varied_000-003) with the second sensor
  profile ``coarse_stereo``: an auxiliary tuning set for what depends on the sensor
  (the registration's settings were checked on it).
* ``evaluation``: never used for choosing anything: ``room`` seed 1 (room_000-002,
  Kinect v1), ``varied`` seed 1 (varied_000-005, Kinect v1) and ``varied`` seed 2
  (varied_000-005) with the second sensor profile ``coarse_stereo``.

Per-pixel categories of the target, from the exact geometry of its 640x480 pixels
(``SyntheticScene.exact_view``) nearest-resized to 256x256 like the depth: ``grazing``
(incidence above 65 deg),
``far`` (exact depth beyond 4 m), ``thin`` (a pole, leg or rod <= 3 cm wide), ``rest``
(none of these); ``all``. The first three may overlap.

Metrics, pooled over every pixel of a set (not averaged per frame set), against the
pipeline's truth (the nearest-resized clean target depth, as in gt_quality.csv: the
exact depth at the sample positions of the input and of the GT):

* ``completeness``: share of truth pixels with depth;
* ``mae_counted``: MAE over truth pixels, a missing pixel counting as its truth depth;
* ``mae_both``: MAE over pixels where the GT, the input and the truth all have depth;
* ratios GT / input of both MAEs;
* the confidence (gt.exr channel ``S``): rank correlation with the actual error, the
  share of GT pixels with |error| <= sigma and <= 2 sigma, the MAE of the most certain 80 %;
* ``clean_own``: the renderer's own error, the GT fused from the 6 neighbours' clean
  depth with exact poses, MAE vs the truth (and its completeness).

Usage::

    python3 bench/bench_gt_protocol.py --sets tuning                      # choose defaults on this
    python3 bench/bench_gt_protocol.py --sets evaluation                  # report this
    python3 bench/bench_gt_protocol.py --sets evaluation --registration fast   # overfit registration, preset fast
    python3 bench/bench_gt_protocol.py --fixture                          # 7-Scenes: GT completeness, leave-target-out
    python3 bench/bench_gt_protocol.py --sets tuning --set rel_sigma=3 --png /tmp/pngs
    python3 bench/bench_gt_protocol.py --sets tuning --added ambiguous_px=0.0   # error of the pixels a variant adds
    python3 bench/bench_gt_protocol.py --sets evaluation --selection coverage  # frameset.selection: coverage

With ``--selection coverage`` (source poses only) each frame set adds views from its
40-frame sequence (:mod:`depthgt.gt.coverage`, ``--fs`` sets its ``coverage_*`` limits);
the candidate frames are generated through a frame cache per sequence (not cached on disk).

Frame sets are generated once and cached (``--cache``, default /tmp/depthgt_protocol);
registrations are cached there too. Prints Markdown tables and writes a tidy CSV.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from depthgt.gt.cache import ResizedScene
from depthgt.gt.coverage import add_coverage_views
from depthgt.gt.planning import coverage_candidates, stable_seed
from depthgt.gt.render import fuse
from depthgt.registration import Alignment, FrameSetData, load_frameset, poses_from_source
from depthgt.settings import FrameSetSettings, RenderSettings, registration_settings

REPO = Path(__file__).resolve().parents[1]
SIZE = (256, 256)
TARGETS = (8, 20, 32)
N_FRAMES = 40
GRAZING_COS = float(np.cos(np.radians(65.0)))
FAR_M = 4.0

SETS: dict[str, list[dict]] = {
    "tuning": [
        dict(family="room", seed=0, sensor="kinect_v1", scenes=range(0, 3)),
        dict(family="varied", seed=0, sensor="kinect_v1", scenes=range(0, 4)),
    ],
    # an auxiliary tuning set: the tuning set's varied rooms (seed 0) seen by the second
    # sensor profile, to tune what depends on the sensor (e.g. the registration) without
    # looking at the evaluation set's coarse_stereo rooms (seed 2)
    "tuning_stereo": [
        dict(family="varied", seed=0, sensor="coarse_stereo", scenes=range(0, 4)),
    ],
    "evaluation": [
        dict(family="room", seed=1, sensor="kinect_v1", scenes=range(0, 3)),
        dict(family="varied", seed=1, sensor="kinect_v1", scenes=range(0, 6)),
        dict(family="varied", seed=2, sensor="coarse_stereo", scenes=range(0, 6)),
    ],
}
CATEGORIES = ("all", "grazing", "far", "thin", "rest")


# ------------------------------------------------------------------------------ data


def _key(group: dict, k: int, t: int) -> str:
    return f"{group['family']}_{k:03d}_s{group['seed']}_{group['sensor']}_t{t:03d}"


def load_cached(cache: Path, group: dict, k: int, t: int) -> dict:
    """The frame set (FrameSetData fields) and the target's exact view at 256x256."""
    path = cache / "framesets" / f"{_key(group, k, t)}.npz"
    if not path.exists():
        from depthgt.geometry import _centre_indices
        from depthgt.sources.base import open_scene

        scene = open_scene(
            "synthetic",
            None,
            f"{group['family']}_{k:03d}",
            seed=group["seed"],
            sensor=group["sensor"],
            n_frames=N_FRAMES,
        )
        members = [t + o for o in FrameSetSettings().offsets]
        data = load_frameset(scene, members, SIZE, True, torch.device("cpu"))
        # the exact geometry at the source's pixels, nearest-resized like the depth: the
        # categories of the very points the input, the truth and the GT describe
        view = scene.exact_view(t)
        iy = _centre_indices(scene.image_size[0], SIZE[0], torch.device("cpu")).numpy()
        ix = _centre_indices(scene.image_size[1], SIZE[1], torch.device("cpu")).numpy()
        view = type(view)(*(a[iy][:, ix] for a in view))
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            rgb=(data.rgb.numpy() * 255 + 0.5).astype(np.uint8),
            depth=data.depth_m.numpy(),
            truth=data.truth_m.numpy(),
            K=data.K.numpy(),
            T=data.T_world_cam.numpy(),
            src_hw=np.array(data.src_hw),
            exact=view.depth_m,
            cos=view.cos_incidence,
            thin=view.thin,
            members=np.array(members),
        )
    z = np.load(path)
    data = FrameSetData(
        rgb=torch.from_numpy(z["rgb"]).float() / 255.0,
        depth_m=torch.from_numpy(z["depth"]),
        K=torch.from_numpy(z["K"]),
        T_world_cam=torch.from_numpy(z["T"]),
        truth_m=torch.from_numpy(z["truth"]),
        frame_ids=[str(m) for m in z["members"]],
        src_hw=tuple(int(x) for x in z["src_hw"]),
    )
    return dict(data=data, exact=z["exact"], cos=z["cos"], thin=z["thin"], members=[int(m) for m in z["members"]])


def registration_section(preset: str, overrides: list[str]) -> dict:
    """The ``registration`` config section of ``--registration`` and ``--reg-set``
    (``key=value`` or ``section.key=value``, python literals)."""
    section: dict = {"preset": preset}
    for item in overrides:
        k, v = item.split("=", 1)
        *outer, last = k.split(".")
        d = section
        for o in outer:
            d = d.setdefault(o, {})
        d[last] = ast.literal_eval(v)
    return section


def registered_poses(
    cache: Path, item: dict, key: str, preset: str, overrides: list[str] = (), tag: str = ""
) -> tuple[torch.Tensor, list[int]]:
    """T_j_to_t (F-1, 4, 4) of the overfit registration (cached per preset, overrides,
    ``tag`` and the library's source digest: another checkout's or an older code's poses
    are not read back) and the fused member positions."""
    from bench_real import library_digest

    name = (
        preset
        + "".join(f"__{o}" for o in overrides).replace("/", "_").replace(" ", "")
        + (f"__{tag}" if tag else "")
        + f"__{library_digest()}"
    )
    path = cache / "registration" / name / f"{key}.json"
    if not path.exists():
        from depthgt.registration import register_frameset
        from depthgt.settings import registration_settings

        data = item["data"]
        offsets = FrameSetSettings().offsets
        res = register_frameset(
            data.rgb,
            data.depth_m,
            data.K,
            list(offsets),
            registration_settings(registration_section(preset, list(overrides))),
            seed=stable_seed(0, "protocol", key),
        )
        fused = [0] + [i + 1 for i, st in enumerate(res.neighbour_status) if st == "ok"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(
            json.dumps(
                {
                    "T_j_to_t": np.asarray(res.T_j_to_t, dtype=np.float64).tolist(),
                    "fused": fused,
                    "status": res.neighbour_status,
                    "reasons": res.neighbour_reasons,
                    "seconds": res.timings.get("total"),
                }
            )
        )
    doc = json.loads(path.read_text())
    return torch.tensor(doc["T_j_to_t"], dtype=torch.float64), doc["fused"]


def pose_errors_vs_source(T_est: torch.Tensor, data: FrameSetData) -> tuple[np.ndarray, np.ndarray]:
    """Per neighbour (rotation deg, translation m) error of estimated T_j_to_t vs the source's."""
    from depthgt.eval.metrics import pose_delta

    T_src = poses_from_source(data).to(torch.float64)
    dt, dr = pose_delta((torch.linalg.inv(T_src) @ T_est.to(torch.float64)).numpy())
    return np.asarray(dr), np.asarray(dt)


# --------------------------------------------------------------------------- scoring


class Pool:
    """Pooled sums per (category, estimate) over many frame sets."""

    def __init__(self):
        self.sums: dict[tuple[str, str, str], float] = {}

    def add(self, cat: str, est: str, name: str, value: float) -> None:
        k = (cat, est, name)
        self.sums[k] = self.sums.get(k, 0.0) + float(value)

    def get(self, cat: str, est: str, name: str) -> float:
        return self.sums.get((cat, est, name), 0.0)


def categories(item: dict) -> dict[str, np.ndarray]:
    exact, cos, thin = item["exact"], item["cos"], item["thin"]
    grazing = (cos < GRAZING_COS) & (exact > 0)
    far = exact > FAR_M
    return {
        "all": exact > 0,
        "grazing": grazing,
        "far": far,
        "thin": thin & (exact > 0),
        "rest": (exact > 0) & ~grazing & ~far & ~thin,
    }


def score(pool: Pool, cats: dict[str, np.ndarray], estimates: dict[str, np.ndarray], ref: np.ndarray) -> None:
    """Add the pooled sums of every estimate vs ``ref`` (both (H, W) metres, 0 = none)."""
    ref_ok = ref > 0
    both = ref_ok & (estimates["input"] > 0) & (estimates["gt"] > 0)
    for cat, mask in cats.items():
        m = mask & ref_ok
        pool.add(cat, "-", "n_ref", m.sum())
        pool.add(cat, "-", "n_both", (m & both).sum())
        for name, est in estimates.items():
            ok = m & (est > 0)
            err = np.abs(est.astype(np.float64) - ref)
            pool.add(cat, name, "n_valid", ok.sum())
            pool.add(cat, name, "sum_counted", np.where(est > 0, err, ref)[m].sum())
            pool.add(cat, name, "sum_valid", err[ok].sum())
            pool.add(cat, name, "sum_both", err[m & both].sum())


def summarise(pool: Pool, set_name: str, variant: str) -> list[dict]:
    rows = []
    for cat in CATEGORIES:
        n_ref, n_both = pool.get(cat, "-", "n_ref"), pool.get(cat, "-", "n_both")
        if n_ref == 0:
            continue
        r = dict(set=set_name, variant=variant, category=cat, pixels=int(n_ref))
        for est in ("input", "gt"):
            r[f"{est}_completeness"] = pool.get(cat, est, "n_valid") / n_ref
            r[f"{est}_mae_counted_mm"] = 1000 * pool.get(cat, est, "sum_counted") / n_ref
            r[f"{est}_mae_both_mm"] = 1000 * pool.get(cat, est, "sum_both") / max(n_both, 1)
        r["ratio_counted"] = r["gt_mae_counted_mm"] / r["input_mae_counted_mm"]
        r["ratio_both"] = r["gt_mae_both_mm"] / max(r["input_mae_both_mm"], 1e-12)
        n_clean = pool.get(cat, "clean", "n_valid")
        if pool.get(cat, "clean", "n_ref") or n_clean:
            r["clean_own_mae_mm"] = 1000 * pool.get(cat, "clean", "sum_valid") / max(n_clean, 1)
            r["clean_own_completeness"] = n_clean / max(pool.get(cat, "clean", "n_ref"), 1)
        rows.append(r)
    return rows


def _colour(z: np.ndarray, lo: float, hi: float) -> np.ndarray:
    import cv2

    img = cv2.applyColorMap((np.clip((z - lo) / max(hi - lo, 1e-6), 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return img * (z > 0)[..., None]


def write_png(
    path: Path, item: dict, inp: np.ndarray, gt: np.ndarray, ref: np.ndarray, conf: np.ndarray | None
) -> None:
    """input | GT | truth on one depth colour scale; |GT - truth| and |input - truth| (0-5 cm); categories."""
    import cv2

    lo, hi = float(np.quantile(ref[ref > 0], 0.01)), float(np.quantile(ref[ref > 0], 0.99))

    def err(e):
        v = np.where((e > 0) & (ref > 0), np.abs(e - ref), 0)
        img = cv2.applyColorMap((np.clip(v / 0.05, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
        img[(e <= 0) & (ref > 0)] = (255, 255, 255)  # missing: white
        return img

    cats = categories(item)
    cat_img = np.zeros(ref.shape + (3,), np.uint8)
    cat_img[cats["grazing"]] = (0, 160, 0)
    cat_img[cats["far"]] += np.array((160, 0, 0), np.uint8)
    cat_img[cats["thin"]] = (0, 0, 255)
    row1 = np.concatenate([_colour(inp, lo, hi), _colour(gt, lo, hi), _colour(ref, lo, hi)], 1)
    extra = (
        cat_img
        if conf is None
        else cv2.applyColorMap((np.clip(conf / 0.03, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        * (conf > 0)[..., None]
    )
    row2 = np.concatenate([err(inp), err(gt), extra if conf is not None else cat_img], 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate([row1, row2], 0))


def run_set(
    set_name: str,
    settings: RenderSettings,
    cache: Path,
    registration: str | None,
    png_dir: Path | None,
    clean: bool,
    reg_set: list[str] = (),
    reg_tag: str = "",
    scenes_per_group: int | None = None,
    fuse_all: bool = False,
    coverage: FrameSetSettings | None = None,
) -> list[dict]:
    pool, pool_by = Pool(), {}
    added_views, filled_px, t_cov = [], [], []
    t_render, conf_err, conf_sigma = [], [], []
    pose_rows = []
    for group in SETS[set_name]:
        gname = f"{group['family']}/s{group['seed']}/{group['sensor']}"
        gp = pool_by.setdefault(gname, Pool())
        for k in list(group["scenes"])[:scenes_per_group]:
            frames = None
            if coverage is not None:
                from depthgt.sources.base import open_scene

                frames = ResizedScene(
                    open_scene(
                        "synthetic",
                        None,
                        f"{group['family']}_{k:03d}",
                        seed=group["seed"],
                        sensor=group["sensor"],
                        n_frames=N_FRAMES,
                    ),
                    SIZE,
                    keep=2 * coverage.coverage_span + 2,
                    need_pose=not registration,  # overfit: the added views' poses come from the chain
                )
            for t in TARGETS:
                key = _key(group, k, t)
                item = load_cached(cache, group, k, t)
                data = item["data"]
                if registration:
                    T, fused = registered_poses(cache, item, key, registration, reg_set, reg_tag)
                    dr, dt = pose_errors_vs_source(T, data)
                    pose_rows.append(
                        dict(
                            frameset=key,
                            n_fused=len(fused) - 1,
                            rot_med_deg=float(np.median(dr)),
                            rot_max_deg=float(dr.max()),
                            trans_med_cm=100 * float(np.median(dt)),
                            trans_max_cm=100 * float(dt.max()),
                        )
                    )
                    pose_rows[-1]["_dr"], pose_rows[-1]["_dt"] = dr, dt
                    members = fused if len(fused) < len(item["members"]) and not fuse_all else slice(None)
                else:
                    T, members = poses_from_source(data), slice(None)
                c0 = time.process_time()
                out = fuse(data, T, settings, members=members)
                t_render.append(time.process_time() - c0)
                if frames is not None:
                    c0 = time.process_time()
                    cands = coverage_candidates(np.full(N_FRAMES, "train", dtype=object), t, item["members"], coverage)
                    reg = (
                        registration_settings(registration_section(registration, list(reg_set)))
                        if registration
                        else registration_settings({"method": "given"})
                    )
                    cov = add_coverage_views(
                        frames,
                        t,
                        cands,
                        data,
                        Alignment(T, list(range(len(item["members"]))) if members == slice(None) else list(members)),
                        out,
                        coverage,
                        reg,
                        settings,
                        core_offsets=[m - t for m in item["members"]],
                    )
                    t_cov.append(time.process_time() - c0)
                    added_views.append(sum(v["status"] == "ok" for v in cov.record["added"]))
                    filled_px.append(cov.record.get("filled_px", 0))
                    out = cov.render
                gt = out.gt.depth[0, 0].numpy()
                inp = data.depth_m[0, 0].numpy()
                ref = data.truth_m[0, 0].numpy()
                cats = categories(item)
                for p in (pool, gp):
                    score(p, cats, {"input": inp, "gt": gt}, ref)
                m = (gt > 0) & (ref > 0)
                conf_err.append(np.abs(gt - ref)[m])
                conf_sigma.append(out.gt.sigma[0, 0].numpy()[m])
                if clean and not registration:
                    own = fuse(data, poses_from_source(data), settings, depth_m=data.truth_m, members=slice(1, None))
                    g = own.gt.depth[0, 0].numpy()
                    exact = ref
                    for cat, mask in cats.items():
                        m = mask & (exact > 0)
                        ok = m & (g > 0)
                        for p in (pool, gp):
                            p.add(cat, "clean", "n_ref", m.sum())
                            p.add(cat, "clean", "n_valid", ok.sum())
                            p.add(cat, "clean", "sum_valid", np.abs(g.astype(np.float64) - exact)[ok].sum())
                if png_dir is not None:
                    conf = getattr(out, "sigma", None)
                    write_png(
                        png_dir / set_name / f"{key}.png",
                        item,
                        inp,
                        gt,
                        ref,
                        None if conf is None else conf[0, 0].numpy(),
                    )
    if pose_rows:
        pr = pd.DataFrame(pose_rows)
        dr_all = np.concatenate(list(pr.pop("_dr")))
        dt_all = np.concatenate(list(pr.pop("_dt")))
        print(f"\nregistration error vs the source's poses on {set_name}, per frame set:")
        print(pr.to_markdown(index=False, floatfmt=".3g"))
        print(
            f"registration error on {set_name} over all {len(dr_all)} neighbours: rotation median "
            f"{np.median(dr_all):.3f} deg (90th pct {np.quantile(dr_all, 0.9):.3f}, max {dr_all.max():.3f}), "
            f"translation median {100 * np.median(dt_all):.3f} cm (90th pct {100 * np.quantile(dt_all, 0.9):.3f}, "
            f"max {100 * dt_all.max():.3f}); neighbours fused {int(pr.n_fused.sum())} of {len(dr_all)}\n"
        )
    variant = f"registration={registration}" if registration else "source poses"
    variant += ", selection coverage" if coverage is not None else ""
    rows = summarise(pool, set_name, variant)
    for gname, gp in pool_by.items():
        rows += summarise(gp, f"{set_name}:{gname}", variant)
    print(f"render CPU time per frame set: median {np.median(t_render):.3f} s over {len(t_render)}", file=sys.stderr)
    if t_cov:
        print(
            f"coverage on {set_name}: {np.mean(added_views):.2f} views added and {np.mean(filled_px):.0f} px filled per "
            f"frame set; CPU {np.mean(t_cov):.2f} s per frame set (mean; candidates generated and read included)"
        )
    print(confidence_summary(set_name, np.concatenate(conf_err), np.concatenate(conf_sigma)))
    return rows


def confidence_summary(set_name: str, err: np.ndarray, sigma: np.ndarray) -> str:
    """How well the GT's sigma (gt.exr channel S) predicts its actual error, over all GT pixels."""
    keep = sigma <= np.quantile(sigma, 0.8)
    rho = pd.Series(sigma).corr(pd.Series(err), method="spearman")
    return (
        f"confidence on {set_name}: Spearman(sigma, |error|) {rho:.3f}; "
        f"|error| <= sigma for {(err <= sigma).mean():.3f}, <= 2 sigma for {(err <= 2 * sigma).mean():.3f} of GT pixels; "
        f"median |error| / sigma {np.median(err / sigma):.3f}; MAE over all GT pixels {1000 * err.mean():.2f} mm, "
        f"over the 80 % most certain {1000 * err[keep].mean():.2f} mm (sigma <= {1000 * np.quantile(sigma, 0.8):.1f} mm)"
    )


def added_pixels(set_name: str, base: RenderSettings, variant: RenderSettings, cache: Path) -> str:
    """What a more complete renderer setting adds, judged pixel by pixel against the
    truth (source poses): completeness of both, and the error of the GT pixels that only
    ``variant`` has (mean, median, share beyond 5 cm) next to that of the shared ones,
    and how often the variant's sigma covers the added pixels' error (|e| <= 2 sigma)."""
    n_ref = n_base = 0
    added, shared, sig = [], [], []
    for group in SETS[set_name]:
        for k in group["scenes"]:
            for t in TARGETS:
                data = load_cached(cache, group, k, t)["data"]
                T = poses_from_source(data)
                g0 = fuse(data, T, base).gt.depth[0, 0].numpy()
                out = fuse(data, T, variant).gt
                g1 = out.gt.depth[0, 0].numpy()
                ref = data.truth_m[0, 0].numpy()
                new = (g0 <= 0) & (g1 > 0) & (ref > 0)
                n_ref += int((ref > 0).sum())
                n_base += int(((g0 > 0) & (ref > 0)).sum())
                added.append(np.abs(g1 - ref)[new])
                shared.append(np.abs(g0 - ref)[(g0 > 0) & (ref > 0)])
                sig.append(out.gt.sigma[0, 0].numpy()[new])
    e, e0, sg = np.concatenate(added), np.concatenate(shared), np.concatenate(sig)
    if not e.size:
        return f"{set_name}: the variant adds no GT pixel"
    return (
        f"{set_name}: completeness {n_base / n_ref:.4f} -> {(n_base + e.size) / n_ref:.4f} ({e.size} pixels added); "
        f"added pixels: MAE {1000 * e.mean():.1f} mm, median {1000 * np.median(e):.1f} mm, beyond 5 cm {np.mean(e > 0.05):.3f}, "
        f"|e| <= 2 sigma {np.mean(e <= 2 * sg):.2f}; the defaults' pixels: MAE {1000 * e0.mean():.2f} mm, median "
        f"{1000 * np.median(e0):.2f} mm, beyond 5 cm {np.mean(e0 > 0.05):.4f}"
    )


# -------------------------------------------------------------------------- 7-Scenes


def run_fixture(fixture: Path, settings: RenderSettings, step: int) -> list[dict]:
    """GT completeness and leave-target-out consistency on the real fixture (reference
    poses), as the workflow computes them (pipeline.fuse, quality.error_stats)."""
    from depthgt.eval.metrics import depth_errors
    from depthgt.jobs.common import open_source_scene

    scene = open_source_scene({"kind": "sevenscenes", "root": str(fixture)}, fixture.name)
    fs = FrameSetSettings()
    rows = []
    for t in range(fs.reach, len(scene) - fs.reach, step):
        data = load_frameset(scene, [t + o for o in fs.offsets], SIZE, True, torch.device("cpu"))
        T = poses_from_source(data)
        gt = fuse(data, T, settings).gt.depth[0, 0].numpy()
        lto = fuse(data, T, settings, members=slice(1, None)).gt.depth[0, 0].numpy()
        inp = data.depth_m[0, 0].numpy()
        s = depth_errors(lto, inp)
        rows.append(
            dict(
                target=t,
                gt_completeness=float((gt > 0).mean()),
                input_completeness=float((inp > 0).mean()),
                lto_mae_valid_mm=1000 * s["mae_m"],
                lto_completeness=s["completeness"],
            )
        )
    return rows


# ---------------------------------------------------------------------------- main


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="*", default=[], choices=list(SETS))
    ap.add_argument(
        "--registration", default=None, help="overfit registration preset (e.g. fast) instead of the source's poses"
    )
    ap.add_argument(
        "--reg-set",
        nargs="*",
        default=[],
        help="registration overrides key=value or section.key=value (python literals), "
        "e.g. refine_settings.iters=(8,5,3); cached separately",
    )
    ap.add_argument(
        "--scenes",
        type=int,
        default=None,
        help="a subset: only the first N scenes of each group of a set (default all)",
    )
    ap.add_argument(
        "--fuse-all",
        action="store_true",
        help="diagnostic: fuse every neighbour, also those the registration's checks failed",
    )
    ap.add_argument("--reg-tag", default="", help="extra name of the registration cache (the code is in it already)")
    ap.add_argument("--no-clean", action="store_true", help="skip the clean-neighbours (renderer's own error) case")
    ap.add_argument(
        "--fixture",
        nargs="?",
        const=str(
            next(
                (
                    p
                    for p in (
                        REPO.parent / "shared/data/7scenes-kitchen",
                        REPO.parents[1] / "shared/data/7scenes-kitchen",
                    )
                    if p.is_dir()
                ),
                REPO.parent / "shared/data/7scenes-kitchen",
            )
        ),
        default=None,
    )
    ap.add_argument("--fixture-step", type=int, nargs="+", default=[9, 4])
    ap.add_argument("--set", nargs="*", default=[], help="RenderSettings overrides key=value (python literals)")
    ap.add_argument("--grid", default=None, help="key=v1;v2;... : one RenderSettings field over values (compact table)")
    ap.add_argument(
        "--added",
        nargs="*",
        default=[],
        help="RenderSettings overrides key=value of a more complete variant: the error of the GT pixels it adds",
    )
    ap.add_argument("--cache", type=Path, default=Path("/tmp/depthgt_protocol"))
    ap.add_argument("--png", type=Path, default=None, help="write input | GT | truth images here")
    ap.add_argument("--selection", choices=["window", "coverage"], default="window", help="frameset.selection")
    ap.add_argument("--fs", nargs="*", default=[], help="FrameSetSettings overrides key=value (coverage_span, ...)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_gt_protocol.csv"))
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    settings = RenderSettings(**{k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in a.set)})
    print(f"command: python3 bench/bench_gt_protocol.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    if a.added:
        variant = replace(settings, **{k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.added)})
        for name in a.sets:
            print(added_pixels(name, settings, variant, a.cache))
        return
    if a.grid:
        key, _, values = a.grid.partition("=")
        compact = []
        for value in values.split(";"):
            st = replace(settings, **{key: ast.literal_eval(value)})
            for s in a.sets:
                for r in run_set(
                    s, st, a.cache, a.registration, None, not a.no_clean, a.reg_set, a.reg_tag, a.scenes, a.fuse_all
                ):
                    if ":" not in r["set"]:
                        compact.append(dict(value=value, **r))
        df = pd.DataFrame(compact)
        cols = ["value", "set", "category", "gt_completeness", "input_completeness", "ratio_counted", "ratio_both"]
        cols += [c for c in ("clean_own_mae_mm", "clean_own_completeness") if c in df]
        print(f"grid over {key}")
        print(df[cols].to_markdown(index=False, floatfmt=".4g"))
        return
    coverage = None
    if a.selection == "coverage":
        coverage = FrameSetSettings(
            selection="coverage", **{k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.fs)}
        )
    rows = []
    for s in a.sets:
        rows += run_set(
            s,
            settings,
            a.cache,
            a.registration,
            a.png,
            not a.no_clean,
            a.reg_set,
            a.reg_tag,
            a.scenes,
            a.fuse_all,
            coverage,
        )
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 30)
    if rows:
        df = pd.DataFrame(rows)
        df.to_csv(a.out, index=False)
        cols = [
            "set",
            "category",
            "pixels",
            "input_completeness",
            "gt_completeness",
            "input_mae_counted_mm",
            "gt_mae_counted_mm",
            "ratio_counted",
            "input_mae_both_mm",
            "gt_mae_both_mm",
            "ratio_both",
        ]
        cols += [c for c in ("clean_own_mae_mm", "clean_own_completeness") if c in df]
        print(f"\nreference: the pipeline's truth (nearest-resized clean target); {df['variant'].iloc[0]}")
        print(df[cols].to_markdown(index=False, floatfmt=".4g"))
    if a.fixture:
        for step in a.fixture_step:
            fx = pd.DataFrame(run_fixture(Path(a.fixture), settings, step))
            print(
                f"\n7-Scenes fixture, reference poses, targets every {step} frames ({len(fx)} frame sets): "
                f"GT completeness {fx.gt_completeness.mean():.4f} (input {fx.input_completeness.mean():.4f}), "
                f"leave-target-out MAE where both valid {fx.lto_mae_valid_mm.mean():.2f} mm, "
                f"completeness {fx.lto_completeness.mean():.4f}"
            )


if __name__ == "__main__":
    main()
