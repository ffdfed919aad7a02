"""Figures (PNG, matplotlib's Agg backend) and Markdown tables of the validation study's results
(the dict of ``study.run_study``). Stresses are divided by the load: sigma_0 (Kirsch), p (Lamé)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dicer.validation.study import COEFFICIENTS, kirsch_settings, scan_settings

KIRSCH_EXACT = 3.0
_PNG = {"dpi": 110, "metadata": {"Software": None}}  # no version string: same bytes on a rerun


def _pct(value: float, exact: float) -> str:
    return f"{100.0 * (value / exact - 1.0):+.1f}"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def kirsch_figure(results: dict, path: str | os.PathLike) -> None:
    """sigma_x / sigma_0 at theta = 90 deg and the largest rim stress against smooth.coefficient.

    One panel per element type, with the minimum scaled Jacobian on a second axis.

    Parameters
    ----------
    results : dict
        From :func:`~dicer.validation.study.run_study`.
    path : str or os.PathLike
        The PNG written.
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    k = np.array(COEFFICIENTS)
    for ax, etype in zip(axes, ("CPS4", "CPS8")):
        ax.axhspan(0.97 * KIRSCH_EXACT, 1.03 * KIRSCH_EXACT, color="0.9", label="3.0 ± 3 %")
        for part, style in (("quarter", "-"), ("full", "--")):
            rows = results["kirsch"][part]
            at90 = [rows[f"k={c:g}"][etype]["sigma_x_90"] for c in COEFFICIENTS]
            peak = [rows[f"k={c:g}"][etype]["peak"] for c in COEFFICIENTS]
            ax.plot(k, at90, style, color="C0", marker="o", ms=4, label=f"σx at 90°, {part}")
            ax.plot(k, peak, style, color="C3", marker="^", ms=4, label=f"largest rim stress, {part}")
        q = results["kirsch"]["quarter"]["defaults"][etype]
        ax.plot([0.85, 0.95], [q["sigma_x_90"]] * 2, ":", color="C0", lw=2, label="σx at 90°, class defaults")
        ax.plot([0.85, 0.95], [q["peak"]] * 2, ":", color="C3", lw=2, label="largest, class defaults")
        ax.set_xlabel("smooth.coefficient (every node class)")
        ax.set_title(f"Kirsch plate, a = 7 voxels, {etype}")
        sj = ax.twinx()
        sj.plot(k, [results["kirsch"]["quarter"][f"k={c:g}"]["min_sj"] for c in COEFFICIENTS], "s-", color="0.45",
                ms=4, label="min scaled Jacobian")
        sj.axhline(0.3, color="0.45", lw=0.8, ls=":")
        sj.set_ylim(0, 1.05)
        sj.set_ylabel("min scaled Jacobian (grey)")
    axes[0].set_ylabel("stress / σ0")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, **_PNG)
    plt.close(fig)


def _finish(plt, fig, ax, path, xlabel: str, ylabel: str, title: str, legend_size: int) -> None:
    """Label a one-panel figure, write it (same bytes on a rerun) and close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=legend_size)
    fig.tight_layout()
    fig.savefig(path, **_PNG)
    plt.close(fig)


def rim_figure(results: dict, path: str | os.PathLike) -> None:
    """Hoop stress along the quarter plate's rim against the angle from the load axis.

    Parameters
    ----------
    results : dict
        As in :func:`kirsch_figure`.
    path : str or os.PathLike
        The PNG.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    theta = np.linspace(0, 90, 181)
    ax.plot(theta, 1 - 2 * np.cos(np.radians(2 * theta)), "k-", lw=1, label="Kirsch: 1 − 2 cos 2θ")
    rows = results["kirsch"]["quarter"]
    for setting, etype, style in (("k=0", "CPS4", "C7"), ("defaults", "CPS4", "C0"), ("defaults", "CPS8", "C3"),
                                  ("defaults+merge", "CPS4", "C2"), ("labels fit", "CPS4", "C4"),
                                  ("labels fit", "CPS8", "C1")):
        if setting not in rows:
            continue
        r = rows[setting][etype]
        ax.plot(r["rim_theta_deg"], r["rim_hoop"], ".-", color=style, ms=3, lw=0.7, label=f"{etype}, {setting}")
    _finish(plt, fig, ax, path, "θ (degrees from the load axis)", "hoop stress / σ0 at the rim nodes",
            "Quarter plate rim, a = 7 voxels", 7)


