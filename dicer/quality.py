"""Mesh quality report: counts per material, element sizes and shape metrics.

Sits above the mesh package and only reads meshes; nothing in ``dicer.mesh``
imports it.
"""

from __future__ import annotations

import base64
import html
import json

import numpy as np

from dicer import __version__, library_versions
from dicer.arrays import nonzero
from dicer.config import takes_settings
from dicer.image import count_labels
from dicer.mesh.metrics import characteristic_length, element_metrics
from dicer.mesh.model import Mesh

_PERCENTILES = (1, 5, 25, 50, 75, 95, 99)
_NODE_CLASSES = "ABCDEFX"  # X: irregular nodes (dicer.mesh.boundary.NODE_CLASSES)
REPORT_METRICS = ("scaled_jacobian", "edge_ratio", "volume", "characteristic_length")
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


def wave_speeds(materials: list[dict], plane_stress: bool = False) -> np.ndarray:
    """Each material's wave speed that an explicit solver's stable time step divides an
    element's length by: the dilatational one, sqrt(E (1 - nu) / (rho (1 + nu) (1 - 2 nu))),
    for solids and plane strain; sqrt(E / (rho (1 - nu^2))) for plane stress.

    Parameters
    ----------
    materials : list of dict
        Label 1 first: ``youngs_modulus`` (MPa), ``poissons_ratio``, ``density`` (t/mm^3).
    plane_stress : bool, optional
        2D elements in plane stress (CPS4, CPS8: the 2D default).

    Returns
    -------
    (K + 1,) float64 ndarray
        mm/s, indexed by label (0: nan).
    """
    e, nu, rho = (np.array([float(m[k]) for m in materials]) for k in ("youngs_modulus", "poissons_ratio", "density"))
    if plane_stress:
        return np.r_[np.nan, np.sqrt(e / (rho * (1.0 - nu * nu)))]
    return np.r_[np.nan, np.sqrt(e * (1.0 - nu) / (rho * (1.0 + nu) * (1.0 - 2.0 * nu)))]


MASS_SCALING_STEPS = (1.5, 2.0, 4.0)
"""Time steps, as multiples of the model's smallest, at which the report gives the mass that
mass scaling (LS-DYNA's DT2MS, Abaqus' fixed mass scaling) adds to reach them."""


def explicit_time_step(length: np.ndarray, volume: np.ndarray, material: np.ndarray, speeds: np.ndarray,
                       densities: np.ndarray) -> dict:
    """An explicit solver's stable time step and what mass scaling to longer ones costs.

    Each element's step is its characteristic length over its material's wave speed; the
    model's is the smallest (before the solver's safety factor, LS-DYNA's TSSFAC 0.9). Mass
    scaling gives each element faster than a target step the mass that slows it to it:
    (target / step)^2 times its own.

    Parameters
    ----------
    length, volume : (M,) float64 ndarray
        mm (:func:`dicer.mesh.metrics.characteristic_length`) and mm^3 (mm^2 in 2D: per mm of
        thickness).
    material : (M,) int ndarray
        Labels, 1..K.
    speeds, densities : (K + 1,) float64 ndarray
        mm/s (:func:`wave_speeds`) and t/mm^3, indexed by label.

    Returns
    -------
    dict
        ``smallest_s``, ``element`` (numbered from 1 in mesh order, as the decks number them),
        ``material`` (its label), ``mass_scaling``: for each of ``MASS_SCALING_STEPS``,
        ``{"times_smallest", "time_step_s", "mass_added_percent", "elements_scaled"}``, and
        ``smallest_by_material``: label -> that material's smallest step.
    """
    step = length / speeds[material]
    worst = int(np.argmin(step))
    smallest = float(step[worst])
    mass = densities[material] * np.abs(volume)
    total = float(mass.sum())
    scaling = []
    for times in MASS_SCALING_STEPS:
        target = times * smallest
        slow = step < target
        added = float(np.sum(mass[slow] * ((target / step[slow]) ** 2 - 1.0)))
        scaling.append({"times_smallest": times, "time_step_s": _r(target),
                        "mass_added_percent": _r(100.0 * added / total), "elements_scaled": int(np.count_nonzero(slow))})
    by_label = np.full(speeds.size, np.inf)
    np.minimum.at(by_label, material, step)
    return {"smallest_s": _r(smallest), "element": worst + 1, "material": int(material[worst]),
            "mass_scaling": scaling,
            "smallest_by_material": {int(k): _r(by_label[k]) for k in np.flatnonzero(np.isfinite(by_label))}}


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


