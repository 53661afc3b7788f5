"""bench/bench_pipeline.py's per-function profile (``--profile N``): a profile of functions
whose own and cumulative times are known up to the clock, shown per frame set."""

from __future__ import annotations

import cProfile
import importlib.util
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _bench_pipeline():
    spec = importlib.util.spec_from_file_location("bench_pipeline", REPO / "bench/bench_pipeline.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _sleeper() -> None:  # 20 ms of wall clock (cProfile's timer), in time.sleep
    time.sleep(0.02)


def _outer() -> None:  # its own loop, then 20 ms in _sleeper
    x = 0
    for i in range(100_000):
        x += i
    _sleeper()


def _rows(part: str) -> dict[str, tuple[float, float, float]]:
    """function -> (calls, own ms, cumulative ms) of a markdown table of profile_table."""
    out = {}
    for line in part.splitlines():
        cells = [c.strip() for c in line.split("|")[1:-1]]
        if len(cells) == 4 and cells[0] != "function" and not set(cells[1]) <= set("-:"):
            out[cells[0]] = tuple(float(c) for c in cells[1:])
    return out


def test_the_profile_shows_own_and_cumulative_ms_per_frame_set():
    bench = _bench_pipeline()
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(4):  # four "frame sets"
        _outer()
    prof.disable()
    table = bench.profile_table(prof, n_sets=4, top=4)
    own, cumulative = table.split("depthgt's functions")
    rows = _rows(own)
    sleep = rows["<built-in method time.sleep>"]
    outer = next(v for k, v in rows.items() if k.endswith(" _outer"))
    assert sleep[0] == 1.0 and outer[0] == 1.0  # calls per set, not in all four
    assert 19.0 < sleep[1] < 60.0  # 20 ms per set, not 80
    assert outer[2] > outer[1] + sleep[1] - 1.0  # its cumulative time holds the sleep
    assert not _rows(cumulative)  # only the package's functions there, and this test has none
    # a checkout called depthgt holds more than the package: only the package counts
    pkg = Path("/x/depthgt/src/depthgt")
    assert bench._name(("~", 0, "<built-in method time.sleep>"), pkg) == "<built-in method time.sleep>"
    assert bench._name(("/x/depthgt/src/depthgt/gt/build.py", 7, "f"), pkg) == "depthgt/gt/build.py:7 f"
    assert bench._name(("/x/depthgt/tests/test_x.py", 3, "g"), pkg) == "test_x.py:3 g"
    assert not bench._in_package("/x/depthgt/tests/test_x.py", pkg)
    # the test file of this very checkout, profiled against the package under it
    here = Path(__file__).resolve()
    mine = bench.profile_table(prof, n_sets=4, top=4, package=here.parents[1] / "src" / "depthgt")
    assert not _rows(mine.split("depthgt's functions")[1])