def lame_figure(results: dict, path: str | os.PathLike) -> None:
    """Bore hoop stress / exact against the inner radius in voxels.

    The mean over the bore nodes, bars from the lowest to the highest node.

    Parameters
    ----------
    results : dict
    path : str or os.PathLike
        The PNG to write.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    rows = dict(sorted(((k, v) for k, v in results["lame"].items() if "+" not in k), key=lambda kv: float(kv[0][2:])))
    a = np.array([float(k[2:]) for k in rows])
    ax.axhspan(0.97, 1.03, color="0.9", label="± 3 %")
    for etype, shift, color in (("C3D8", 0.97, "C0"), ("C3D20", 1.03, "C3")):
        exact = np.array([r[etype]["exact"] for r in rows.values()])
        mean = np.array([r[etype]["mean"] for r in rows.values()]) / exact
        lo = mean - np.array([r[etype]["min"] for r in rows.values()]) / exact
        hi = np.array([r[etype]["max"] for r in rows.values()]) / exact - mean
        ax.errorbar(a * shift, mean, yerr=[lo, hi], fmt="o-", color=color, capsize=3, label=f"{etype}: mean, node range")
        fit = np.array([r[etype]["wall_fit"] for r in rows.values()]) / exact
        ax.plot(a * shift, fit, "D", mfc="none", color=color, label=f"{etype}: wall fit at r = a")
        fits = {float(k[2:].split("+")[0]): r for k, r in results["lame"].items() if k.endswith("+fit")}
        if fits:
            ax.plot(np.array(sorted(fits)) * shift, [fits[k][etype]["mean"] / fits[k][etype]["exact"]
                                                     for k in sorted(fits)],
                    "s", ms=6, mfc="none", color=color, label=f"{etype}: mean, surface fitted to the labels")
        scans = {float(k[2:]): r for k, r in results.get("lame-scan", {}).items() if "+" not in k}
        if scans:
            ax.plot(np.array(sorted(scans)) * shift, [scans[k][etype]["mean"] / scans[k][etype]["exact"]
                                                      for k in sorted(scans)],
                    "*", ms=10, color=color, label=f"{etype}: mean, from the grey-value image")
    ax.set_xscale("log")
    ax.minorticks_off()
    ax.set_xticks(a, [f"{v:g}" for v in a])
    _finish(plt, fig, ax, path, "inner radius a (voxels); outer radius 2a", "bore hoop stress / exact",
            "Lamé cylinder under internal pressure, default smoothing", 7)


def kirsch_table(results: dict, part: str) -> str:
    """Markdown rows of the Kirsch plate.

    Setting, min SJ, inverted, then per element type sigma_x at 90 deg (error %; where
    +90 and -90 deg differ, both follow the mean) and the largest rim stress (error %
    against 3.0, angle); for the grey-value parts (``*-scan*``) also the rim nodes' distance
    from the hole's circle (mean and largest |r - a|, voxels) and the rim fit at 90 deg.

    Parameters
    ----------
    results : dict
    part : str
        ``quarter``, ``full``, ``full-offset``, or a grey-value part: ``quarter-scan``,
        ``full-scan``, ``quarter-scan-clean``, ``full-scan-clean``.

    Returns
    -------
    str
    """
    rim = "-scan" in part
    head = ("| setting | min SJ | inverted | " + ("rim \\|r − a\\| mean / max | " if rim else "")
            + "CPS4 σx(90°) | error % | CPS4 largest (angle) | CPS8 σx(90°) | error % | CPS8 largest (angle) |"
            + (" rim fit at 90° CPS4 / CPS8 (scatter) |" if rim else "") + "\n"
            + "|---" * (11 if rim else 9) + "|\n")
    lines = []
    rows = results["kirsch"][part]
    order = scan_settings("quarter") if rim else kirsch_settings()
    for name in [n for n in order if n in rows]:  # the study's order, whatever the dict's
        r = rows[name]
        cells = [name, f"{r['min_sj']:.3f}", str(r["inverted"])]
        if rim:
            cells.append(f"{r['CPS4']['rim_radius_error_mean']:.3f} / {r['CPS4']['rim_radius_error_max']:.3f}")
        for etype in ("CPS4", "CPS8"):
            e = r[etype]
            each = e["sigma_x_90_each"]
            both = f" ({each[0]:.3f} / {each[1]:.3f})" if len(each) == 2 and abs(each[0] - each[1]) > 5e-4 else ""
            cells += [f"{e['sigma_x_90']:.3f}{both}", _pct(e["sigma_x_90"], KIRSCH_EXACT),
                      f"{e['peak']:.3f} ({_pct(e['peak'], KIRSCH_EXACT)} %, {e['peak_angle_deg']:.0f}°)"]
        if rim:
            c4, c8 = r["CPS4"], r["CPS8"]
            cells.append(f"{c4['rim_fit_90']:.3f} / {c8['rim_fit_90']:.3f} ({c4['rim_fit_scatter']:.2f} / "
                         f"{c8['rim_fit_scatter']:.2f})")
        lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def kirsch_edges_table(results: dict, part: str) -> str:
    """Markdown rows of a Kirsch part solved with Kirsch's displacements on the outer edges.

    Setting, then per element type sigma_x at 90 deg (error % against 3.0, exact for this
    loading), the largest rim stress (error %, angle) and the rim fit at 90 deg.

    Parameters
    ----------
    results : dict
    part : str
        As :func:`kirsch_table`.

    Returns
    -------
    str
    """
    head = ("| setting | CPS4 σx(90°) | error % | CPS4 largest (angle) | CPS8 σx(90°) | error % | "
            "CPS8 largest (angle) | rim fit at 90° CPS4 / CPS8 |\n" + "|---" * 8 + "|\n")
    rows = results["kirsch"][part]
    order = scan_settings("quarter") if "-scan" in part else kirsch_settings()
    lines = []
    for name in [n for n in order if n in rows and "kirsch_edges" in rows[n]["CPS4"]]:
        cells = [name]
        for etype in ("CPS4", "CPS8"):
            e = rows[name][etype]["kirsch_edges"]
            each = e["sigma_x_90_each"]
            both = f" ({each[0]:.3f} / {each[1]:.3f})" if len(each) == 2 and abs(each[0] - each[1]) > 5e-4 else ""
            cells += [f"{e['sigma_x_90']:.3f}{both}", _pct(e["sigma_x_90"], KIRSCH_EXACT),
                      f"{e['peak']:.3f} ({_pct(e['peak'], KIRSCH_EXACT)} %, {e['peak_angle_deg']:.0f}°)"]
        cells.append(f"{rows[name]['CPS4']['kirsch_edges']['rim_fit_90']:.3f} / "
                     f"{rows[name]['CPS8']['kirsch_edges']['rim_fit_90']:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def reference_table(results: dict) -> str:
    """Markdown rows of the O-grid reference (``reference.kirsch_ogrid``): sigma_x at 90 deg.

    Parameters
    ----------
    results : dict

    Returns
    -------
    str
    """
    rows = results.get("kirsch-reference", {})
    lines = [f"| {etype} | {r['elements']} | {r['sigma_x_90']:.3f} | {_pct(r['sigma_x_90'], KIRSCH_EXACT)} |"
             for etype, r in rows.items()]
    square = results.get("kirsch-square")
    if square:  # the cases' finite plate under uniform tension, converged: its own exact value
        lines.append(f"| CPS8, the cases' square plate (L = 20 a) under uniform tension | {square['elements']} | "
                     f"{square['sigma_x_90']:.3f} | {_pct(square['sigma_x_90'], KIRSCH_EXACT)} |")
    return "| element | elements | σx(90°) | error % |\n|---|---|---|---|\n" + "\n".join(lines) + "\n"


def lame_table(results: dict, key: str = "lame") -> str:
    """Markdown rows of the Lamé cylinder.

    Case, elements, min SJ, inverted, per element type the mean bore hoop stress / p, its
    error %, the node range (error % of the lowest and highest node) and the error of the
    wall fit (Lamé's form through the nodes inside the wall, at the bore).

    Parameters
    ----------
    results : dict
    key : str, optional
        ``lame`` (from labels) or ``lame-scan`` (from the grey-value image).

    Returns
    -------
    str
    """
    head = ("| case | elements | min SJ | inverted | exact | C3D8 mean | error % | node range % | "
            "wall fit % | C3D20 mean | error % | node range % | wall fit % |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for name, r in sorted(results[key].items(), key=lambda kv: ("+" in kv[0], float(kv[0][2:].split("+")[0]))):
        cells = [name, str(r["C3D8"]["elements"]), f"{r['min_sj']:.3f}", str(r["inverted"]),
                 f"{r['C3D8']['exact']:.4f}"]
        for etype in ("C3D8", "C3D20"):
            e = r[etype]
            cells += [f"{e['mean']:.3f}", _pct(e["mean"], e["exact"]),
                      f"{_pct(e['min'], e['exact'])} … {_pct(e['max'], e['exact'])}", _pct(e["wall_fit"], e["exact"])]
        lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


_EDGE_PARTS = (("quarter", "quarter plate"), ("full", "full plate"), ("quarter-scan", "grey-value image, quarter plate"),
               ("full-scan", "grey-value image, full plate"),
               ("quarter-scan-clean", "grey-value image without noise, quarter plate"),
               ("full-scan-clean", "grey-value image without noise, full plate"))


def write_all(results: dict, folder: str | os.PathLike) -> str:
    """Write kirsch.png, kirsch_rim.png and lame.png into a folder.

    Parameters
    ----------
    results : dict
    folder : str or os.PathLike

    Returns
    -------
    str
        The Markdown tables.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    kirsch_figure(results, folder / "kirsch.png")
    rim_figure(results, folder / "kirsch_rim.png")
    lame_figure(results, folder / "lame.png")
    return ("### Kirsch, quarter plate\n\n" + kirsch_table(results, "quarter") + "\n### Kirsch, full plate\n\n"
            + kirsch_table(results, "full") + "\n### Kirsch, full plate, hole centre off the lattice\n\n"
            + kirsch_table(results, "full-offset")
            + "\n### Kirsch from a grey-value image, quarter plate\n\n" + kirsch_table(results, "quarter-scan")
            + "\n### Kirsch from a grey-value image, full plate\n\n" + kirsch_table(results, "full-scan")
            + "\n### Kirsch from a grey-value image without noise, quarter plate\n\n"
            + kirsch_table(results, "quarter-scan-clean")
            + "\n### Kirsch from a grey-value image without noise, full plate\n\n"
            + kirsch_table(results, "full-scan-clean")
            + "\n### Kirsch, the O-grid reference (infinite plate, exact 3.0)\n\n" + reference_table(results)
            + "".join(f"\n### Kirsch's displacements on the outer edges (exact 3.0), {title}\n\n"
                      + kirsch_edges_table(results, part) for part, title in _EDGE_PARTS if part in results["kirsch"])
            + "\n### Lamé, quarter cylinder\n\n" + lame_table(results)
            + "\n### Lamé from a grey-value image, quarter cylinder\n\n" + lame_table(results, "lame-scan"))
