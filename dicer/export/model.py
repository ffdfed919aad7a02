"""The solver model: a mesh made ready for any writer (numbering, element type and order,
material blocks, node sets, exterior and interface faces, provenance).

:func:`prepare_model` checks the mesh against the configuration and builds one
:class:`SolverModel`; every format writes from it. Surface sets come from the face
neighbours of :mod:`dicer.mesh.faces`.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dicer.arrays import nonzero
from dicer.config import name_clash, stage_kwargs
from dicer.errors import DicerError
from dicer.export.provenance import provenance, sha256_in_background
from dicer.image import MAX_LABEL
from dicer.mesh.boundary import PLANE_TOLERANCE
from dicer.mesh.faces import cavity_faces, materials_across, neighbour_materials
from dicer.mesh.frame import mirrored, to_scanner
from dicer.mesh.model import Mesh, Sized, pieces
from dicer.mesh.topology import (HEX20_FACES, HEX20_MIRROR, HEX_FACE_MIRROR, HEX_FACES, HEX_MIRROR, QUAD8_SIDES,
                                 QUAD_EDGES)
from dicer.parallel import ordered_map

log = logging.getLogger("dicer")

# element type -> (dimension, order); the node order of every type is VTK's (= Abaqus's)
ELEMENT_TYPES = {
    "C3D8": (3, 1), "C3D8R": (3, 1), "C3D8I": (3, 1),
    "C3D20": (3, 2), "C3D20R": (3, 2),
    "CPS4": (2, 1), "CPS4R": (2, 1), "CPE4": (2, 1), "CPE4R": (2, 1),
    "CPS8": (2, 2), "CPS8R": (2, 2), "CPE8": (2, 2), "CPE8R": (2, 2),
}
DEFAULT_TYPES = {(3, 1): "C3D8", (3, 2): "C3D20", (2, 1): "CPS4", (2, 2): "CPS8"}


def element_types(dim: int, order: int) -> list[str]:
    """The Abaqus element names of one dimension and order, as listed.

    Parameters
    ----------
    dim : int
        2 or 3.
    order : int
        1 or 2.

    Returns
    -------
    list of str
    """
    return [t for t, (d, o) in ELEMENT_TYPES.items() if d == dim and o == order]


class _AfterSets:
    """An attribute of the surface sets: reading or setting it waits for sets in the making
    (:meth:`SolverModel.sets_meanwhile`); the value lives in ``_<name>``."""

    def __set_name__(self, owner, name: str) -> None:
        self.slot = "_" + name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        obj._wait()
        return getattr(obj, self.slot)

    def __set__(self, obj, value) -> None:
        obj._wait()
        setattr(obj, self.slot, value)


@dataclass
class SolverModel(Sized):
    """A mesh ready for a solver file: everything a writer needs, nothing format-specific.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Node coordinates, mm; node i is written as number i + 1.
    cells : (M, n) int ndarray
        Node indices in VTK/Abaqus order (8 or 20 per hex, 4 or 8 per quad).
    material : (M,) int ndarray
        Labels 1..K; element j is written as number j + 1.
    names : dict of int to str
        Label -> class name.
    props : dict of int to dict
        Label -> material dict from the config.
    element_type : str
        Abaqus name (C3D8, C3D20, CPS4, ...).
    dim, order : int
        2 or 3; 1 or 2.
    thickness : float
        Thickness of 2D plane elements, mm.
    digits : int
        Significant digits of the coordinates (``export.digits``).
    heading : list of str, optional
        Provenance lines (no date, no path).
    use_heading : bool, optional
        Write the first heading line as the title (``*HEADING``; ``export.heading``).
    cell_data : dict of str to ndarray, optional
        Further per-element arrays (VTU).
    mesh : Mesh, optional
        The linear mesh the model was made from (the VTU writer keeps its lattice data).

    Attributes
    ----------
    node_sets : dict of str to ndarray
        Set name -> sorted 0-based node indices (bounding planes, material boundaries,
        interfaces).
    exterior : (F, 2) int64 ndarray or None
        Rows (element index, face number 1..6 / 1..4) of the element faces on the exterior
        surface: the outer surface of every body, the walls of cavities left out.
    cavities : (F, 2) int64 ndarray or None
        The same rows for the walls of the cavities the material closes round (enclosed
        voids: a sinus, an unlabelled hole); empty when there are none.
    interfaces : dict of str to (F, 2) int64 ndarray
        Interface name ``<a>_<b>`` -> rows (element index, face number) of the faces of
        material a with material b behind them (a < b), grouped by face number, elements
        ascending; for formats with face sets (Exodus, FEBio).

    The surface sets may still be in the making on a thread (:meth:`sets_meanwhile`):
    reading any of these four waits for them.
    """

    points: np.ndarray
    cells: np.ndarray
    material: np.ndarray
    names: dict[int, str]
    props: dict[int, dict]
    element_type: str
    dim: int
    order: int
    thickness: float
    digits: int
    heading: list[str] = field(default_factory=list)
    use_heading: bool = True
    cell_data: dict[str, np.ndarray] = field(default_factory=dict)
    mesh: Mesh | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self._node_sets: dict[str, np.ndarray] = {}
        self._exterior: np.ndarray | None = None
        self._cavities: np.ndarray | None = None
        self._interfaces: dict[str, np.ndarray] = {}
        self._pending = None
        self._lock = threading.Lock()  # readers on several threads wait for one result

    def sets_meanwhile(self, build) -> None:
        """Build surface sets on a thread while the writer starts on nodes and elements.

        ``build()`` returns (node sets, exterior, cavities, interfaces); the node sets follow
        those the model holds. The first read of ``node_sets``, ``exterior``, ``cavities`` or
        ``interfaces`` waits for them (and raises what ``build`` raised).
        """
        from dicer.parallel import meanwhile

        self._pending = meanwhile(build)

    def _wait(self) -> None:
        if self._pending is None:
            return
        with self._lock:
            if self._pending is not None:
                node_sets, self._exterior, self._cavities, self._interfaces = self._pending()
                self._node_sets.update(node_sets)
                self._pending = None

    node_sets = _AfterSets()
    exterior = _AfterSets()
    cavities = _AfterSets()
    interfaces = _AfterSets()

    def free_face_sets(self) -> dict[str, np.ndarray]:
        """The sets of faces of one element, those with faces: EXTERIOR, CAVITIES -> (F, 2)
        rows (element index, face number)."""
        return {name: rows for name, rows in (("EXTERIOR", self.exterior), ("CAVITIES", self.cavities))
                if rows is not None and rows.size}

    def facets(self, faces: np.ndarray) -> np.ndarray:
        """Node indices of element faces, wound outward (counter-clockwise seen from outside
        the element: the normal FEBio's and LS-DYNA's pressure loads take).

        Parameters
        ----------
        faces : (F, 2) int ndarray
            Rows of element index and Abaqus face number 1..6.

        Returns
        -------
        (F, 4) or (F, 8) int ndarray
            0-based.
        """
        table = HEX20_FACES if self.order == 2 else HEX_FACES
        return self.cells[faces[:, 0][:, None], table[faces[:, 1] - 1]]

    def face_sets(self) -> dict[str, np.ndarray]:
        """Element-face set name -> (F, 2) rows (element index, face number): EXTERIOR,
        CAVITIES, then the interfaces (Exodus side sets, FEBio surfaces)."""
        return {**self.free_face_sets(), **self.interfaces}

    def name_list(self) -> list[str]:
        """Material names by label, 1..K (entry i names label i + 1)."""
        return [self.names[k] for k in range(1, max(self.names) + 1)]

    def labels(self) -> list[int]:
        """Material labels present, ascending."""
        # a count per label: np.unique sorted every element (0.05 s a call at 6.4 M)
        return [int(k) for k in np.flatnonzero(np.bincount(self.material, minlength=max(self.names) + 1))]

    def blocks(self) -> list[tuple[int, np.ndarray]]:
        """(label, element indices ascending) per material present."""
        counts = np.bincount(self.material, minlength=max(self.names) + 1)
        present = np.flatnonzero(counts)
        if present.size <= 8:
            # a few materials (the usual case): one comparison pass per label costs less than a sort
            return [(int(k), np.flatnonzero(self.material == k)) for k in present]
        order = np.argsort(self.material, kind="stable")
        out, start = [], 0
        for k in range(counts.size):
            if counts[k]:
                out.append((k, order[start : start + counts[k]]))
                start += counts[k]
        return out


def resolve_element_type(mesh: Mesh, order: int, element_type: str | None, path: Path) -> tuple[str, int]:
    """The element type and order (``export.order``, ``export.element_type``), checked against the mesh.

    Parameters
    ----------
    mesh : Mesh
    order : int
        1 or 2 (the schema checked it).
    element_type : str or None
        An Abaqus name of the schema's list; None picks the default for the dimension and order.
    path : Path
        The output file, named in error messages.

    Returns
    -------
    element_type : str
        Abaqus name.
    order : int
        1 or 2.

    Raises
    ------
    DicerError
        A type that does not fit the dimension or the order.
    """
    order, etype = int(order), element_type
    if etype is None:
        return DEFAULT_TYPES[(mesh.dim, order)], order
    dim, etype_order = ELEMENT_TYPES[etype]
    if dim != mesh.dim:
        raise DicerError(f"{path}: element type {etype} is for {dim}D meshes but the mesh is {mesh.dim}D; "
                         f"use one of {', '.join(element_types(mesh.dim, order))}")
    if etype_order != order:
        raise DicerError(f"{path}: export.order is {order} but element type {etype} has order {etype_order}; "
                         f"use one of {', '.join(element_types(mesh.dim, order))} or set export.order={etype_order}")
    return etype, order



def _face_nodes(cells: np.ndarray, table: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elements (F,) and their nodes (F, c) of the faces marked in the (M, faces) bool array ``faces``."""
    e_idx, f_idx = nonzero(faces)
    return e_idx, cells[e_idx[:, None], table[f_idx]]