def element_neighbours(mesh: Mesh) -> np.ndarray:
    """The element across each face (2D: edge) of any conforming mesh.

    A voxel mesh of its lattice (smoothed or not) reads them off its voxel grid; any
    other mesh matches faces by their nodes.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    (M, F) int64 ndarray
        Element index, -1 for none.
    """
    from dicer.mesh.faces import face_neighbours, voxel_face_neighbours

    nb = voxel_face_neighbours(mesh)
    if nb is None:
        nb = face_neighbours(np.asarray(mesh.cells, np.int64), mesh.dim, mesh.n_points)
    return nb


def surface_euler(mesh: Mesh, neighbours: np.ndarray) -> dict[int, int]:
    """The Euler characteristic of each material's surface in a 3D mesh: V - E + F of the
    element faces it shares with no element of its own material.

    A closed surface of g holes has 2 - 2g; a material of c parts, each with g holes and
    v cavities, sums to 2 (c + v - g). Merging that fills a hole or a cavity changes it.

    Parameters
    ----------
    mesh : Mesh
        3D (hexahedra, 8 or 20 nodes; the corners are used).
    neighbours : (M, 6) int ndarray
        :func:`element_neighbours`.

    Returns
    -------
    dict of int to int
        Label -> Euler characteristic, for the labels with elements.
    """
    from dicer.mesh.topology import HEX_FACES

    cells = np.asarray(mesh.cells)[:, :8]
    material = np.asarray(mesh.material)
    nb = np.asarray(neighbours)
    other = np.where(nb >= 0, material[np.maximum(nb, 0)], -1)
    elem, face = nonzero(other != material[:, None])
    faces = cells[elem[:, None], HEX_FACES[face]].astype(np.int64)  # (F, 4)
    mats = material[elem]
    order = np.argsort(mats, kind="stable")
    faces, mats = faces[order], mats[order]
    starts = np.flatnonzero(np.r_[True, mats[1:] != mats[:-1]])
    seen = np.zeros(mesh.n_points, bool)
    return {int(label): _quads_euler(f, seen) for label, f in zip(mats[starts].tolist(), np.split(faces, starts[1:]))}


def _quads_euler(quads: np.ndarray, seen: np.ndarray) -> int:
    """V - E + F of a set of quadrilaterals (Q, 4) int64 of node numbers; ``seen``: an (N,)
    bool scratch array (its contents are overwritten)."""
    n = seen.size
    seen[:] = False
    seen[quads.ravel()] = True
    a, b = quads.ravel(), np.roll(quads, -1, axis=1).ravel()
    keys = np.sort(np.minimum(a, b) * n + np.maximum(a, b))  # counted by sorting: np.unique hashes slowly here
    edges = int(np.count_nonzero(keys[1:] != keys[:-1])) + 1
    return int(np.count_nonzero(seen)) - edges + quads.shape[0]


def region_euler(mesh: Mesh) -> dict[int, int]:
    """The Euler characteristic of each material's region in a 2D mesh: V - E + F of its
    quadrilaterals (parts less holes).

    Parameters
    ----------
    mesh : Mesh
        2D (4- or 8-node quadrilaterals; the corners are used).

    Returns
    -------
    dict of int to int
        Label -> Euler characteristic, for the labels with elements.
    """
    cells = np.asarray(mesh.cells)[:, :4].astype(np.int64)
    material = np.asarray(mesh.material)
    seen = np.zeros(mesh.n_points, bool)
    return {int(label): _quads_euler(cells[material == label], seen) for label in np.unique(material).tolist()}


