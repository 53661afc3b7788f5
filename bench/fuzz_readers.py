"""Fuzz the source readers: 10,000 seeded mutants of a valid ScanNet ``.sens`` file plus
the crafted cases of issue 10 (headers declaring 60000x60000, 40000x26000, 16000x16000
and 8000x6000 pixels, empty and truncated payloads, 16-bit/RGBA/TIFF colour, zlib bombs
of 1 GiB and 3 GiB, a lowered frame count, degenerate poses, ...), and optionally
mutants of JPEG/PNG colour and PNG depth files read through the 7-Scenes adapter.

Every case opens its scene and reads every frame in a worker process whose address
space is capped (default 512 MiB above its start-up size). Prints the outcome counts,
the frame-error reasons, every failure (an exception that is not the project's, a
timeout or a dead worker), the peak resident memory of a case, and the frames lost
without a recorded reason. Exit status 1 when any acceptance number is not 0.

    python3 bench/fuzz_readers.py                      # 10,000 .sens mutants + crafted
    python3 bench/fuzz_readers.py --images 1000        # + 1,000 of each image kind
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from fuzz_harness import crafted_cases, mutant_cases, run_fuzz, summarise  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sens", type=int, default=10_000, help=".sens mutants")
    ap.add_argument("--images", type=int, default=0, help="mutants of each image kind (jpeg, png, depth_png)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cap-mib", type=int, default=512)
    ap.add_argument(
        "--bombs-mib",
        type=int,
        nargs="*",
        default=[6, 1024, 3072],
        help="inflated sizes of the crafted zlib bombs (6 MiB fits the payload bound of the test geometry)",
    )
    ap.add_argument("--json", type=Path, help="write every case's record here")
    args = ap.parse_args()

    counts = {"sens": args.sens, **({k: args.images for k in ("jpeg", "png", "depth_png")} if args.images else {})}
    cases = mutant_cases(counts, args.seed) + crafted_cases(tuple(m << 20 for m in args.bombs_mib))
    t0, cpu0 = time.time(), resource.getrusage(resource.RUSAGE_CHILDREN)
    records = run_fuzz(cases, cap_mib=args.cap_mib)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    s = summarise(records)

    print(
        f"command: python3 bench/fuzz_readers.py --sens {args.sens} --images {args.images} --seed {args.seed} "
        f"--cap-mib {args.cap_mib} --bombs-mib {' '.join(map(str, args.bombs_mib))}"
    )
    print(
        f"cases: {s['cases']} ({', '.join(f'{k} {v}' for k, v in counts.items())} mutants, "
        f"{len(cases) - sum(counts.values())} crafted)"
    )
    by_kind = Counter((r["kind"], r["outcome"]) for r in records)
    for kind in sorted({k for k, _ in by_kind}):
        print(f"  {kind:10s} " + ", ".join(f"{o} {n}" for (k, o), n in sorted(by_kind.items()) if k == kind))
    print(f"outcomes: {json.dumps(s['outcomes'], sort_keys=True)}")
    print(f"frame-error reasons: {json.dumps(s['frame_error_reasons'], sort_keys=True)}")
    print(f"cases with recorded scene problems: {s['cases_with_recorded_problems']}")
    print(f"exceptions other than the project's (incl. timeouts, dead workers): {len(s['failures'])}")
    for f in s["failures"][:20]:
        print(f"  {f['case']}: {f['outcome']}: {f['message']}")
    print(
        f"peak resident memory of one case: {s['peak_mib_max']} MiB ({s['peak_case']}); "
        f"cases above 512 MiB: {s['cases_over_512_mib']}"
    )
    print(f"frames lost without a recorded reason: {s['frames_lost_unrecorded']}")
    print("crafted:")
    for r in records:
        if r["kind"] == "crafted":
            print(
                f"  {r['case']:34s} {r['outcome']:13s} ok {r['frames_ok']} errors {r['frame_errors']} "
                f"problems {r['problems']} peak {r['peak_mib']} MiB | {r['message'][:110]}"
            )
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    print(f"CPU (user+sys of the workers): {cpu:.1f} s; wall {time.time() - t0:.1f} s (noisy: shared machine)")
    if args.json:
        args.json.write_text(json.dumps(records, indent=1))
    return 0 if not s["failures"] and not s["cases_over_512_mib"] and not s["frames_lost_unrecorded"] else 1


if __name__ == "__main__":
    sys.exit(main())