def _grouped_nodes(code: np.ndarray, nodes: np.ndarray, n_points: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Distinct codes (ascending) and, for each, the sorted distinct nodes paired with it.

    code : (F,) int64, one code per row of ``nodes``; nodes : (F, c) node indices.
    """
    distinct, which = np.unique(code, return_inverse=True)
    if distinct.size * n_points > 32 * nodes.size:
        # many codes (an atlas's pairs of labels): one sort of (code, node) keys
        key = np.unique((code[:, None] * n_points + nodes).ravel())  # int64: codes < 2**32, nodes < 2**31
        if not key.size:
            return key, []
        group, node = np.divmod(key, n_points)
        cut = np.flatnonzero(group[1:] != group[:-1]) + 1
        return group[np.r_[0, cut]], np.split(node, cut)
    # a few codes: a flag per node for each (a tenth of the sort's time for two materials)
    flags = np.zeros(n_points, bool)
    groups = []
    for g in range(distinct.size):
        flags[nodes[which == g]] = True
        groups.append(np.flatnonzero(flags))
        flags[groups[-1]] = False
    return distinct, groups


def _surface_sets(model: SolverModel, kinds: set[str], nb_mat: np.ndarray, cells: np.ndarray,
                  points: np.ndarray) -> tuple[dict, np.ndarray | None, np.ndarray | None, dict]:
    """Exterior and cavity faces and surface, material boundary and interface node sets from
    neighbour materials: (node sets, exterior faces or None, cavity faces or None, interfaces),
    as the SolverModel holds them.

    Sets come in the order EXTERIOR, CAVITIES, <a>_BOUNDARY by label, <a>_<b> by label a then b
    (a < b); only sets with nodes are kept. Nodes are collected as (set, node) pairs
    from the faces concerned, so the work follows the surface, not the number of
    materials or pairs of them.
    """
    dim = model.dim
    if model.order == 2:
        table = HEX20_FACES if dim == 3 else QUAD8_SIDES
    else:
        table = HEX_FACES if dim == 3 else QUAD_EDGES
    n = model.n_points
    node_sets, exterior_faces, cavity_rows, interfaces = {}, None, None, {}
    ext_e, ext_f = [], []
    bound_code, bound_nodes, pair_code, pair_nodes, pair_face = [], [], [], [], []

    def one(part: slice) -> tuple:
        """(exterior faces, boundary faces, interface faces) of one piece, None for kinds not asked."""
        start = part.start
        mat = model.material[part].astype(np.int64)
        nbm = nb_mat[part]
        corners = cells[part]
        ext = bound = pair = None
        if "exterior" in kinds:
            f_idx, e_idx = nonzero((nbm == 0).T)  # grouped by face number
            ext = (e_idx + start, f_idx)
        if "materials" in kinds:  # faces of a material with another (or none) behind them
            e_idx, nodes = _face_nodes(corners, table, nbm != mat[:, None])
            bound = (mat[e_idx], nodes)
        if "interfaces" in kinds:  # faces of material a with material b > a behind them
            later = nbm > mat[:, None]
            e_idx, nodes = _face_nodes(corners, table, later)
            pair = (mat[e_idx] << 16 | nbm[later].astype(np.int64),  # labels <= MAX_LABEL < 2**16
                    nodes, np.column_stack(nonzero(later)) + [start, 1])  # (element, face number)
        return ext, bound, pair

    # pieces side by side (numpy leaves the interpreter lock), their faces joined in order
    for ext, bound, pair in ordered_map(one, pieces(model.n_cells)):
        if ext is not None:
            ext_e.append(ext[0])
            ext_f.append(ext[1])
        if bound is not None:
            bound_code.append(bound[0])
            bound_nodes.append(bound[1])
        if pair is not None:
            pair_code.append(pair[0])
            pair_nodes.append(pair[1])
            pair_face.append(pair[2])
    if "exterior" in kinds:
        e, f = np.concatenate(ext_e), np.concatenate(ext_f)
        order = np.lexsort((e, f))  # grouped by face number, elements ascending
        e, f = e[order], f[order]
        # a pressure on the outer surface must not press on the walls of enclosed voids
        cavity = cavity_faces(points, cells, dim, e, f)
        exterior_faces, cavity_rows = (np.column_stack([e[keep], f[keep] + 1]).astype(np.int64)
                                       for keep in (~cavity, cavity))
        flags = np.zeros(n, bool)
        for name, rows in (("EXTERIOR", exterior_faces), ("CAVITIES", cavity_rows)):
            if rows.size:
                flags[cells[rows[:, :1], table[rows[:, 1] - 1]]] = True
                node_sets[name] = np.flatnonzero(flags)
                flags[node_sets[name]] = False
    width = table.shape[1]
    if "materials" in kinds:
        codes, groups = _grouped_nodes(np.concatenate(bound_code), np.concatenate(bound_nodes).reshape(-1, width), n)
        for k, ids in zip(codes.tolist(), groups):
            node_sets[f"{model.names[k]}_BOUNDARY"] = ids
    if "interfaces" in kinds:
        code = np.concatenate(pair_code)
        codes, groups = _grouped_nodes(code, np.concatenate(pair_nodes).reshape(-1, width), n)
        for c, ids in zip(codes.tolist(), groups):
            node_sets[f"{model.names[c >> 16]}_{model.names[c & 0xFFFF]}"] = ids
        # the same faces as (element, face number) rows per pair: by face number, elements ascending
        faces = np.concatenate(pair_face).astype(np.int64).reshape(-1, 2)
        order = np.lexsort((faces[:, 0], faces[:, 1], code))
        code, faces = code[order], faces[order]
        cut = np.flatnonzero(code[1:] != code[:-1]) + 1
        for c, rows in zip(code[np.r_[0, cut]].tolist() if code.size else [], np.split(faces, cut)):
            interfaces[f"{model.names[c >> 16]}_{model.names[c & 0xFFFF]}"] = rows
    return node_sets, exterior_faces, cavity_rows, interfaces


def _plane_sets(mesh: Mesh, points: np.ndarray, lattice2: np.ndarray | None, path) -> dict[str, np.ndarray]:
    """The nodes on each of the image's bounding planes (X0 ... Z1), by lattice index and
    position, for boundary conditions on cut and symmetry planes.

    A node of a bounding lattice plane that smoothing moved off it
    (``smooth.bounding_planes: free`` with ``keep_bounding_planes: false``) is left out: a
    symmetry condition on it would pull it back. The tolerance is the smoothing's own
    (:func:`dicer.mesh.boundary.bounding_planes`, 1e-6 voxel). A plane with no node left
    on it gets no set; either case is warned of.
    """
    sets, left = {}, []
    g2 = 2 * np.asarray(mesh.grid_shape, np.int64)
    spacing = np.asarray(mesh.spacing, float)
    for axis in range(mesh.dim):
        for side, target in (("0", 0), ("1", g2[axis])):
            if lattice2 is None:
                ids = np.flatnonzero(mesh.lattice[:, axis] == target // 2)
            else:
                ids = np.flatnonzero(lattice2[:, axis] == target)
            plane = float(mesh.origin[axis]) + target / 2 * spacing[axis]
            on = np.abs(points[ids, axis] - plane) <= PLANE_TOLERANCE * spacing[axis]
            name = "XYZ"[axis] + side
            if not on.all():
                left.append(f"{name}: {ids.size - int(on.sum())} of {ids.size} nodes")
                ids = ids[on]
            if ids.size:
                sets[name] = ids
    if left:
        log.warning("export: %s: smoothing moved nodes of the image's bounding planes off them (%s), which "
                    "smooth.keep_bounding_planes: false allows; the plane sets hold only the nodes still on their "
                    "plane (a plane with none gets no set): for boundary conditions on the planes, smooth with "
                    "smooth.keep_bounding_planes: true (or smooth.bounding_planes: mirror)",
                    Path(path).name, ", ".join(left))
    return sets


def quadratic_nodes(mesh: Mesh, midside_nodes: str, neighbours=None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The quadratic mesh of ``mesh`` (:func:`dicer.mesh.quadratic.quadratic_mesh`).

    Parameters
    ----------
    mesh : Mesh
    midside_nodes : {"midpoints", "curved"}
        ``export.midside_nodes``: curved bends the edges of faces on a boundary (the exterior
        or an interface) onto its curve.
    neighbours : callable, optional
        As for :func:`prepare_model`.

    Returns
    -------
    points : (N + E, 3) float64 ndarray
    cells : (M, 20) or (M, 8) int64 ndarray
    lattice2 : (N + E, 3) int64 ndarray
    across : (M, F) ndarray or None
        With curved: the material across each face (0 for none), which the sets take too.
    """
    from dicer.mesh.quadratic import curved_quadratic_mesh, curving_volume_change

    across = None
    boundary = None
    if midside_nodes == "curved":
        across = _materials_across(mesh, neighbours)
        boundary = across != mesh.material[:, None].astype(across.dtype)
    points, cells, lattice2, curved = curved_quadratic_mesh(mesh, boundary)
    if midside_nodes == "curved":
        _say_curving(mesh, curving_volume_change(mesh, points, cells, curved))
    return points, cells, lattice2, across


CURVING_VOLUME_WARNING = 0.05
"""A material's volume changed by this share by curved mid-edge nodes is warned of: quality
reports the linear mesh's (measured -0.01 % on the head CT, +1.6 % on a ball of radius 8 voxels,
+10.4 % on one of radius 3)."""


def _say_curving(mesh: Mesh, change: dict[int, float]) -> None:
    """Log what curved mid-edge nodes did to the materials' volumes; warn where it is much."""
    if not change:
        return
    names = list(mesh.names or ())

    def name(m: int) -> str:
        return names[m - 1] if 0 < m <= len(names) else f"material {m}"

    much = {m: v for m, v in change.items() if abs(v) > CURVING_VOLUME_WARNING}
    if much:
        log.warning("export: the curved mid-edge nodes change the volume of %s from the linear mesh's (which "
                    "quality.json reports): parts a few elements across bend their arcs through few nodes; set "
                    "export.midside_nodes: midpoint to keep the linear mesh's volumes",
                    ", ".join(f"{name(m)} {100 * v:+.1f} %" for m, v in sorted(much.items())))
    else:
        m = max(change, key=lambda k: abs(change[k]))
        log.info("export: the curved mid-edge nodes change the materials' volumes by %+.2f %% at most (%s)",
                 100 * change[m], name(m))


def _materials_across(mesh: Mesh, neighbours=None) -> np.ndarray:
    """(M, F): the material across each face of ``mesh`` (0 for none), from ``neighbours()``
    where the caller found them."""
    return neighbour_materials(mesh) if neighbours is None else materials_across(mesh.material, neighbours())


def prepare_model(mesh: Mesh, config: dict, source=None, path: Path | str = "model",
                  build_sets: bool = True, neighbours=None, quadratic=None) -> SolverModel:
    """Validate a mesh against the configuration and build the SolverModel the writers share.

    Parameters
    ----------
    mesh : Mesh
    config : dict
        The ``materials`` and ``export`` sections (as whole or in part: read through
        :func:`dicer.config.stage_kwargs`, the schema's defaults fill what is left out).
    source : str or os.PathLike, optional
        The input the model was made from, for the provenance.
    path : Path or str, optional
        The output file, named in error messages.
    build_sets : bool, optional
        Build the node sets and surfaces ``export.sets`` asks for (False for a format
        that holds none).
    neighbours : callable, optional
        Returns the (M, F) element across each face of ``mesh`` (-1 for none), as
        :func:`dicer.quality.element_neighbours` gives it: a run that needs them elsewhere
        too (the quality report) finds them once. Without it the sets find what they need.
    quadratic : callable, optional
        ``quadratic(midside_nodes)`` gives :func:`quadratic_nodes` of ``mesh`` for that
        placement: a run that writes several decks of order 2 places the mid-edge nodes once
        (their fold check is most of an order-2 export). Without it they are placed here.

    Returns
    -------
    SolverModel

    Raises
    ------
    DicerError
        No elements, labels that do not match the materials, non-finite coordinates, or
        clashing set names.
    """
    path = Path(path)
    ex = stage_kwargs(config, "export")
    etype, order = resolve_element_type(mesh, ex["order"], ex["element_type"], path)
    materials = ex["materials"]
    k = len(materials)
    if mesh.n_cells == 0:
        raise DicerError(f"{path}: the mesh has no elements; nothing to export")
    lo, hi = int(mesh.material.min()), int(mesh.material.max())
    if lo < 1 or hi > k:
        raise DicerError(f"{path}: element material labels run {lo}..{hi} but the config names {k} material(s) "
                         f"(labels 1..{k}); add materials to the config")
    if hi > MAX_LABEL:
        raise DicerError(f"{path}: material label {hi} is above {MAX_LABEL}, the largest a label volume holds; "
                         "renumber the materials")
    if not np.all(np.isfinite(mesh.points)):
        raise DicerError(f"{path}: the mesh has non-finite node coordinates; re-run the stage that made it")
    kinds = set(ex["sets"])
    clash = name_clash([m["name"] for m in materials], kinds)
    if clash:
        raise DicerError(f"{path}: {clash}")
    kinds = kinds if build_sets else set()
    digest = sha256_in_background(source)
    names = {i + 1: m["name"] for i, m in enumerate(materials)}
    props = {i + 1: dict(m) for i, m in enumerate(materials)}  # every property: the schema fills them
    cells = np.asarray(mesh.cells)
    if cells.dtype.kind not in "iu" or cells.dtype.itemsize < 4:
        cells = cells.astype(np.int64)
    elif build_sets and not cells.flags.writeable:
        # a file mapping (dicer export reads its mesh mapped): a deck's writer and check
        # gather the rows of each material, and a gather of scattered rows from a mapping
        # walks the page tables for each row; an atlas's hundreds of interleaved materials
        # took 10x longer than from memory. The copy costs about 0.1 s per 5 M elements
        # (VTU, which holds no sets, writes the cells in order and is spared it).
        cells = np.array(cells)
    lattice2 = None  # twice the lattice index (order 2: mid-edge nodes at half-integers)
    points = mesh.points
    nb_mat = None
    if order == 2:
        if quadratic is None:
            points, cells, lattice2, nb_mat = quadratic_nodes(mesh, ex["midside_nodes"], neighbours)
        else:
            points, cells, lattice2, nb_mat = quadratic(ex["midside_nodes"])
    model = SolverModel(
        points=points, cells=cells, material=mesh.material.astype(np.int32), names=names, props=props,
        element_type=etype, dim=mesh.dim, order=order, thickness=float(ex["thickness"]),
        digits=int(ex["digits"]), use_heading=bool(ex["heading"]), mesh=mesh,
    )
    if "planes" in kinds:
        model.node_sets.update(_plane_sets(mesh, points, lattice2, path))
    if kinds & {"materials", "interfaces", "exterior"}:
        if model.n_points >= 2**31:
            raise DicerError(f"{path}: node sets of models with 2**31 nodes or more are not supported; leave "
                             "materials, interfaces and exterior out of export.sets")
        flip = mesh.direction is not None and mirrored(mesh.direction)

        def build(cells=model.cells, points=model.points, nb_mat=nb_mat):  # the lattice frame's
            nb = _materials_across(mesh, neighbours) if nb_mat is None else nb_mat
            node_sets, exterior, cavities, interfaces = _surface_sets(model, kinds, nb, cells, points)
            if flip:
                _mirror_faces([exterior, cavities, *interfaces.values()])
            return node_sets, exterior, cavities, interfaces

        # on a thread: the writer starts on the nodes and elements, which need no sets
        model.sets_meanwhile(build)
    model.heading = provenance(source, config, etype, order, digest())  # the digest was computed meanwhile
    if mesh.direction is not None:
        _to_scanner_frame(model, mesh)
    return model


def _to_scanner_frame(model: SolverModel, mesh: Mesh) -> None:
    """Move the model from the lattice frame into scanner coordinates (docs/coordinates.md).

    Node sets and element numbers stay as they are; with a reflection in the direction
    cosines the corners go in their mirrored order (else every element would be inverted)
    and the bottom and top face numbers of the face sets swap with them.
    """
    model.points = to_scanner(model.points, mesh.spacing, mesh.origin, mesh.direction)
    if mirrored(mesh.direction):  # the face sets are mirrored where they are built
        model.cells = model.cells[:, HEX_MIRROR if model.order == 1 else HEX20_MIRROR]


def _mirror_faces(face_sets: list) -> None:
    """Swap the face numbers of (element, face number) rows as a reflection does, in place,
    and sort the rows by face number again."""
    for rows in face_sets:
        if rows is not None and rows.size:
            rows[:, 1] = HEX_FACE_MIRROR[rows[:, 1]]
            rows[:] = rows[np.lexsort((rows[:, 0], rows[:, 1]))]  # grouped by face number again


def scanner_mesh(mesh: Mesh, model: SolverModel) -> Mesh:
    """The linear mesh as exported: the model's points and cells, marked as scanner coordinates.

    Reading the file back then gives the lattice frame again.

    Parameters
    ----------
    mesh : Mesh
    model : SolverModel
        Built from ``mesh`` by :func:`prepare_model`.

    Returns
    -------
    Mesh
        ``mesh`` itself if it has no direction.
    """
    if mesh.direction is None:
        return mesh
    out = mesh.copy()
    out.points, out.cells, out.scanner = model.points, model.cells, True
    return out


