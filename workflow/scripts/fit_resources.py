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


def _upper_bound(size, peak, offset) -> tuple[int, ...]:
    """The coefficients c >= 0 of the least sum of (offset + size c) / peak with no
    offset + size c below its peak (a linear programme), each rounded up to 5 MB."""
    import math

    from scipy.optimize import linprog

    best = linprog((size / peak[:, None]).sum(axis=0), A_ub=-size, b_ub=-(peak - offset),
                   bounds=[(0, None)] * size.shape[1])
    return tuple(5 * math.ceil(c / 5 - 1e-9) for c in best.x)


def fit_run(path: str) -> tuple[tuple[int, int, int], tuple[int, int], int]:
    """RUN_MESH, RUN_MESH_ORDER2 and RUN_RELAXED from whole `dicer run` peaks
    (docs/run-memory.tsv): the baseline, MB per million elements and per million surface faces
    of the smallest upper bound of the order-1 runs of scans; what the order-2 runs of scans need
    on top, per million elements and faces; and the MB per million faces the runs of label
    volumes (their staircase relaxed: rows named ``labels``) need on top of those."""
    import numpy as np

    with open(path, encoding="utf-8") as handle:
        rows = list(csv.DictReader((line for line in handle if not line.startswith("#")), delimiter="\t"))
    scans = [r for r in rows if "labels" not in r["scan"]]
    size = {o: np.array([[1.0, int(r["elements"]) / 1e6, int(r["faces"]) / 1e6] for r in scans if r["order"] == o])
            for o in "12"}
    peak = {o: np.array([float(r["peak_mb"]) for r in scans if r["order"] == o]) for o in "12"}
    linear = _upper_bound(size["1"], peak["1"], 0.0)
    quadratic = _upper_bound(size["2"][:, 1:], peak["2"], size["2"] @ np.array(linear, float))
    extra = 0.0
    for r in rows:
        if "labels" in r["scan"]:
            coef = np.array(linear, float) + (np.r_[0.0, quadratic] if r["order"] == "2" else 0.0)
            need = coef @ [1.0, int(r["elements"]) / 1e6, int(r["faces"]) / 1e6]
            extra = max(extra, (float(r["peak_mb"]) - need) / (int(r["faces"]) / 1e6))
    return linear, quadratic, int(np.ceil(extra / 10.0) * 10)


if __name__ == "__main__":
    if Path(sys.argv[1]).name == "run-memory.tsv":
        linear, quadratic, relaxed = fit_run(sys.argv[1])
        print(f"RUN_MESH = {linear}\nRUN_MESH_ORDER2 = {quadratic}\nRUN_RELAXED = {relaxed}")
    else:
        for stage, (base_mb, mb_per_m, base_s, s_per_m) in fit(sys.argv[1]).items():
            print(f'    "{stage}": ({base_mb}, {mb_per_m}, {base_s}, {s_per_m}),')