def voxel_euler(labels: np.ndarray, which) -> dict[int, int]:
    """The Euler characteristic each label's voxels give what :func:`surface_euler` (3D:
    twice the voxels', that of their surface) or :func:`region_euler` (2D) counts, for the
    labels ``which``.

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        Fixed labels (no edge or corner contacts: every connectivity gives one answer).
    which : iterable of int

    Returns
    -------
    dict of int to int
    """
    from scipy import ndimage
    from skimage.measure import euler_number

    labels = np.asarray(labels)
    boxes = ndimage.find_objects(labels)
    out = {}
    for label in which:
        box = boxes[label - 1] if 0 < label <= len(boxes) else None
        if box is None:
            continue
        value = int(euler_number(np.pad(labels[box] == label, 1), connectivity=1))
        out[int(label)] = 2 * value if labels.ndim == 3 else value
    return out


def _grid_parts(shape: tuple[int, ...], voxel: np.ndarray, material: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face-connected parts of a voxel mesh (each element's ``voxel`` in the grid of
    ``shape``, :func:`dicer.mesh.faces.voxel_elements`) by labelling its voxel grid: its
    voxels are its elements, and face neighbours are voxels next to each other along an axis.

    Returns the element count of each part of the model, and of each part of one material
    with that material: (model sizes, part materials, part sizes).
    """
    from scipy import ndimage
    from skimage.measure import label as label_regions

    top = int(material.max())
    kind = np.uint8 if top < 256 else np.uint16 if top < 65536 else np.int64
    grid = np.zeros(int(np.prod(shape)), kind)  # 0: no element
    grid[voxel] = material
    grid = grid.reshape(shape)
    # face connectivity: neighbours along one axis only
    parts, _ = ndimage.label(grid, ndimage.generate_binary_structure(grid.ndim, 1))
    model_sizes = np.bincount(parts.ravel()[voxel])[1:]  # the elements' voxels: no count of the empty ones
    del parts
    # parts of one material: skimage joins neighbours only when they hold the same value
    regions = label_regions(grid, background=0, connectivity=1).ravel()[voxel]
    sizes = np.bincount(regions)
    region_material = np.zeros(sizes.size, np.int64)
    region_material[regions] = material
    return model_sizes, region_material[1:], sizes[1:]


def _graph_parts(m: int, nb: np.ndarray, material: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face-connected parts of any mesh from the element across each face ``nb`` (M, F):
    connected components of the graph of shared faces, for the model and, keeping only
    faces between elements of one material, per material. Same returns as :func:`_grid_parts`."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    row = np.arange(m)[:, None]
    same = material[nb] == material[:, None]  # nb = -1 gives rubbish, dropped by nb > row

    def components(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # each shared face once (towards the higher element), the rows' entries straight
        # into CSR form: no (row, column) pair arrays and no sort of them
        indptr = np.zeros(m + 1, np.int64)
        np.cumsum(np.count_nonzero(keep, axis=1), out=indptr[1:])
        indices = nb[keep].astype(np.int32 if m < 2**31 else np.int64)
        graph = csr_matrix((np.ones(indices.size), indices, indptr), shape=(m, m))
        _, comp = connected_components(graph, directed=False)
        return comp, np.bincount(comp)

    upper = nb > row
    _, model_sizes = components(upper)
    upper &= same
    del same
    comp, sizes = components(upper)
    comp_material = np.zeros(sizes.size, np.int64)
    comp_material[comp] = material  # any element's material: all of a component share it
    return model_sizes, comp_material, sizes


def floating_parts(mesh: Mesh, neighbours: np.ndarray | None = None, voxel: np.ndarray | None = None) -> dict:
    """Connected parts of the model and of each material, through shared faces (2D: edges).

    Elements that share only an edge or a node do not hold together in a solve, so parts are
    face-connected, as ``fix`` counts them on the voxels. A voxel mesh of its lattice
    (smoothed or not) is labelled on its voxel grid; any other mesh goes through the
    graph of its face neighbours.

    Parameters
    ----------
    mesh : Mesh
    neighbours : (M, F) int64 ndarray, optional
        From :func:`element_neighbours`; for a mesh that is not a voxel mesh, computed
        here when not given.
    voxel : (M,) int64 ndarray, optional
        :func:`dicer.mesh.faces.voxel_elements` of the mesh when already computed.

    Returns
    -------
    dict
        ``{"model": {...}, "materials": {label: {...}}}``, each with ``parts`` (count),
        ``largest`` and ``smallest`` (elements of the largest and smallest part); the
        model's also ``floating_elements``: the elements outside its largest part (any is
        a part a static solve cannot hold).
    """
    from dicer.mesh.faces import voxel_elements

    m = mesh.n_cells
    out = {"model": {"parts": 0, "largest": 0, "smallest": 0, "floating_elements": 0}, "materials": {}}
    if m == 0:
        return out
    material = np.asarray(mesh.material, np.int64)
    if material.min() <= 0:  # the grid holds 0 for no element
        voxel = None
    elif voxel is None:
        voxel = voxel_elements(mesh)
    if voxel is not None:
        shape = tuple(int(n) for n in np.asarray(mesh.grid_shape)[:mesh.dim])
        model_sizes, comp_material, sizes = _grid_parts(shape, voxel, material)
    else:
        nb = element_neighbours(mesh) if neighbours is None else neighbours
        model_sizes, comp_material, sizes = _graph_parts(m, nb, material)
    out["model"] = {"parts": int(model_sizes.size), "largest": int(model_sizes.max()),
                    "smallest": int(model_sizes.min()), "floating_elements": int(m - model_sizes.max())}
    order = np.argsort(comp_material, kind="stable")
    cm, sz = comp_material[order], sizes[order]
    start = np.flatnonzero(np.r_[True, cm[1:] != cm[:-1]])
    count = np.diff(np.r_[start, cm.size])
    largest, smallest = np.maximum.reduceat(sz, start), np.minimum.reduceat(sz, start)
    out["materials"] = {int(k): {"parts": int(n), "largest": int(hi), "smallest": int(lo)}
                        for k, n, hi, lo in zip(cm[start], count, largest, smallest)}
    return out


@takes_settings("quality")
def quality_report(mesh: Mesh, *, names: list, poor_scaled_jacobian: float, stretched_edge_ratio: float,
                   labels=None, original=None, metrics: dict | None = None, neighbours: np.ndarray | None = None,
                   parts: dict | None = None, voxel: np.ndarray | None = None, properties: list | None = None,
                   plane_stress: bool = True) -> dict:
    """Quality figures of a mesh as a JSON-ready dict.

    Settings come as keywords (:func:`dicer.config.stage_kwargs` of ``quality``); a
    configuration given as the second argument works too (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    mesh : Mesh
        The mesh to assess.
    names : list of str
        Material names, label 1 first.
    poor_scaled_jacobian : float
        Elements below this scaled Jacobian are counted as poor.
    stretched_edge_ratio : float
        Elements whose longest edge is more than this many times their shortest are
        counted as stretched (a solver's accuracy suffers long before the Jacobian does).
    labels : Volume, optional
        The labels the mesh came from; adds voxel counts and the volume of the mesh
        against the voxel volume per material, and the Euler characteristic of each
        material's surface (2D: region) in the voxels beside the mesh's (``topology_changed`` names the
        materials where they differ: a hole, channel or cavity that merging filled).
    original : Volume, optional
        The segmentation before downsampling (the full-resolution labels); adds its voxel
        volume per material and the mesh's volume change against it, which holds what
        downsampling changed too.
    metrics : dict, optional
        The elements' metrics already computed
        (:func:`dicer.mesh.metrics.element_metrics` with at least ``REPORT_METRICS``).
    neighbours : (M, F) int64 ndarray, optional
        The element across each face (:func:`element_neighbours`).
    parts : dict, optional
        :func:`floating_parts` of the mesh, already computed.
    voxel : (M,) int64 ndarray, optional
        :func:`dicer.mesh.faces.voxel_elements` of the mesh, already computed (None: made
        here when needed).
    properties : list of dict, optional
        The materials' properties, label 1 first (the config's ``materials``, as the decks
        take them); adds an explicit solver's stable time step (:func:`explicit_time_step`),
        each material's smallest, and the mass that scaling to longer ones adds. Left out
        when the mesh has an inverted element or a label the list does not reach.
    plane_stress : bool, optional
        A 2D mesh's elements are in plane stress (CPS4, CPS8, the default), not plane strain:
        the time step's wave speed (:func:`wave_speeds`). 3D meshes ignore it.

    Returns
    -------
    dict
    """
    names = {i: n for i, n in enumerate(names, start=1)}
    if metrics is None:
        metrics = element_metrics(mesh.points, mesh.cells, REPORT_METRICS)
    sj, vol, er = metrics["scaled_jacobian"], metrics["volume"], metrics["edge_ratio"]
    poor = float(poor_scaled_jacobian)
    unit = "mm^3" if mesh.dim == 3 else "mm^2"

    materials = {}
    per = _material_counts(mesh, sj, vol)
    if labels is not None:
        in_volume = count_labels(labels.array, int(per["label"].max()) + 1)
        voxel_volume = float(np.prod(labels.spacing))
    if original is not None:
        orig_count = count_labels(original.array, int(per["label"].max()) + 1)
        orig_voxel_volume = float(np.prod(original.spacing))
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
        if original is not None:
            voxels = int(orig_count[label]) if label < orig_count.size else 0
            entry[f"original_volume_{unit}"] = _r(voxels * orig_voxel_volume)
            if voxels:
                entry["original_volume_change_percent"] = _r(
                    100.0 * (per["volume"][i] / (voxels * orig_voxel_volume) - 1.0))
        materials[names.get(label, f"material_{label}")] = entry

    meshed = set(per["label"].tolist())
    length = metrics["characteristic_length"] if "characteristic_length" in metrics \
        else characteristic_length(mesh.points, mesh.cells)
    report = {
        "dicer_version": __version__,
        # what made the model's last bits: the same versions give the same bytes (constraints.txt)
        "library_versions": library_versions(),
        "dimension": mesh.dim,
        "element_type": mesh.cell_type,
        "nodes": mesh.n_points,
        "elements": mesh.n_cells,
        "materials": materials,
        f"element_volume_{unit}": {**_stats(vol), "total": _r(vol.sum())},
        "scaled_jacobian": _stats(sj),
        "edge_ratio": _stats(er),
        # an explicit solver's stable time step is the smallest of these over the wave speed
        "characteristic_length_mm": _stats(length),
        "inverted_elements": int(np.count_nonzero(sj <= 0)),
        "poor_elements": int(np.count_nonzero(sj < poor)),
        "poor_threshold": poor,
        "stretched_elements": int(np.count_nonzero(er > stretched_edge_ratio)),
        "stretched_threshold": float(stretched_edge_ratio),
        # named materials the model has no element of (a class the segmentation left empty, a
        # material downsampling or the fixes removed): the deck has no element set for them
        "materials_without_elements": [n for i, n in names.items() if i not in meshed],
    }
    if mesh.n_cells and labels is not None and np.asarray(labels.array).ndim == mesh.dim:
        from dicer.mesh.faces import voxel_elements

        # each material's surface against its voxels': merging that closed a hole or a channel
        # a voxel or two wide, or filled a cavity, changes it; a voxel mesh of these labels
        # (smoothed or not) has their topology and needs no count
        if voxel is None and parts is None:
            voxel = voxel_elements(mesh)
        array = np.asarray(labels.array)
        same = (voxel is not None and array.shape == tuple(int(k) for k in np.asarray(mesh.grid_shape)[:mesh.dim])
                and int(np.count_nonzero(array)) == mesh.n_cells
                and np.array_equal(array.reshape(-1)[voxel], np.asarray(mesh.material)))
        changed = []
        if not same:
            if mesh.dim == 3:
                if neighbours is None:  # made once, for the floating parts too
                    neighbours = element_neighbours(mesh)
                euler = surface_euler(mesh, neighbours)
            else:
                euler = region_euler(mesh)
            voxels = voxel_euler(array, euler)
            for label, value in euler.items():
                entry = materials[names.get(label, f"material_{label}")]
                entry["surface_euler"] = value
                if label in voxels:
                    entry["voxel_surface_euler"] = voxels[label]
                    if voxels[label] != value:
                        changed.append(names.get(label, f"material_{label}"))
        report["topology_changed"] = changed
    if (properties and mesh.n_cells and int(per["label"].max()) <= len(properties) and not report["inverted_elements"]
            and float(length.min()) > 0):  # an inverted element stops an explicit solver at once
        speeds = wave_speeds(properties, plane_stress=mesh.dim == 2 and plane_stress)
        step = explicit_time_step(length, vol, np.asarray(mesh.material, np.int64), speeds,
                                  np.r_[np.nan, [float(m["density"]) for m in properties]])
        for label, smallest in step.pop("smallest_by_material").items():
            report["materials"][names.get(label, f"material_{label}")]["smallest_time_step_s"] = smallest
        step["material"] = names.get(step["material"], f"material_{step['material']}")
        report["explicit_time_step"] = step
    parts = floating_parts(mesh, neighbours, voxel) if parts is None else parts
    report["parts"] = {"model": parts["model"],
                       "materials": {names.get(k, f"material_{k}"): v for k, v in parts["materials"].items()}}
    if "node_class" in mesh.point_data:
        cls = np.asarray(mesh.point_data["node_class"]).astype(np.int64)
        counts = np.bincount(cls, minlength=len(_NODE_CLASSES) + 1)
        report["node_classes"] = {"interior": int(counts[0])} | {
            c: int(counts[i + 1]) for i, c in enumerate(_NODE_CLASSES)
        }
    return report


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _table(rows: list[tuple[str, object]]) -> str:
    body = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _grid(header: list[str], rows: list[list[object]], classes: list[str] | None = None) -> str:
    """A table with a header row; ``classes``: a CSS class per row ('' for none)."""
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        f"<tr{f' class={c!r}' if c else ''}>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row) + "</tr>"
        for row, c in zip(rows, classes or [""] * len(rows)))
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(value, spec: str = "") -> str:
    if value is None:
        return "–"
    return format(value, spec) if spec else str(value)


STYLE = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin-bottom:1.5em}"
         "th,td{border:1px solid #bbb;padding:3px 8px;text-align:left}td{font-variant-numeric:tabular-nums}"
         "tr.warn td{background:#fde0dd}img{max-width:100%}figure{margin:0 0 1.5em 0}"
         "figcaption{font-size:90%;color:#444}")


def notices_html(report: dict) -> str:
    """Highlighted lines naming the materials without elements and those whose surface
    topology differs from their voxels' ('' when there are none).

    Parameters
    ----------
    report : dict
        From :func:`quality_report`.

    Returns
    -------
    str
    """
    rows = [[what, ", ".join(report.get(key) or [])]
            for key, what in (("materials_without_elements", "materials without elements"),
                              ("topology_changed", "surface topology unlike the voxels"))
            if report.get(key)]
    return _grid(["notice", "materials"], rows, ["warn"] * len(rows)) if rows else ""


def parts_html(report: dict) -> str:
    """The floating-parts table: the model's face-connected parts and each material's.

    Parameters
    ----------
    report : dict
        From :func:`quality_report`.

    Returns
    -------
    str
        HTML.
    """
    parts = report.get("parts")
    if not parts:
        return ""
    model = parts["model"]
    rows = [["whole model", model["parts"], model["largest"], model["smallest"], model["floating_elements"]]]
    rows += [[name, e["parts"], e["largest"], e["smallest"], "–"] for name, e in parts["materials"].items()]
    classes = ["warn" if model["parts"] > 1 else ""] + [""] * len(parts["materials"])
    verdict = ("one part: nothing floats" if model["parts"] == 1 else
               f"{model['parts']} parts: {model['floating_elements']} element(s) float free of the largest part "
               "(a static solve needs each part held)")
    return ("<h2>Floating parts</h2><p>Parts connected through shared faces; " + html.escape(verdict) + ".</p>"
            + _grid(["", "parts", "largest part (elements)", "smallest part (elements)", "floating elements"],
                    rows, classes))


def volume_html(report: dict) -> str:
    """Per material, the mesh's volume against the meshed labels and the original segmentation.

    Parameters
    ----------
    report
        As in :func:`parts_html`.

    Returns
    -------
    str
        An HTML table.
    """
    unit = "mm^3" if report["dimension"] == 3 else "mm^2"
    rows = []
    for name, e in report["materials"].items():
        rows.append([name, _fmt(e.get(f"volume_{unit}")), _fmt(e.get(f"voxel_volume_{unit}")),
                     _fmt(e.get("volume_change_percent"), "+.2f"), _fmt(e.get(f"original_volume_{unit}")),
                     _fmt(e.get("original_volume_change_percent"), "+.2f")])
    return ("<h2>Volume</h2><p>The mesh's volume per material against the voxels it was made from (after "
            "downsampling and the connectivity fixes) and against the original segmentation (full resolution), "
            "which also holds what downsampling changed.</p>"
            + _grid(["material", f"mesh ({unit})", f"meshed labels ({unit})", "change (%)",
                     f"original segmentation ({unit})", "change against the original (%)"], rows))


def render_html(report: dict, pictures: list[tuple[str, bytes]] = ()) -> str:
    """A self-contained HTML page of the report.

    Tables, and pictures embedded as data URIs, so the page shows them wherever it is
    opened (a browser, inside ``snakemake --report``, sent by mail).

    Parameters
    ----------
    report : dict
        From :func:`quality_report`.
    pictures : sequence of (str, bytes), optional
        Caption and PNG bytes of each picture.

    Returns
    -------
    str
    """
    top = [(k, report[k]) for k in ("dimension", "element_type", "nodes", "elements", "inverted_elements",
                                      "poor_elements", "poor_threshold", "stretched_elements",
                                      "stretched_threshold")]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>dicer mesh quality</title>",
        f"<style>{STYLE}</style></head><body>",
        f"<h1>Mesh quality</h1><p>dicer {html.escape(report['dicer_version'])}"
        + ("" if "library_versions" not in report else " (" + ", ".join(
            f"{html.escape(k)} {html.escape(v)}" for k, v in report["library_versions"].items()) + ")") + "</p>",
        _table(top),
        notices_html(report),
        parts_html(report),
        volume_html(report),
    ]
    for caption, png in pictures:
        text = html.escape(caption, quote=True)
        parts.append(f"<figure><img src='{_data_uri(png)}' alt='{text}'><figcaption>{html.escape(caption)}"
                     "</figcaption></figure>")
    parts.append("<h2>Materials</h2>")
    for name, entry in report["materials"].items():
        parts.append(f"<h3>{html.escape(name)}</h3>" + _table(list(entry.items())))
    figures = ("scaled_jacobian", "edge_ratio", "element_volume", "characteristic_length")
    for key in sorted(k for k in report if k.startswith(figures)):
        parts.append(f"<h2>{html.escape(key)}</h2>" + _table(list(report[key].items())))
    step = report.get("explicit_time_step")
    if step:
        rows = [("smallest stable time step, s", step["smallest_s"]), ("its element", step["element"]),
                ("its material", step["material"])]
        rows += [(f"mass scaling to {m['times_smallest']:g} times it ({m['time_step_s']:.3g} s)",
                  f"+{m['mass_added_percent']:.3g} % mass on {m['elements_scaled']} element(s)")
                 for m in step["mass_scaling"]]
        parts.append("<h2>Explicit time step</h2>" + _table(rows))
    if "node_classes" in report:
        parts.append("<h2>Boundary node classes</h2>" + _table(list(report["node_classes"].items())))
    for stage, entry in report.get("stages", {}).items():
        # scalars as they are, small nested values as compact JSON
        rows = [(k, v if not isinstance(v, (dict, list)) else json.dumps(v, sort_keys=True)[:300])
                for k, v in entry.items()]
        parts.append(f"<h2>Stage: {html.escape(stage)}</h2>" + _table(rows))
    parts.append("</body></html>\n")
    return "".join(parts)
