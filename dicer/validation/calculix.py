"""Running CalculiX ``ccx`` on a deck and reading the nodal stresses of its .frd output.

Units are the model's: mm and MPa throughout the validation cases.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

from dicer.errors import DicerError

_STRESS = b"\n -4  STRESS"
_LINE = 3 + 10 + 6 * 12  # " -1", node number (10 wide), six values (12 wide): the .frd long format


def ccx_path() -> str | None:
    """The ``ccx`` executable on PATH.

    Returns
    -------
    str or None
        None when there is none.
    """
    return shutil.which("ccx")


def run_ccx(folder: str | os.PathLike, deck: str, job: str = "job", timeout: float = 600) -> Path:
    """Write a deck to ``folder/job.inp`` and solve it with ccx (one thread).

    Parameters
    ----------
    folder : str or os.PathLike
    deck : str
        The deck's text.
    job : str, optional
        Job name.
    timeout : float, optional
        Seconds.

    Returns
    -------
    Path
        ``folder/job.frd``.

    Raises
    ------
    DicerError
        ccx is missing, exits non-zero or reports an *ERROR.
    """
    exe = ccx_path()
    if exe is None:
        raise DicerError("ccx (CalculiX) is not on PATH; install it (Debian/Ubuntu: apt-get install calculix-ccx)")
    folder = Path(folder)
    (folder / f"{job}.inp").write_text(deck)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CCX_NPROC_STIFFNESS": "1", "CCX_NPROC_EQUATION_SOLVER": "1"}
    proc = subprocess.run([exe, "-i", job], cwd=folder, capture_output=True, text=True, timeout=timeout, env=env)
    log = proc.stdout + proc.stderr
    if proc.returncode != 0 or "*ERROR" in log:
        raise DicerError(f"{folder / job}.inp: ccx failed (exit {proc.returncode}): {log[-2000:]}")
    return folder / f"{job}.frd"


def read_frd_stress(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The last nodal STRESS block of an ASCII .frd file.

    The integration-point values extrapolated to the nodes and averaged over the
    elements sharing each node, as ccx writes them.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    nodes : (N,) int64 ndarray
        Node numbers as in the deck, 1-based.
    stress : (N, 6) float64 ndarray
        xx, yy, zz, xy, yz, zx.
    """
    data = Path(path).read_bytes()
    at = data.rfind(_STRESS)
    if at < 0:
        raise DicerError(f"{path}: no nodal STRESS block (ask for it with *EL FILE / S)")
    start = data.index(b"\n -1", at) + 1
    end = data.index(b"\n -3", start) + 1
    block = np.frombuffer(data[start:end], np.uint8)
    if block.size % (_LINE + 1):
        raise DicerError(f"{path}: the STRESS block is not in the fixed-width long format")
    rows = block.reshape(-1, _LINE + 1)
    if not (np.all(rows[:, :3] == np.frombuffer(b" -1", np.uint8)) and np.all(rows[:, -1] == ord("\n"))):
        raise DicerError(f"{path}: unexpected line in the STRESS block")
    ids = rows[:, 3:13].copy().view("S10").ravel().astype(np.int64)
    fields = rows[:, 13:_LINE].copy().view("S12").reshape(-1, 6)
    return ids, fields.astype(np.float64)
