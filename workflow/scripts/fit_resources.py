"""Fit the resource formula of dicer/resources.py to measured stage peaks.

    python workflow/scripts/fit_resources.py docs/cluster-measurements.tsv

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


if __name__ == "__main__":
    for stage, (base_mb, mb_per_m, base_s, s_per_m) in fit(sys.argv[1]).items():
        print(f'    "{stage}": ({base_mb}, {mb_per_m}, {base_s}, {s_per_m}),')
