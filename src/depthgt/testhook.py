"""Pause points for the tests that kill a running build at a known place.

A job passes named points (``job:<its log file>`` when it starts, ``train:<checkpoint>:epoch=<e>``
after a training epoch's checkpoint is written). Nothing happens unless the environment
variable ``DEPTHGT_TEST_HOLD_DIR`` names a folder: then, at a point that matches the
pattern ``DEPTHGT_TEST_HOLD_AT`` (fnmatch, default ``*``), the process writes a file
there saying where it is and waits until a file ``release`` appears in that folder.
A test can then kill the build while a job is known to be at that point, instead of
polling for a running job and racing it. Standard library only.
"""

from __future__ import annotations

import os
import re
import time
from fnmatch import fnmatchcase
from pathlib import Path

__all__ = ["HOLD_DIR", "HOLD_AT", "hold"]

HOLD_DIR = "DEPTHGT_TEST_HOLD_DIR"
HOLD_AT = "DEPTHGT_TEST_HOLD_AT"


def hold(point: str) -> None:
    """Wait at ``point`` while a test holds this process (see the module docstring);
    return at once otherwise."""
    folder = os.environ.get(HOLD_DIR)
    if not folder or not fnmatchcase(point, os.environ.get(HOLD_AT, "*")):
        return
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    name = re.sub(r"[^A-Za-z0-9_.=-]+", "_", point)[-150:]
    (d / f"{name}.{os.getpid()}.held").write_text(point + "\n")
    while not (d / "release").exists():
        time.sleep(0.05)
