"""The built dataset as users read it: bytes per frame set, GTDataset throughput, the
export's time, and the arrays a reader gets (to compare two builds or two checkouts).

Run it with the checkout whose reader is measured first on ``PYTHONPATH`` (it imports
only public API, so it runs against older checkouts too)::

    PYTHONPATH=src python3 bench/bench_dataset.py bytes WORKDIR
    PYTHONPATH=src python3 bench/bench_dataset.py loader WORKDIR --split test --epochs 3
    PYTHONPATH=src python3 bench/bench_dataset.py export WORKDIR --split test
    PYTHONPATH=src python3 bench/bench_dataset.py dump WORKDIR --split test --out a.npz
    python3 bench/bench_dataset.py compare a.npz b.npz

* ``bytes``: per frame-set shard, bytes per built frame set (the shard's size over its
  frame sets) and per member (gt.exr, input.exr, the colour, patches.npz, JSON), in
  bytes as stored in the shard; 1 MB = 10^6 bytes;
* ``loader``: samples per second of ``GTDataset(kind)`` through a ``DataLoader`` with
  ``--workers`` workers (default 2), ``--batch`` samples per batch, ``--epochs`` passes
  in a fresh loader each (the first pass includes the workers' start); with
  ``--workers 0`` also the CPU time per sample (less sensitive to a loaded machine);
* ``export``: wall seconds of ``depthgt export`` (``export_dataset``) of the split to a
  temporary folder, png16;
* ``dump`` / ``compare``: every sample of a split (input, gt, sigma, truth, rgb and the
  ids) to an npz; the largest absolute difference per array between two dumps (for
  ``sigma`` also the largest relative one) and whether the patch pairs' ids agree.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import zipfile
from collections import Counter
from pathlib import Path

import numpy as np


def _bytes(workdir: Path) -> None:
    shards = sorted((workdir / "results" / "framesets").glob("*/*/*.zip"))
    total_sets, total_bytes, members = 0, 0, Counter()
    for shard in shards:
        with zipfile.ZipFile(shard) as z:
            sets = {i.filename.split("/")[0] for i in z.infolist() if i.filename.endswith("/frameset.json")}
            for i in z.infolist():
                members[i.filename.rsplit("/", 1)[-1]] += i.compress_size
        size = shard.stat().st_size
        total_sets += len(sets)
        total_bytes += size
        print(f"{shard.relative_to(workdir)}: {len(sets)} frame sets, {size / max(len(sets), 1) / 1e6:.3f} MB per set")
    print(
        f"all: {total_sets} frame sets, {total_bytes / total_sets / 1e6:.3f} MB ({total_bytes / total_sets / 2**20:.3f} "
        f"MiB) per set"
    )
    for name, b in sorted(members.items()):
        print(f"  {name}: {b / total_sets / 1e3:.1f} kB per set")


def _loader(workdir: Path, split: str, kind: str, workers: int, batch: int, epochs: int) -> None:
    from torch.utils.data import DataLoader

    from depthgt.data import GTDataset

    os.chdir(workdir)
    ds = GTDataset(Path("results"), split, kind)
    for epoch in range(epochs):
        loader = DataLoader(ds, batch_size=batch, num_workers=workers)
        t, cpu = time.perf_counter(), time.process_time()
        n = sum(len(b["patch"]) for b in loader)
        wall, cpu = time.perf_counter() - t, time.process_time() - cpu
        print(
            f"{kind} {split} epoch {epoch}: {n} samples in {wall:.2f} s = {n / wall:.1f} samples/s "
            f"({workers} workers, batch {batch})" + ("" if workers else f"; CPU {cpu / n * 1e3:.2f} ms per sample")
        )


def _export(workdir: Path, split: str, kind: str, workers: int) -> None:
    from depthgt.data import export_dataset

    os.chdir(workdir)
    with tempfile.TemporaryDirectory(prefix="depthgt-bench-export-") as dest:
        t = time.perf_counter()
        index = export_dataset(Path("results"), Path(dest), "png16", [split], kind, workers=workers, progress=False)
        wall = time.perf_counter() - t
    print(
        f"export {kind} {split} png16: {len(index)} samples in {wall:.2f} s = {len(index) / wall:.1f} samples/s "
        f"({workers} workers)"
    )


def _dump(workdir: Path, split: str, kind: str, out: Path) -> None:
    from depthgt.data import GTDataset

    out = out.resolve()
    os.chdir(workdir)
    ds = GTDataset(Path("results"), split, kind)
    samples = [ds[i] for i in range(len(ds))]
    arrays = {
        k: np.stack([s[k].numpy() for s in samples])
        for k in ("input", "gt", "sigma", "truth", "rgb", "K")
        if k in samples[0]
    }
    arrays["ids"] = np.array([f"{s['dataset']}/{s['scene']}/{s['target']}/{s['patch']}" for s in samples])
    np.savez(out, **arrays)
    print(f"{len(samples)} samples of {kind} {split} -> {out}")


def _compare(a: Path, b: Path) -> None:
    with np.load(a) as x, np.load(b) as y:
        print(f"ids equal: {np.array_equal(x['ids'], y['ids'])} ({len(x['ids'])} vs {len(y['ids'])} samples)")
        for k in sorted(set(x.files) & set(y.files) - {"ids"}):
            if x[k].shape != y[k].shape:
                print(f"{k}: shapes differ {x[k].shape} vs {y[k].shape}")
                continue
            d = np.abs(x[k].astype(np.float64) - y[k].astype(np.float64))
            same = np.array_equal(x[k], y[k])
            both = (x[k] > 0) & (y[k] > 0)
            rel = f", max rel diff {(d[both] / np.abs(x[k][both])).max():.3g}" if k == "sigma" and both.any() else ""
            print(
                f"{k}: identical {same}, max abs diff {d.max():.3g}{rel}, differing elements {(d > 0).mean():.4f}"
                + (
                    f", validity equal {np.array_equal(x[k] > 0, y[k] > 0)}"
                    if k in ("input", "gt", "truth", "sigma")
                    else ""
                )
            )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mode", choices=["bytes", "loader", "export", "dump", "compare"])
    p.add_argument("paths", nargs="+", type=Path, help="the working directory (compare: two dumps)")
    p.add_argument("--split", default="test")
    p.add_argument("--kind", default="patches", choices=["patches", "frames"])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("dump.npz"))
    args = p.parse_args()
    wd = args.paths[0].resolve()
    if args.mode == "bytes":
        _bytes(wd)
    elif args.mode == "loader":
        _loader(wd, args.split, args.kind, args.workers, args.batch, args.epochs)
    elif args.mode == "export":
        _export(wd, args.split, args.kind, args.workers)
    elif args.mode == "dump":
        _dump(wd, args.split, args.kind, args.out)
    else:
        _compare(args.paths[0], args.paths[1])


if __name__ == "__main__":
    main()
