"""The same bytes on another CPU.

numpy picks its SIMD kernels when it starts, by the CPU (AVX-512, AVX2, the x86-64-v2
baseline on x86), and OpenBLAS its kernels likewise: a cluster's older nodes run other kernels
than a new laptop. dicer's results must not depend on which: its sums are numpy's
reductions in a fixed order, never BLAS products. ``NPY_DISABLE_CPU_FEATURES`` makes this
machine's numpy take the kernels of an older CPU, ``OPENBLAS_CORETYPE`` OpenBLAS's and
``GLIBC_TUNABLES`` the C library's (its exp, log and sin differ without FMA), so whole runs
under them must write the files a run with every feature writes, byte for byte.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

ON = [feature for feature in __cpu_dispatch__ if __cpu_features__.get(feature)]  # ascending
REPO = Path(__file__).resolve().parents[1]


_PROBE = ("import hashlib, math, numpy as np; x = np.linspace(-20.0, 20.0, 100001); "
          "print(hashlib.sha256(np.exp(x).tobytes() + np.tanh(x).tobytes()"
          " + np.array([math.exp(v) + math.sin(v) for v in x]).tobytes()).hexdigest())")
"""numpy's vector exp and tanh and the C library's exp and sin: each differs in the last bit
between the kernels of newer and older CPUs (measured here: numpy's under AVX2 and at the
baseline, the C library's without FMA)."""

_OLD_LIBM = ("glibc.cpu.hwcaps=-AVX512F,-AVX512DQ,-AVX512BW,-AVX512VL,-AVX2,-FMA,-AVX512F_Usable,-AVX2_Usable,"
             "-FMA_Usable")
"""The C library's math without AVX-512, AVX2 and FMA (a CPU before 2013): glibc picks its exp,
log and sin by the CPU too."""


def _probe(env: dict) -> str:
    proc = subprocess.run([sys.executable, "-c", _PROBE], env={**os.environ, **env}, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def _run(folder: Path, env: dict, *args) -> dict[str, str]:
    """``dicer`` with ``args`` (its output folder ``folder``) under ``env``: SHA-256 of every file written."""
    proc = subprocess.run([sys.executable, "-m", "dicer", *map(str, args), "-o", str(folder), "-q"],
                          env={**os.environ, **env}, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.mark.skipif(not ON, reason="numpy dispatches no SIMD kernels on this CPU: nothing to vary")
def test_runs_write_the_same_bytes_with_the_kernels_of_older_cpus(tmp_path):
    # the head phantom's CT (segment, fix, merge, smooth fitted to the scan, every export), and its
    # labels under the static-stress settings (the staircase's relaxation, the pillow layer, C3D20)
    assert subprocess.run([sys.executable, "-m", "dicer", "phantom", "head", "--size", "48", "-o",
                           str(tmp_path / "head.nii.gz"), "-q"], capture_output=True).returncode == 0
    variants = {"every feature": {}}
    if len(ON) > 1:  # the lowest dispatched level only (x86: AVX2 without AVX-512)
        variants[f"{ON[0]} only"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(ON[1:]), "OPENBLAS_CORETYPE": "Haswell"}
    variants["the baseline"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(ON), "OPENBLAS_CORETYPE": "Nehalem",
                                "GLIBC_TUNABLES": _OLD_LIBM}
    # each variant must change the arithmetic the probe sees, or it would prove nothing
    native = _probe({})
    variants = {name: env for name, env in variants.items() if not env or _probe(env) != native}
    if len(variants) == 1:
        pytest.skip("the kernels of older CPUs compute alike here: nothing to compare")
    written = {}
    for i, (name, env) in enumerate(variants.items()):
        scan = _run(tmp_path / f"ct{i}", env, "run", tmp_path / "head.nii.gz", "--set",
                    "workflow.exports=[inp,vtu,k,exo,feb]")
        labels = _run(tmp_path / f"static{i}", env, "run", "--labels", tmp_path / "ct0" / "labels_fixed.nii.gz",
                      "--config", REPO / "config" / "static-stress.yaml")
        written[name] = (scan, labels)
    reference = written["every feature"]
    assert {"model.inp", "model.k", "model.exo", "model.feb", "smoothed.vtu", "quality.json"} <= set(reference[0])
    assert len(reference[1]) >= 15
    for name, files in written.items():
        for ours, theirs in zip(files, reference):
            assert ours == theirs, (name, sorted(k for k in theirs if ours.get(k) != theirs[k]))
