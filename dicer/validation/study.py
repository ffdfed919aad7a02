"""The validation study of ``docs/validation.md``: every case, setting and element order.

``run_study(work)`` returns a JSON-ready dict (values rounded to 4 decimals, so reruns give
the same bytes):

* ``kirsch``: {part: {setting: {"min_sj", "inverted", "backed_off", "CPS4": {...}, "CPS8": {...}}}}
  for part quarter / full and setting ``k=<coefficient>`` or ``defaults`` (the smooth
  stage's per-class defaults), all without plane merging; plus ``defaults+merge``, the
  whole default chain of ``dicer run``; and part ``full-offset`` (the full plate with its
  hole centre off the lattice by ``OFFSET``) at the settings ``OFFSET_SETTINGS``.
* ``lame``: {"a=<inner>": {...}} at default smoothing without merging, and ``a=7+merge``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from dicer.validation import cases

COEFFICIENTS = (0.0, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95)
NO_MERGE = "merge.passes=[0,0,0]"
KIRSCH_RADIUS, KIRSCH_WIDTH = 7.0, 140  # a = 7 voxels, L = 20 a
OFFSET = (0.35, 0.2)  # the full plate's hole centre off the lattice (voxels)
OFFSET_SETTINGS = ("k=0", "k=0.8", "defaults", "defaults+merge")
LAME_RADII = (7.0, 14.0, 28.0)  # inner radius a; outer 2 a
ORDER_NAMES = {"kirsch": {1: "CPS4", 2: "CPS8"}, "lame": {1: "C3D8", 2: "C3D20"}}


def _rounded(value):
    if isinstance(value, float):
        return round(value, 4)
    if isinstance(value, dict):
        return {str(k): _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def _named(result: dict, case: str) -> dict:
    return {ORDER_NAMES[case].get(k, k) if isinstance(k, int) else k: v for k, v in result.items()}


def kirsch_settings() -> dict[str, list[str]]:
    """The settings of the Kirsch sweep.

    Returns
    -------
    dict of str to list of str
        Setting name -> ``--set`` overrides.
    """
    out = {f"k={k:g}": [NO_MERGE, f"smooth.coefficient={k!r}"] for k in COEFFICIENTS}
    out["defaults"] = [NO_MERGE]
    out["defaults+merge"] = []
    return out


def run_study(work: str | os.PathLike, log=print) -> dict:
    """Run every case in folders under ``work``.

    Parameters
    ----------
    work : str or os.PathLike
    log : callable, optional
        Called with each line of progress.

    Returns
    -------
    dict
        The results described in the module notes.
    """
    work = Path(work)
    results = {"kirsch": {}, "lame": {}}
    for part in ("quarter", "full"):
        t0 = time.perf_counter()
        rows = {}
        for name, sets in kirsch_settings().items():
            r = cases.kirsch(work / f"kirsch_{part}_{name}", part, sets, KIRSCH_RADIUS, KIRSCH_WIDTH)
            rows[name] = _named(r, "kirsch")
            log(f"kirsch {part} {name}: CPS4 {r[1]['sigma_x_90']:.4f} CPS8 {r[2]['sigma_x_90']:.4f} "
                f"min SJ {r['min_sj']:.3f}")
        results["kirsch"][part] = rows
        log(f"kirsch {part}: {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    rows = {}
    for name in OFFSET_SETTINGS:
        r = cases.kirsch(work / f"kirsch_offset_{name}", "full", kirsch_settings()[name], KIRSCH_RADIUS, KIRSCH_WIDTH,
                         offset=OFFSET)
        rows[name] = _named(r, "kirsch")
        log(f"kirsch full-offset {name}: CPS4 {r[1]['sigma_x_90_each']} CPS8 {r[2]['sigma_x_90_each']}")
    results["kirsch"]["full-offset"] = rows
    log(f"kirsch full-offset: {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    for a in LAME_RADII:
        r = cases.lame(work / f"lame_{a:g}", "quarter", [NO_MERGE], inner=a, outer=2 * a)
        results["lame"][f"a={a:g}"] = _named(r, "lame")
        log(f"lame a={a:g}: C3D8 {r[1]['error_mean']:+.4f} C3D20 {r[2]['error_mean']:+.4f}")
    r = cases.lame(work / "lame_7_merge", "quarter", [], inner=LAME_RADII[0], outer=2 * LAME_RADII[0])
    results["lame"][f"a={LAME_RADII[0]:g}+merge"] = _named(r, "lame")
    log(f"lame: {time.perf_counter() - t0:.0f} s")
    return _rounded(results)
