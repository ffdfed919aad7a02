"""Fit the resource formula of dicer/resources.py to measured stage peaks.

    python workflow/scripts/fit_resources.py docs/cluster-measurements.tsv
    python workflow/scripts/fit_resources.py docs/run-memory.tsv          # RUN_MESH

Per stage: the baseline is the smallest measured peak (the Python interpreter with numpy,
scipy, SimpleITK and meshio loaded: it dominates small cases), the slope the largest
(peak - baseline) / size over the cases, size being the stage's input size (scan voxels,
voxels after downsampling, or mesh elements; dicer.resources.SIZE_OF). The same for
seconds. Prints the COEFFICIENTS table that dicer/resources.py holds.
"""

import csv
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from dicer.resources import SIZE_OF  # noqa: E402


def fit(path: str) -> dict[str, tuple[float, float, float, float]]:
    rows = defaultdict(list)
    with open(path, encoding="utf-8") as handle:
        for row in csv.DictReader((line for line in handle if not line.startswith("#")), delimiter="\t"):
            rows[row["stage"]].append(row)
    table = {}
    for stage, measured in rows.items():
        sizes = [int(r[SIZE_OF[stage]]) / 1e6 for r in measured]
        peaks = [float(r["max_rss_mb"]) for r in measured]
        seconds = [float(r["seconds"]) for r in measured]
        base_mb, base_s = min(peaks), min(seconds)
        mb_per_m = max((p - base_mb) / x for p, x in zip(peaks, sizes))
        s_per_m = max((s - base_s) / x for s, x in zip(seconds, sizes))
        table[stage] = (round(base_mb), round(mb_per_m, 1), round(base_s, 1), round(s_per_m, 1))
    return table


def fit_run(path: str) -> tuple[int, int, int]:
    """RUN_MESH from whole `dicer run` peaks (docs/run-memory.tsv): the baseline, MB per
    million elements and per million surface faces of the smallest upper bound (a linear
    programme: the sum of estimate / peak least, no estimate below its peak), each rounded up
    to 5 MB."""
    import math

    import numpy as np
    from scipy.optimize import linprog

    with open(path, encoding="utf-8") as handle:
        rows = list(csv.DictReader((line for line in handle if not line.startswith("#")), delimiter="\t"))
    size = np.array([[1.0, int(r["elements"]) / 1e6, int(r["faces"]) / 1e6] for r in rows])
    peak = np.array([float(r["peak_mb"]) for r in rows])
    best = linprog((size / peak[:, None]).sum(axis=0), A_ub=-size, b_ub=-peak, bounds=[(0, None)] * 3)
    return tuple(5 * math.ceil(c / 5 - 1e-9) for c in best.x)


if __name__ == "__main__":
    if Path(sys.argv[1]).name == "run-memory.tsv":
        print(f"RUN_MESH = {fit_run(sys.argv[1])}")
    else:
        for stage, (base_mb, mb_per_m, base_s, s_per_m) in fit(sys.argv[1]).items():
            print(f'    "{stage}": ({base_mb}, {mb_per_m}, {base_s}, {s_per_m}),')
