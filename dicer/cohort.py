"""Cohort overview: one row per patient from its quality report and its stages' benchmarks.

Pure functions on already-read data (``dicer cohort`` reads the files): the quality reports
(``quality.json``) and Snakemake's ``benchmark:`` lines (wall seconds ``s`` and peak resident
memory ``max_rss`` in MB per stage).
"""

from __future__ import annotations

import html

from dicer.quality import STYLE

#: stages in pipeline order (others follow alphabetically)
STAGE_ORDER = ("phantom", "segment", "labels", "downsample", "fix", "mesh", "merge", "smooth", "export_inp",
               "export_vtu", "export_out", "export_neu", "export_k", "export_msh", "export_exo", "export_e",
               "export_feb", "quality")


def _stages(benchmarks: dict[str, dict[str, dict]]) -> list[str]:
    seen = {stage for stages in benchmarks.values() for stage in stages}
    return [s for s in STAGE_ORDER if s in seen] + sorted(seen - set(STAGE_ORDER))


def _materials(reports: dict[str, dict]) -> list[str]:
    names: list[str] = []
    for report in reports.values():
        names += [n for n in report.get("materials", {}) if n not in names]
    return names


def _number(value) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):  # Snakemake writes NA for a stage too short to sample
        return None
    return out if out == out else None


def report_problem(report) -> str | None:
    """What keeps ``report`` from being read as a quality report, or None.

    Parameters
    ----------
    report : object
        A parsed ``quality.json``.

    Returns
    -------
    str or None
        e.g. ``"'materials' is a list, not an object"``.
    """
    if not isinstance(report, dict):
        return f"the file holds a {type(report).__name__}, not an object"
    if "elements" not in report:
        return "no element count"
    parts = report.get("parts", {})
    sections = {"scaled_jacobian": report.get("scaled_jacobian", {}), "parts": parts,
                "characteristic_length_mm": report.get("characteristic_length_mm", {}),
                "explicit_time_step": report.get("explicit_time_step", {}),
                "materials": report.get("materials", {}), "library_versions": report.get("library_versions", {}),
                "parts.model": parts.get("model", {}) if isinstance(parts, dict) else {}}
    for name, value in sections.items():
        if not isinstance(value, dict):
            return f"{name!r} is a {type(value).__name__}, not an object"
    numbers = {k: report.get(k) for k in ("elements", "nodes", "inverted_elements", "poor_elements",
                                          "stretched_elements")}
    numbers |= {f"scaled_jacobian.{k}": sections["scaled_jacobian"].get(k) for k in ("min", "p1")}
    numbers["characteristic_length_mm.min"] = sections["characteristic_length_mm"].get("min")
    numbers["explicit_time_step.smallest_s"] = sections["explicit_time_step"].get("smallest_s")
    numbers |= {f"parts.model.{k}": sections["parts.model"].get(k) for k in ("parts", "floating_elements")}
    for name, material in sections["materials"].items():
        if not isinstance(material, dict):
            return f"'materials.{name}' is a {type(material).__name__}, not an object"
        numbers |= {f"materials.{name}.{k}": material.get(k)
                    for k in ("volume_change_percent", "original_volume_change_percent")}
    for name, value in numbers.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            return f"{name!r} is {value!r}, not a number"
    for name, version in sections["library_versions"].items():
        if not isinstance(version, str):
            return f"'library_versions.{name}' is {version!r}, not a version"
    if not isinstance(report.get("dicer_version", ""), str):
        return f"'dicer_version' is {report['dicer_version']!r}, not a version"
    for key in ("materials_without_elements", "topology_changed"):
        listed = report.get(key, [])
        if not isinstance(listed, list) or not all(isinstance(m, str) for m in listed):
            return f"{key!r} is {listed!r}, not a list of names"
    if "scaled_jacobian" not in report:  # a stage's report (smooth.json) counts elements too
        return "no scaled Jacobian: a stage's report?"
    return None


