"""Fuzzing of the readers: every mutant of a valid .sens, JPEG, PNG colour or PNG depth
input, and every crafted case of issue 10, ends as a project error or a recorded skip,
within a 512 MiB memory cap, and no frame disappears without a recorded reason.

A few hundred seeded mutants here (about 10 s of CPU); bench/fuzz_readers.py runs
10,000 with the full-size zlib bombs.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fuzz_harness import Case, crafted_cases, mutant_cases, run_fuzz, summarise  # noqa: E402

CAP_MIB = 512


def test_fuzzed_and_crafted_inputs_end_in_project_errors_or_recorded_skips(tmp_path):
    cases = mutant_cases({"sens": 300, "jpeg": 80, "png": 60, "depth_png": 60}, seed=0)
    cases += crafted_cases(bomb_bytes=(6 << 20, 64 << 20))
    cases += [Case("control", name="allocate_1GiB", param=1 << 30)]
    records = run_fuzz(cases, cap_mib=CAP_MIB, tmp=tmp_path)
    by_case = {r["case"]: r for r in records}
    assert len(records) == len(cases)

    # the harness works: an allocation beyond the cap is caught and reported as a failure
    control = by_case.pop("allocate_1GiB")
    assert control["outcome"] == "exception" and "MemoryError" in control["message"]
    records = list(by_case.values())
    summary = summarise(records)
    assert summary["failures"] == [], summary["failures"][:5]
    assert summary["frames_lost_unrecorded"] == 0
    assert summary["peak_mib_max"] is not None and summary["peak_mib_max"] < CAP_MIB
    # the mutants reach every kind of outcome
    assert {"ok", "frame_errors", "source_error"} <= set(summary["outcomes"])
    assert summary["frame_error_reasons"]["unreadable"] > 50 and summary["cases_with_recorded_problems"] > 20

    crafted = {r["case"]: r for r in records if r["kind"] == "crafted"}
    accepted = {"sens_grey_colour", "sens_no_imu_block"}
    recorded = {
        "sens_lowered_frame_count",
        "sens_frame_count_2^64-1",
        "sens_garbage_after_frames",
        "sens_colour_size_2^63",
    }
    stopped = {"sens_name_length_2^60", "sens_header_colour_60000x60000"}
    for name, r in crafted.items():
        if name in accepted:
            assert r["outcome"] == "ok" and r["problems"] == 0, r
        elif name in recorded:
            assert r["problems"] == 1, r
        elif name in stopped:
            assert r["outcome"] == "source_error", r
        else:
            assert r["outcome"] == "frame_errors" and sum(r["frame_errors"].values()) == 1, r
    assert crafted["sens_lowered_frame_count"]["frames_ok"] == 4
    assert re.search(r"holds 2 more frame record", crafted["sens_lowered_frame_count"]["message"])
    assert crafted["depth_png_other_size"]["frame_errors"] == {"size_mismatch": 1}
    for bottom in ("0000", "0002"):
        assert crafted[f"sens_pose_bottom_row_{bottom}"]["frame_errors"] == {"invalid_pose": 1}


def test_fuzzing_is_seeded(tmp_path):
    cases = mutant_cases({"sens": 25, "jpeg": 10}, seed=7)

    def strip(recs):
        return [
            (r["case"], r["outcome"], r["frame_errors"], re.sub(r"/\S+/work/", "", r["message"]))  # noqa: E731
            for r in recs
        ]

    first = strip(run_fuzz(cases, tmp=tmp_path / "a"))
    assert first == strip(run_fuzz(cases, tmp=tmp_path / "b"))
    assert first != strip(run_fuzz(mutant_cases({"sens": 25, "jpeg": 10}, seed=8), tmp=tmp_path / "c"))
