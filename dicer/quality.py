"""Mesh quality report: counts per material, element sizes and shape metrics.

Sits above the mesh package and only reads meshes; nothing in ``dicer.mesh``
imports it.
"""

from __future__ import annotations

import html
import json

import numpy as np

from dicer import __version__
from dicer.config import material_names
from dicer.mesh.metrics import element_metrics
from dicer.mesh.model import Mesh

_PERCENTILES = (1, 5, 25, 50, 75, 95, 99)
_NODE_CLASSES = "ABCDEF"
REPORT_METRICS = ("scaled_jacobian", "edge_ratio", "volume")
"""The element metrics :func:`quality_report` uses."""


def _r(x: float) -> float:
    """Round for a stable, readable report (6 significant digits)."""
    return float(f"{float(x):.6g}")


def _stats(values: np.ndarray) -> dict:
    if values.size == 0:
        return {}
    out = {"min": _r(values.min()), "max": _r(values.max()), "mean": _r(values.mean())}
    for p, v in zip(_PERCENTILES, np.percentile(values, _PERCENTILES)):
        out[f"p{p}"] = _r(v)
    return out


def _material_counts(mesh: Mesh, sj: np.ndarray, vol: np.ndarray) -> dict[str, np.ndarray]:
    """Per material present, ascending: ``label``, ``elements``, ``nodes``, ``volume`` and
    ``min_scaled_jacobian``, each (K,), in passes over all elements (none per material)."""
    material = np.asarray(mesh.material, np.int64)
    size = int(material.max()) + 1 if material.size else 1
    elements = np.bincount(material, minlength=size)
    label = np.flatnonzero(elements)
    lowest = np.full(size, np.inf)
    np.minimum.at(lowest, material, sj)
    nodes = _material_nodes(mesh.cells, material, label, size, mesh.n_points)
    return {"label": label, "elements": elements[label], "nodes": nodes,
            "volume": np.bincount(material, weights=vol, minlength=size)[label], "min_scaled_jacobian": lowest[label]}


def _material_nodes(cells: np.ndarray, material: np.ndarray, label: np.ndarray, size: int, n_points: int
                    ) -> np.ndarray:
    """(K,) the number of distinct nodes of each material ``label`` holds: the distinct
    (node, material) pairs, one flag per pair in an (n_points, K) table when that is no
    larger than the element corners as int64 keys (one pass over the corners), else by
    sorting those keys."""
    k = label.size
    rank = np.zeros(size, np.int64)
    rank[label] = np.arange(k)
    if n_points * k <= cells.size * 8:
        seen = np.zeros((n_points, k), bool)
        seen[cells, rank[material][:, None]] = True
        return np.count_nonzero(seen, axis=0)
    key = cells * np.int64(k)
    key += rank[material][:, None]
    key = key.ravel()
    key.sort(kind="stable")  # element corners come in runs of increasing nodes
    first = np.ones(key.size, bool)
    np.not_equal(key[1:], key[:-1], out=first[1:])
    return np.bincount(key[first] % k, minlength=k)