def cohort_rows(reports: dict[str, dict], benchmarks: dict[str, dict[str, dict]] | None = None) -> tuple[list[str], list[list]]:
    """The cohort table: column names, one row per patient in the order of ``reports``.

    Columns: patient, elements, nodes, min_scaled_jacobian, p1_scaled_jacobian, inverted,
    poor, stretched (edge ratio above the quality stage's limit; missing in reports made
    before it was counted), parts (face-connected parts of the model), floating_elements,
    materials_without_elements and topology_changed (material names, space-separated; missing
    in reports made before they were listed), poor_threshold, stretched_threshold,
    min_characteristic_length_mm (the smallest element length, which sets an explicit solver's
    time step; missing in reports made before it was measured), explicit_time_step_s (that step
    with the materials' wave speeds, the smallest over the elements; missing in reports made
    before it was given), per material
    ``volume_change_percent:<name>`` (against the meshed labels) and
    ``original_volume_change_percent:<name>`` (against the full-resolution segmentation),
    per stage ``seconds:<stage>`` and ``peak_mb:<stage>``.

    Parameters
    ----------
    reports : dict of str to dict
        Patient -> quality report (``dicer quality``'s JSON).
    benchmarks : dict, optional
        Patient -> stage -> a benchmark line as a dict (keys ``s``, ``max_rss``).

    Returns
    -------
    columns : list of str
    rows : list of list
        A missing value is None.
    """
    benchmarks = benchmarks or {}
    materials = _materials(reports)
    stages = _stages(benchmarks)
    columns = ["patient", "elements", "nodes", "min_scaled_jacobian", "p1_scaled_jacobian", "inverted", "poor",
               "stretched", "parts", "floating_elements", "materials_without_elements", "topology_changed",
               "poor_threshold", "stretched_threshold", "min_characteristic_length_mm", "explicit_time_step_s"]
    columns += [f"volume_change_percent:{m}" for m in materials]
    columns += [f"original_volume_change_percent:{m}" for m in materials]
    columns += [f"{kind}:{s}" for s in stages for kind in ("seconds", "peak_mb")]
    rows = []
    for patient, r in reports.items():
        sj = r.get("scaled_jacobian", {})
        parts = r.get("parts", {}).get("model", {})
        row = [patient, r.get("elements"), r.get("nodes"), sj.get("min"), sj.get("p1"), r.get("inverted_elements"),
               r.get("poor_elements"), r.get("stretched_elements"), parts.get("parts"), parts.get("floating_elements")]
        for key in ("materials_without_elements", "topology_changed"):  # None in reports made before
            names = r.get(key)
            row.append(None if names is None else " ".join(names))
        row += [r.get("poor_threshold"), r.get("stretched_threshold")]  # a patient's config may set its own
        row.append(r.get("characteristic_length_mm", {}).get("min"))
        row.append(r.get("explicit_time_step", {}).get("smallest_s"))
        mats = r.get("materials", {})
        row += [mats.get(m, {}).get("volume_change_percent") for m in materials]
        row += [mats.get(m, {}).get("original_volume_change_percent") for m in materials]
        bench = benchmarks.get(patient, {})
        for s in stages:
            row += [_number(bench.get(s, {}).get("s")), _number(bench.get(s, {}).get("max_rss"))]
        rows.append(row)
    return columns, rows


def _cell(value, spec: str = "") -> str:
    return "–" if value is None else (format(value, spec) if spec else str(value))


def cohort_tsv(columns: list[str], rows: list[list]) -> str:
    """The table as tab-separated text (empty cells for missing values).

    Parameters
    ----------
    columns, rows : list
        From :func:`cohort_rows`.

    Returns
    -------
    str
    """
    lines = ["\t".join(columns)]
    lines += ["\t".join("" if v is None else str(v) for v in row) for row in rows]
    return "\n".join(lines) + "\n"


def _own(row: list, where: int | None, heading, sign: str) -> str:
    """" (< t)": the row's own threshold where it is not the heading's."""
    mine = None if where is None else row[where]
    return "" if mine is None or mine == heading else f" ({sign} {mine:g})"


