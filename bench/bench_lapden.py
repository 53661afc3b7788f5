"""Per-epoch training time of LapDEN presets (CPU, and CUDA when present).

Runs the library's own training step (``depthgt.enhance.train.train_epoch``: batch
assembly, flips, forward, the full multi-scale loss, backward, Adam) on N random
128x128 patch pairs held in memory (noisy slanted planes with holes, so the loss and
its masks do real work). Slow configurations are timed on ``--max-batches`` steps
after ``--warmup`` steps and extrapolated to the full epoch; the output says so.

    python bench/bench_lapden.py                      # both presets, CPU (+ CUDA if any)
    python bench/bench_lapden.py --pairs 2000 --max-batches 10 --json out.json
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time

import torch
from torch.utils.data import Dataset

from depthgt.enhance.lapden import count_parameters, lapden_from_preset
from depthgt.enhance.train import TrainSettings, build_loss, memory_layout, train_epoch


class RandomPatches(Dataset):
    """N random (input, gt) 128x128 pairs: slanted planes, 2 cm noise, 3% holes."""

    def __init__(self, n: int, size: int = 128, seed: int = 0):
        g = torch.Generator().manual_seed(seed)
        u = torch.arange(size, dtype=torch.float32)
        z0 = 1.0 + 3.0 * torch.rand(n, 1, 1, 1, generator=g)
        sx, sy = (0.02 * torch.rand(n, 2, 1, 1, generator=g) - 0.01).unbind(1)
        self.gt = z0 + sx[:, None] * u.view(1, 1, 1, -1) + sy[:, None] * u.view(1, 1, -1, 1)
        noisy = self.gt + 0.02 * torch.randn(self.gt.shape, generator=g)
        self.input = torch.where(torch.rand(self.gt.shape, generator=g) < 0.03, torch.zeros_like(noisy), noisy)
        c = (size - 1) / 2
        self.K = torch.tensor([[230.0, 0.0, c], [0.0, 230.0, c], [0.0, 0.0, 1.0]])

    def __len__(self):
        return len(self.gt)

    def __getitem__(self, i):
        return {"input": self.input[i], "gt": self.gt[i], "K": self.K, "rgb": torch.zeros(3, *self.gt.shape[-2:])}


def bench_one(
    preset: str, device: torch.device, data: RandomPatches, batch_size: int, max_batches: int | None, warmup: int
) -> dict:
    torch.manual_seed(0)
    model = lapden_from_preset(preset).to(device).to(memory_format=memory_layout(device))  # as train() does
    loss_fn = build_loss("lapden", {})
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    n_batches = math.ceil(len(data) / batch_size)
    if warmup:
        warm = TrainSettings(batch_size=batch_size, max_batches_per_epoch=warmup, progress=False)
        train_epoch(model, loss_fn, opt, data, warm, epoch=0, device=device)
    settings = TrainSettings(batch_size=batch_size, max_batches_per_epoch=max_batches, progress=False)
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    terms = train_epoch(model, loss_fn, opt, data, settings, epoch=1, device=device)
    if device.type == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    measured = int(terms["batches"])
    row = {
        "preset": preset,
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
        "threads": torch.get_num_threads(),
        "parameters": count_parameters(model),
        "pairs": len(data),
        "batch_size": batch_size,
        "batches_measured": measured,
        "batches_per_epoch": n_batches,
        "seconds_per_batch": dt / measured,
        "seconds_per_epoch": dt / measured * n_batches,
        "extrapolated": measured < n_batches,
        "loss": terms["total"],
    }
    if device.type == "cuda":
        row["peak_memory_mib"] = torch.cuda.max_memory_allocated(device) / 2**20
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=2000, help="patch pairs per epoch (default dataset: ~2000)")
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--presets", nargs="+", default=["default", "paper"])
    ap.add_argument("--devices", nargs="+", default=["cpu", "cuda"], help="cuda is skipped when absent")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads")
    ap.add_argument(
        "--max-batches",
        type=int,
        default=None,
        help="time only this many steps and extrapolate (default: 20 on CPU, full epoch on CUDA)",
    )
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--json", default=None, help="write the rows here")
    args = ap.parse_args(argv)

    torch.set_num_threads(args.threads)
    data = RandomPatches(args.pairs)
    rows = []
    for dev_name in args.devices:
        if dev_name == "cuda" and not torch.cuda.is_available():
            print("cuda: not available, skipped", file=sys.stderr)
            continue
        device = torch.device(dev_name)
        for preset in args.presets:
            mb = args.max_batches if args.max_batches is not None else (20 if dev_name == "cpu" else None)
            row = bench_one(preset, device, data, args.batch_size, mb, args.warmup)
            rows.append(row)
            extra = f" (extrapolated from {row['batches_measured']} steps)" if row["extrapolated"] else ""
            print(
                f"{preset:8s} {row['device']:5s} {row['parameters']:>9,d} params  "
                f"{row['seconds_per_batch'] * 1e3:8.1f} ms/step  {row['seconds_per_epoch']:9.1f} s/epoch "
                f"of {row['pairs']} pairs{extra}",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
