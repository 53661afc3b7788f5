"""`snakemake --lint` has no findings: every rule has a log and a software environment,
no long run blocks, input functions apart from rules."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO


def test_snakemake_lint_is_clean():
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--lint"], cwd=REPO, capture_output=True, text=True)
    findings = [line for line in (proc.stdout + proc.stderr).splitlines() if line.startswith("Lints for")]
    assert proc.returncode == 0 and not findings, proc.stdout[-4000:] + proc.stderr[-4000:]


def test_every_rule_declares_the_environment_file():
    env = REPO / "workflow/envs/depthgt.yaml"
    assert "-e ${DEPTHGT_REPO}" in env.read_text()
