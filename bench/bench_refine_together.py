"""CPU seconds per frame set of `refine` registering a group of frame sets together (the
path a GPU runs, ``refine_source_poses_many``) and one set at a time, on the CPU.

    python3 bench/bench_refine_together.py --framesets 8
    python3 bench/bench_refine_together.py --framesets 8 --against /work/base --repeats 2

Consecutive 7-Scenes frame sets (``../shared/data/7scenes-kitchen``, 256x256, the source's
poses as the start) read through one batch frame cache, a warm-up group of two first; one
torch thread. Printed: CPU s per set together and one by one, and the largest pose
difference between the two. ``--against CHECKOUT`` runs the same in a process with
``CHECKOUT/src`` after each run of this checkout (``--repeats`` times, alternating) and
prints both and their ratio.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

if __name__ == "__main__" and "--src" in sys.argv:  # run another checkout's library (see --against)
    sys.path.insert(0, sys.argv[sys.argv.index("--src") + 1])

import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = next((p for p in (ROOT.parent / "shared", ROOT.parents[1] / "shared") if p.is_dir()), ROOT.parent / "shared")


def measure(n: int) -> dict:
    from depthgt.framecache import FrameCache
    from depthgt.jobs.common import open_source_scene
    from depthgt.registration import load_frameset, poses_from_source
    from depthgt.registration.local import refine_source_poses, refine_source_poses_many
    from depthgt.settings import FrameSetSettings, registration_settings

    source = {"kind": "sevenscenes", "name": "7scenes", "root": str(SHARED / "data/7scenes-kitchen")}
    scene = open_source_scene(source, "7scenes-kitchen", need_poses=True)
    offsets = list(FrameSetSettings().offsets)
    reach = max(abs(o) for o in offsets)
    settings = registration_settings({"method": "refine"})
    out = {}
    for how in ("together", "one_by_one"):
        cache = FrameCache(keep=4 * reach + 2)
        datas = [
            load_frameset(scene, [t + o for o in offsets], (256, 256), True, torch.device("cpu"), cache=cache)
            for t in range(reach, reach + n + 2)
        ]
        warm, timed = datas[:2], datas[2:]

        def run(group, how=how):
            if how == "together":
                return refine_source_poses_many(group, offsets, settings)
            return [
                refine_source_poses(
                    d.rgb, d.depth_m, d.K, offsets, poses_from_source(d), settings, cache=d.cache, positions=d.positions
                )
                for d in group
            ]

        run(warm)
        c0 = time.process_time()
        res = run(timed)
        out[how] = (time.process_time() - c0) / len(timed)
        out[f"T_{how}"] = [r.T_j_to_t.tolist() for r in res]
    diff = max(
        float((torch.tensor(a) - torch.tensor(b)).abs().max()) for a, b in zip(out["T_together"], out["T_one_by_one"])
    )
    return {"together": out["together"], "one_by_one": out["one_by_one"], "pose_diff": diff}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--framesets", type=int, default=8)
    ap.add_argument("--against", help="another checkout (its src/ is used), run after each run of this one")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--src", help=argparse.SUPPRESS)  # internal: the library this process runs
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # internal: one JSON line
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.json:
        print(json.dumps(measure(a.framesets)))
        return
    print(f"command: python3 bench/bench_refine_together.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    for r in range(a.repeats if a.against else 1):
        mine = measure(a.framesets)
        print(
            f"this checkout, run {r}: together {mine['together']:.3f} CPU s per set, one by one "
            f"{mine['one_by_one']:.3f}, largest pose difference {mine['pose_diff']:.2e}"
        )
        if a.against:
            src = str(Path(a.against).absolute() / "src")
            cmd = [sys.executable, __file__, "--src", src, "--json", "--framesets", str(a.framesets)]
            other = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.splitlines()[-1])
            print(
                f"{a.against}, run {r}: together {other['together']:.3f}, one by one {other['one_by_one']:.3f}; "
                f"together, other / this: {other['together'] / mine['together']:.2f}x"
            )


if __name__ == "__main__":
    main()
