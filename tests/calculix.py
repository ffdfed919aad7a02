"""Running CalculiX from tests: one place for the solver call and the .dat parsing."""

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

CCX = shutil.which("ccx")
needs_ccx = pytest.mark.skipif(CCX is None, reason="CalculiX (ccx) is not installed")


def run_ccx(folder: Path, step: str, model: str | None = "model.inp", timeout: float = 300) -> str:
    """Run ccx on a deck that ``*INCLUDE``s ``model`` (None: ``step`` is the whole deck) and adds
    ``step``; return the .dat text. Fails on a non-zero exit status or an ``*ERROR`` line."""
    deck = step if model is None else f"*INCLUDE, INPUT={model}\n{step}"
    (Path(folder) / "job.inp").write_text(deck)
    proc = subprocess.run([CCX, "-i", "job"], cwd=folder, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "*ERROR" not in log, log[-3000:]
    return (Path(folder) / "job.dat").read_text()


def total_force(dat: str, set_name: str) -> np.ndarray:
    """The last ``*NODE PRINT ... TOTALS=ONLY`` force triple of ``set_name`` in a .dat text."""
    pattern = rf"total force \(fx,fy,fz\) for set {set_name.upper()} and time\s+\S+\s+(\S+)\s+(\S+)\s+(\S+)"
    found = re.findall(pattern, dat)
    assert found, dat[-1000:]
    return np.array([float(v) for v in found[-1]])