def render_cohort_html(columns: list[str], rows: list[list], poor_threshold: float | None = None) -> str:
    """The cohort overview as one self-contained HTML table.

    A patient with an inverted element, a floating part, a material without elements or a
    surface whose topology merging changed is highlighted.

    Parameters
    ----------
    columns, rows : list
        From :func:`cohort_rows`.
    poor_threshold : float, optional
        The scaled Jacobian below which an element counts as poor, shown in the heading; a
        row counted below another one (its column ``poor_threshold``) shows its own beside
        its count, and so does a row whose ``stretched_threshold`` differs from the first row's.

    Returns
    -------
    str
    """
    at = {c: i for i, c in enumerate(columns)}
    stretched_at = next((row[at["stretched_threshold"]] for row in rows if "stretched_threshold" in at
                         and row[at["stretched_threshold"]] is not None), None)
    materials = [c.split(":", 1)[1] for c in columns if c.startswith("volume_change_percent:")]
    stages = [c.split(":", 1)[1] for c in columns if c.startswith("seconds:")]
    head1 = ("<tr><th rowspan='2'>patient</th><th rowspan='2'>elements</th><th rowspan='2'>nodes</th>"
             "<th colspan='2'>scaled Jacobian</th><th rowspan='2'>inverted</th><th rowspan='2'>poor"
             + (f" (&lt; {poor_threshold:g})" if poor_threshold is not None else "") + "</th>"
             "<th rowspan='2'>stretched" + (f" (edge ratio &gt; {stretched_at:g})" if stretched_at is not None else "")
             + "</th><th rowspan='2'>parts</th><th rowspan='2'>floating elements</th>"
             "<th rowspan='2'>materials without elements</th><th rowspan='2'>surface topology changed</th>"
             "<th rowspan='2'>smallest element length, mm</th><th rowspan='2'>explicit time step, s</th>"
             + (f"<th colspan='{len(materials)}'>volume change, % (against meshed labels / original)</th>"
                if materials else "")
             + (f"<th colspan='{len(stages)}'>seconds / peak MB per stage</th>" if stages else "") + "</tr>")
    head2 = ("<tr><th>min</th><th>p1</th>" + "".join(f"<th>{html.escape(m)}</th>" for m in materials)
             + "".join(f"<th>{html.escape(s)}</th>" for s in stages) + "</tr>")
    body = []
    for row in rows:
        warn = (bool(row[at["inverted"]]) or (row[at["parts"]] or 1) > 1
                or bool(row[at["materials_without_elements"]]) or bool(row[at["topology_changed"]]))
        cells = [html.escape(str(row[at["patient"]])), _cell(row[at["elements"]]), _cell(row[at["nodes"]]),
                 _cell(row[at["min_scaled_jacobian"]], ".3f"), _cell(row[at["p1_scaled_jacobian"]], ".3f"),
                 _cell(row[at["inverted"]]),
                 _cell(row[at["poor"]]) + _own(row, at.get("poor_threshold"), poor_threshold, "&lt;"),
                 _cell(row[at["stretched"]]) + _own(row, at.get("stretched_threshold"), stretched_at, "&gt;"),
                 _cell(row[at["parts"]]),
                 _cell(row[at["floating_elements"]]),
                 html.escape(_cell(row[at["materials_without_elements"]])),
                 html.escape(_cell(row[at["topology_changed"]])),
                 _cell(row[at["min_characteristic_length_mm"]], ".3f"),
                 _cell(row[at["explicit_time_step_s"]], ".3g")]
        cells += [f"{_cell(row[at[f'volume_change_percent:{m}']], '+.1f')} / "
                  f"{_cell(row[at[f'original_volume_change_percent:{m}']], '+.1f')}" for m in materials]
        cells += [f"{_cell(row[at[f'seconds:{s}']], '.1f')} / {_cell(row[at[f'peak_mb:{s}']], '.0f')}"
                  for s in stages]
        body.append(f"<tr{' class=warn' if warn else ''}>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>dicer cohort</title>"
            f"<style>{STYLE}</style></head><body><h1>Cohort overview</h1>"
            f"<p>{len(rows)} patient(s). Parts: the model's face-connected parts (more than one: a part "
            "floats). Volume change: the mesh against the voxels it was made from, and against the "
            "original full-resolution segmentation. Smallest element length: its volume over its largest "
            "face; over the material's wave speed, it gives an element's stable explicit time step, the "
            "smallest of which is the model's (before the solver's safety factor). Seconds and peak memory: Snakemake's benchmark of "
            "each stage (– where none was recorded).</p>"
            f"<table>{head1}{head2}{''.join(body)}</table></body></html>\n")