def quality_report(mesh: Mesh, config: dict, labels=None, metrics: dict | None = None) -> dict:
    """Quality figures of ``mesh`` as a JSON-ready dict.

    mesh : the mesh to assess.
    config : dicer configuration (material names, ``quality.poor_scaled_jacobian``).
    labels : optional label Volume the mesh came from; adds voxel counts and the
        volume of the mesh against the voxel volume per material.
    metrics : the elements' metrics already computed (:func:`dicer.mesh.metrics.element_metrics`
        with at least ``REPORT_METRICS``); computed here when not given.
    """
    names = material_names(config)
    if metrics is None:
        metrics = element_metrics(mesh.points, mesh.cells, REPORT_METRICS)
    sj, vol, er = metrics["scaled_jacobian"], metrics["volume"], metrics["edge_ratio"]
    poor = float(config["quality"]["poor_scaled_jacobian"])
    unit = "mm^3" if mesh.dim == 3 else "mm^2"

    materials = {}
    per = _material_counts(mesh, sj, vol)
    if labels is not None:
        in_volume = np.bincount(np.asarray(labels.array).ravel(), minlength=int(per["label"].max()) + 1)
        voxel_volume = float(np.prod(labels.spacing))
    for i, label in enumerate(per["label"].tolist()):
        entry = {
            "label": label,
            "elements": int(per["elements"][i]),
            "nodes": int(per["nodes"][i]),
            f"volume_{unit}": _r(per["volume"][i]),
            "min_scaled_jacobian": _r(per["min_scaled_jacobian"][i]),
        }
        if labels is not None:
            voxels = int(in_volume[label])
            entry["voxels"] = voxels
            entry[f"voxel_volume_{unit}"] = _r(voxels * voxel_volume)
            if voxels:
                entry["volume_change_percent"] = _r(100.0 * (per["volume"][i] / (voxels * voxel_volume) - 1.0))
        materials[names.get(label, f"material_{label}")] = entry

    report = {
        "dicer_version": __version__,
        "dimension": mesh.dim,
        "element_type": mesh.cell_type,
        "nodes": mesh.n_points,
        "elements": mesh.n_cells,
        "materials": materials,
        f"element_volume_{unit}": {**_stats(vol), "total": _r(vol.sum())},
        "scaled_jacobian": _stats(sj),
        "edge_ratio": _stats(er),
        "inverted_elements": int(np.count_nonzero(sj <= 0)),
        "poor_elements": int(np.count_nonzero(sj < poor)),
        "poor_threshold": poor,
    }
    if "node_class" in mesh.point_data:
        cls = np.asarray(mesh.point_data["node_class"]).astype(np.int64)
        counts = np.bincount(cls, minlength=len(_NODE_CLASSES) + 1)
        report["node_classes"] = {"interior": int(counts[0])} | {
            c: int(counts[i + 1]) for i, c in enumerate(_NODE_CLASSES)
        }
    return report


def render_html(report: dict, pictures: list[str] = ()) -> str:
    """An HTML page of the report: tables, and ``pictures`` (paths relative to the page) shown inline."""

    def table(rows: list[tuple[str, object]]) -> str:
        body = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
        return f"<table>{body}</table>"

    top = [(k, report[k]) for k in ("dimension", "element_type", "nodes", "elements", "inverted_elements",
                                      "poor_elements", "poor_threshold")]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>dicer mesh quality</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin-bottom:1.5em}"
        "th,td{border:1px solid #bbb;padding:3px 8px;text-align:left}</style></head><body>",
        f"<h1>Mesh quality</h1><p>dicer {html.escape(report['dicer_version'])}</p>",
        table(top),
    ]
    for picture in pictures:
        src = html.escape(picture, quote=True)
        parts.append(f"<p><a href='{src}'><img src='{src}' alt='{src}' style='max-width:100%'></a></p>")
    parts.append("<h2>Materials</h2>")
    for name, entry in report["materials"].items():
        parts.append(f"<h3>{html.escape(name)}</h3>" + table(list(entry.items())))
    for key in sorted(k for k in report if k.startswith(("scaled_jacobian", "edge_ratio", "element_volume"))):
        parts.append(f"<h2>{html.escape(key)}</h2>" + table(list(report[key].items())))
    if "node_classes" in report:
        parts.append("<h2>Boundary node classes</h2>" + table(list(report["node_classes"].items())))
    for stage, entry in report.get("stages", {}).items():
        # scalars as they are, small nested values as compact JSON
        rows = [(k, v if not isinstance(v, (dict, list)) else json.dumps(v, sort_keys=True)[:300])
                for k, v in entry.items()]
        parts.append(f"<h2>Stage: {html.escape(stage)}</h2>" + table(rows))
    parts.append("</body></html>\n")
    return "".join(parts)
