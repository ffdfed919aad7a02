"""The validation study of ``docs/validation.md``: every case, setting and element order.

``run_study(work)`` returns a JSON-ready dict (values rounded to 4 decimals, so reruns give
the same bytes):

* ``kirsch``: {part: {setting: {"min_sj", "inverted", "backed_off", "CPS4": {...}, "CPS8": {...}}}}
  for part quarter / full and setting ``k=<coefficient>`` or ``defaults`` (the smooth
  stage's per-class defaults), all without plane merging; plus ``defaults+merge``, the
  whole default chain of ``dicer run``; and part ``full-offset`` (the full plate with its
  hole centre off the lattice by ``OFFSET``) at the settings ``OFFSET_SETTINGS``.
* ``lame``: {"a=<inner>": {...}} at default smoothing without merging, ``a=7+merge``, and
  ``a=<inner>+fit`` with the surface fitted to the labels (``smooth.surface_from_labels``).
* ``kirsch`` parts ``quarter-scan`` and ``full-scan``, and ``lame-scan``: the same bodies
  from a CT-like grey-value image (``geometry.kirsch_scan``, ``geometry.lame_scan``) by
  ``dicer run`` on the image with ``smooth.surface_from_image`` (the rim pulled onto the
  image's iso-line), at the settings ``scan_settings(part)`` and ``LAME_SCAN_RADII``; parts
  ``quarter-scan-clean`` and ``full-scan-clean``: the plate's image without noise. The
  settings ``pillow`` (and ``lame`` ``a=7+pillow``, ``lame-scan`` ``a=<inner>+pillow``) add
  the pillow layer over the surface (``smooth.pillow``, docs/smoothing.md §3b).
* ``kirsch-reference``: {"CPS4": {...}, "CPS8": {...}}, the ideal O-grid mesh of dicer's
  element size (``reference.kirsch_ogrid``); ``kirsch-square``: the cases' finite plate under
  uniform tension on a converged mesh (``reference.kirsch_square``), its own exact value.
* Every Kirsch order also gives ``kirsch_edges``: the deck solved with Kirsch's displacements
  on the plate's outer edges (``cases.kirsch_edges``), whose exact answer is 3.0.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from dicer.validation import cases, reference

COEFFICIENTS = (0.0, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95)
NO_MERGE = "merge.passes=[0,0,0]"
KIRSCH_RADIUS, KIRSCH_WIDTH = 7.0, 140  # a = 7 voxels, L = 20 a
OFFSET = (0.35, 0.2)  # the full plate's hole centre off the lattice (voxels)
OFFSET_SETTINGS = ("k=0", "k=0.8", "defaults", "defaults+merge", "labels fit", "labels fit+merge",
                   "labels fit+merge, min SJ 0.3")
LAME_RADII = (7.0, 14.0, 28.0)  # inner radius a; outer 2 a
LAME_SCAN_RADII = (7.0, 14.0)
MIN_SJ_03 = "smooth.min_scaled_jacobian=0.3"  # the validation targets' quality floor as the guard's floor
PILLOW = "smooth.pillow=true"  # a layer of elements over the surface (docs/smoothing.md §3b)
FIT = "smooth.surface_from_labels=true"  # the surface fitted to the labels' staircase (docs/smoothing.md §3c)
TODAY = ["smooth.surface_from_image=false", FIT, MIN_SJ_03]  # the base changed to the defaults until 7 December 2026
# the defaults since 7 December 2026: those and the pillow layer, a label volume's staircase
# relaxed (a scan's faces placed by it), the fit over 7 voxels, curved mid-edge nodes
DEFAULTS = TODAY + [PILLOW, "smooth.label_samples=auto", "smooth.label_surface_radius=7", "export.midside_nodes=curved"]
FIT_TO_SCAN = "smooth.fit_to_scan=true"  # the labels' faces placed within their voxels by the scan (§3c)
CURVED = "export.midside_nodes=curved"  # order 2: boundary mid-edge nodes on the surface's curve (arcs on merged meshes)
UNPLACED = "smooth.fit_to_scan=false"  # the labels' faces as they are (the scan's default until 5 December 2026)
SCAN_NOISE = 30.0  # the grey-value images' noise on a contrast of 1000 (the ``-clean`` parts: none)
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
    """The settings of the Kirsch sweep: the coefficient, the defaults (without and with plane
    merging) and the surface fitted to the labels' staircase (``labels fit``); ``curved``: the
    quadratic deck with ``export.midside_nodes: curved``.

    Returns
    -------
    dict of str to list of str
        Setting name -> ``--set`` overrides.
    """
    out = {f"k={k:g}": [NO_MERGE, f"smooth.coefficient={k!r}"] for k in COEFFICIENTS}
    out["defaults"] = [NO_MERGE]
    out["defaults+merge"] = []
    out["labels fit"] = [NO_MERGE, FIT]
    out["labels fit, min SJ 0.3"] = [NO_MERGE, FIT, MIN_SJ_03]
    out["labels fit+merge"] = [FIT]
    out["labels fit+merge, min SJ 0.3"] = [FIT, MIN_SJ_03]
    out["labels fit+merge, min SJ 0.3, curved"] = [FIT, MIN_SJ_03, CURVED]
    out["labels fit, pillow, min SJ 0.3"] = [NO_MERGE, FIT, PILLOW, MIN_SJ_03]
    return out


def scan_settings(part: str = "quarter") -> dict[str, list[str]]:
    """The settings of the grey-value plates: defaults, the guard's floor at 0.3, k = 0.8, a
    wider image smoothing and the whole default chain (the full plate, four times the
    elements, at the first two and the last only); ``today's defaults``: ``dicer run`` on the
    image at its defaults since 5 December 2026 (no pull onto the image: the surface fitted to
    the segmentation's labels with their faces placed by the scan, the floor 0.3, plane
    merging); ``today's defaults, curved``: those with ``export.midside_nodes: curved``;
    ``fit_to_scan=false``: those with the labels' faces as they are.

    Parameters
    ----------
    part : {"quarter", "full"}, optional

    Returns
    -------
    dict of str to list of str
        Setting name -> ``--set`` overrides.
    """
    out = {"defaults": [NO_MERGE], "min SJ 0.3": [NO_MERGE, MIN_SJ_03]}
    if part == "quarter":
        out["k=0.8"] = [NO_MERGE, "smooth.coefficient=0.8"]
        out["image_sigma=1"] = [NO_MERGE, "smooth.image_sigma=1.0"]
    out["defaults+merge"] = []
    out["today's defaults"] = list(TODAY)
    out["today's defaults, curved"] = list(TODAY) + [CURVED]
    out["fit_to_scan=false"] = list(TODAY) + [UNPLACED]
    out["pillow"] = [NO_MERGE, PILLOW]
    out["pillow, min SJ 0.3"] = [NO_MERGE, PILLOW, MIN_SJ_03]
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
    results = {"kirsch": {}, "lame": {}, "lame-scan": {}}
    for part in ("quarter", "full"):
        t0 = time.perf_counter()
        results["kirsch"][part] = _kirsch_rows(work, part, part, kirsch_settings(), log)
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
    r = cases.lame(work / "lame_7_pillow", "quarter", [NO_MERGE, PILLOW], inner=LAME_RADII[0], outer=2 * LAME_RADII[0])
    results["lame"][f"a={LAME_RADII[0]:g}+pillow"] = _named(r, "lame")
    for a in LAME_RADII:
        r = cases.lame(work / f"lame_{a:g}_fit", "quarter", [NO_MERGE, FIT], inner=a, outer=2 * a)
        results["lame"][f"a={a:g}+fit"] = _named(r, "lame")
        log(f"lame a={a:g}+fit: C3D8 {r[1]['error_mean']:+.4f} C3D20 {r[2]['error_mean']:+.4f}")
    r = cases.lame(work / "lame_7_fit_pillow", "quarter", [NO_MERGE, FIT, PILLOW], inner=LAME_RADII[0],
                   outer=2 * LAME_RADII[0])
    results["lame"][f"a={LAME_RADII[0]:g}+fit+pillow"] = _named(r, "lame")
    for a in LAME_RADII[:2]:  # dicer run's defaults: the labels' fit, the floor 0.3, plane merging
        for suffix, sets in (("+today", [FIT, MIN_SJ_03]), ("+today, curved", [FIT, MIN_SJ_03, CURVED])):
            r = cases.lame(work / f"lame_{a:g}{suffix.replace('+', '_').replace(', ', '_')}", "quarter", sets,
                           inner=a, outer=2 * a)
            results["lame"][f"a={a:g}{suffix}"] = _named(r, "lame")
            log(f"lame a={a:g}{suffix}: C3D8 {r[1]['error_mean']:+.4f} C3D20 {r[2]['error_mean']:+.4f}")
    log(f"lame: {time.perf_counter() - t0:.0f} s")
    _run_scans(work, results, log)
    return _rounded(results)


def kirsch_noise_draws(work: str | os.PathLike, sets: list[str], draws: int = 6, log=print) -> dict:
    """The grey-value Kirsch plate, quarter and full, from ``draws`` draws of its image's noise
    (seeds 0 ...), read against Kirsch's own field (exact 3.0).

    The quarter's image is the full plate's quarter of the same draw, so the two share the
    noise about the top of the hole; the full plate also reads the bottom, whose noise is its
    own. How far the two part on one draw is therefore a matter of the noise as much as of the
    mesh: the spread over draws says which.

    Parameters
    ----------
    work : str or os.PathLike
        Where the models and solver runs go.
    sets : list of str
        ``--set`` overrides.
    draws : int, optional
    log : callable, optional

    Returns
    -------
    dict
        ``{"draws": [{"seed", "min_sj", "inverted", part: {element type: (sigma_x(90), largest
        rim stress, its angle)}}], element type: {"quarter_mean", "quarter_sd", "full_mean",
        "full_sd", "largest_error", "apart_mean", "apart_max", "within_3_percent",
        "within_target"}}``: per element type the readings' mean and standard deviation over
        the draws, the largest |reading / 3 - 1| of any part and draw (sigma_x(90) and the
        largest rim stress), quarter and full's |difference| relative to the full plate's, and
        the draws on which both parts are within 3 % with the largest at 90 +- 10 degrees, and
        on which besides they agree within 1 % (the target of docs/validation.md);
        ``"every_type_within_target"``: the draws on which every element type meets it.
    """
    work = Path(work)
    rows = []
    for seed in range(draws):
        row = {"seed": seed, "min_sj": 1.0, "inverted": 0}
        for part in ("quarter", "full"):
            r = cases.kirsch(work / f"kirsch_draw_{seed}_{part}", part, sets, KIRSCH_RADIUS, KIRSCH_WIDTH, scan=True,
                             noise=SCAN_NOISE, seed=seed)
            row["min_sj"] = min(row["min_sj"], r["min_sj"])
            row["inverted"] += r["inverted"]
            row[part] = {ORDER_NAMES["kirsch"][o]: tuple(r[o]["kirsch_edges"][k] for k in
                                                         ("sigma_x_90", "peak", "peak_angle_deg")) for o in (1, 2)}
        log(f"kirsch draw {seed}: quarter {row['quarter']} full {row['full']}")
        rows.append(row)
    out = {"draws": rows}
    met = np.ones(len(rows), bool)
    for name in ORDER_NAMES["kirsch"].values():
        q = np.array([row["quarter"][name] for row in rows])
        f = np.array([row["full"][name] for row in rows])
        apart = np.abs(q[:, 0] / f[:, 0] - 1.0)
        error = np.maximum(np.abs(q[:, :2] / 3.0 - 1.0).max(axis=1), np.abs(f[:, :2] / 3.0 - 1.0).max(axis=1))
        at_90 = (np.abs(q[:, 2] - 90.0) <= 10.0) & (np.abs(f[:, 2] - 90.0) <= 10.0)
        sound = np.array([row["min_sj"] >= 0.3 and row["inverted"] == 0 for row in rows])
        within = (error <= 0.03) & at_90 & sound
        out[name] = {"quarter_mean": float(q[:, 0].mean()), "quarter_sd": float(q[:, 0].std()),
                     "full_mean": float(f[:, 0].mean()), "full_sd": float(f[:, 0].std()),
                     "largest_error": float(error.max()), "apart_mean": float(apart.mean()),
                     "apart_max": float(apart.max()), "within_3_percent": int(within.sum()),
                     "within_target": int((within & (apart <= 0.01)).sum())}
        met &= within & (apart <= 0.01)
    out["every_type_within_target"] = int(met.sum())
    return _rounded(out)


def _kirsch_rows(work: Path, key: str, part: str, settings: dict, log, **scan) -> dict:
    """One Kirsch plate (``part``) at each of ``settings``, solved: rows by setting name."""
    rows = {}
    for name, sets in settings.items():
        r = cases.kirsch(work / f"kirsch_{key}_{name.replace(' ', '_')}", part, sets, KIRSCH_RADIUS, KIRSCH_WIDTH,
                         **scan)
        rows[name] = _named(r, "kirsch")
        log(f"kirsch {key} {name}: CPS4 {r[1]['sigma_x_90']:.4f} CPS8 {r[2]['sigma_x_90']:.4f} "
            f"min SJ {r['min_sj']:.3f}")
    return rows


def _run_scans(work: Path, results: dict, log) -> None:
    """The grey-value cases into ``results`` (parts ``quarter-scan``, ``full-scan``, ``lame-scan``)."""
    t0 = time.perf_counter()
    results["kirsch-reference"] = {ORDER_NAMES["kirsch"][o]: reference.kirsch_ogrid(work / "kirsch_ogrid", o)
                                   for o in (1, 2)}
    results["kirsch-square"] = reference.kirsch_square(work / "kirsch_square")
    clean = {name: sets for name, sets in scan_settings("quarter").items()
             if name in ("defaults", "min SJ 0.3", "pillow", "pillow, min SJ 0.3", "today's defaults",
                         "today's defaults, curved")}
    full_clean = {name: clean[name] for name in ("min SJ 0.3", "pillow, min SJ 0.3")}
    for key, part, noise, settings in (("quarter-scan", "quarter", SCAN_NOISE, scan_settings("quarter")),
                                       ("full-scan", "full", SCAN_NOISE, scan_settings("full")),
                                       ("quarter-scan-clean", "quarter", 0.0, clean),
                                       ("full-scan-clean", "full", 0.0, full_clean)):
        results["kirsch"][key] = _kirsch_rows(work, key, part, settings, log, scan=True, noise=noise)
    log(f"kirsch scans: {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    rows = {}
    for a in LAME_SCAN_RADII:
        for suffix, sets in (("", [NO_MERGE]), ("+pillow", [NO_MERGE, PILLOW])):
            r = cases.lame(work / f"lame_scan_{a:g}{suffix.replace('+', '_')}", "quarter", sets, inner=a, outer=2 * a,
                           scan=True)
            rows[f"a={a:g}{suffix}"] = _named(r, "lame")
            log(f"lame scan a={a:g}{suffix}: C3D8 {r[1]['error_mean']:+.4f} C3D20 {r[2]['error_mean']:+.4f}")
    r = cases.lame(work / "lame_scan_7_merge", "quarter", [], inner=LAME_SCAN_RADII[0], outer=2 * LAME_SCAN_RADII[0],
                   scan=True)
    rows[f"a={LAME_SCAN_RADII[0]:g}+merge"] = _named(r, "lame")
    for a in LAME_SCAN_RADII:  # dicer run's defaults, and the labels' faces as they are
        for suffix, sets in (("+today", TODAY), ("+today, curved", TODAY + [CURVED]),
                             ("+today, fit_to_scan=false", TODAY + [UNPLACED])):
            r = cases.lame(work / f"lame_scan_{a:g}{suffix.replace('+', '_').replace(', ', '_')}", "quarter", sets,
                           inner=a, outer=2 * a, scan=True)
            rows[f"a={a:g}{suffix}"] = _named(r, "lame")
            log(f"lame scan a={a:g}{suffix}: C3D8 {r[1]['error_mean']:+.4f} C3D20 {r[2]['error_mean']:+.4f}")
    results["lame-scan"] = rows
    log(f"lame scans: {time.perf_counter() - t0:.0f} s")
