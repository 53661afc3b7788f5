"""A training killed in the workflow continues from its last finished epoch (issue 22):
Snakemake deletes the outputs and the log of a killed job before it runs it again, so
the resume state lives in results/models/{model}/resume/, which is not an output."""

from __future__ import annotations

import copy
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml
from conftest import REPO, TINY_ENHANCE, snakemake

# conftest.TINY_ENHANCE (its build is copied) with DDRNet trained for four epochs of two steps
CONFIG = copy.deepcopy(TINY_ENHANCE)
CONFIG["enhance"]["models"] = {"ddrnet": {"model": "ddrnet", "epochs": 4, "model_params": {"channels": 4}}}
CONFIG["evaluation"]["methods"] = ["input", "ddrnet"]
TARGET = "results/models/ddrnet/best.pt"
MODEL_DIR = Path("results/models/ddrnet")


def _weights(path: Path) -> dict:
    return torch.load(path, weights_only=False)


@pytest.mark.slow
def test_killed_training_continues_at_the_next_epoch(tiny_report, tmp_path):
    reference = tmp_path / "reference"  # the session's tiny build (its dataset), training DDRNet
    shutil.copytree(tiny_report, reference, symlinks=True)
    (reference / "config/config.yaml").write_text(yaml.safe_dump(CONFIG))
    snakemake(reference, TARGET)
    assert not (reference / MODEL_DIR / "resume").exists()  # removed once the training ended

    # the same build up to the dataset, without the model
    wd = tmp_path / "killed"
    shutil.copytree(reference, wd, symlinks=True)
    shutil.rmtree(wd / MODEL_DIR)
    (wd / "logs/train/ddrnet.log").unlink()
    hold = tmp_path / "hold"
    env = dict(os.environ, OMP_NUM_THREADS="1", DEPTHGT_TEST_HOLD_DIR=str(hold), DEPTHGT_TEST_HOLD_AT="train:*:epoch=1")
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(wd), "--cores", "2", TARGET]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=env)
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None and not list(hold.glob("*.held")):
            time.sleep(0.05)
    finally:
        # the training waits after writing epoch 1's checkpoint: kill the build there
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert list(hold.glob("*.held")), f"the training never finished epoch 1 (exit code {proc.returncode})"
    assert _weights(wd / MODEL_DIR / "resume/last.pt")["epoch"] == 1
    assert not (wd / TARGET).exists()

    snakemake(wd, TARGET)  # the same command again (--rerun-incomplete, as the default profile)
    log = (wd / "logs/train/ddrnet.log").read_text()
    # the earlier attempt's records are kept, and epochs 0 and 1 are not trained again
    assert log.count("epoch 0: train") == 1 and log.count("epoch 1: train") == 1, log
    assert "from epoch 2 (epochs 0-1 done" in log and log.count("epoch 3: train") == 1
    assert log.index("epoch 1: train") < log.index("from epoch 2") < log.index("epoch 2: train")
    # and it ends as the uninterrupted training did
    for name in ("best.pt", "last.pt"):
        a, b = _weights(reference / MODEL_DIR / name), _weights(wd / MODEL_DIR / name)
        assert (a["epoch"], a["best_epoch"]) == (b["epoch"], b["best_epoch"])
        assert all(torch.equal(a["model_state"][k], b["model_state"][k]) for k in a["model_state"])
    ref_log, got_log = (pd.read_csv(d / MODEL_DIR / "loss_log.csv").drop(columns="seconds") for d in (reference, wd))
    assert list(got_log["epoch"].unique()) == [0, 1, 2, 3]
    pd.testing.assert_frame_equal(got_log, ref_log)
    assert not (wd / MODEL_DIR / "resume").exists()
