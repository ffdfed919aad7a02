"""Solver and viewer exports: the format follows the output file's extension.

``export_mesh(mesh, path, config, source)`` prepares one :class:`SolverModel`
(node numbering, element order and type, per-material blocks, node sets and the
exterior surface), hands it to the writer of the format, reads the file back and
checks it, and only then renames it into place. A failed check raises
DicerError and leaves no file behind.

Formats: Abaqus/CalculiX ``.inp``, VTU ``.vtu`` (ParaView), PATRAN neutral
``.out``/``.neu``, LS-DYNA keyword ``.k``/``.key``/``.dyn``, Gmsh ``.msh``, Exodus II
``.e``/``.exo`` (written with netCDF4), FEBio ``.feb``.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dicer import __version__
from dicer.config import SET_KINDS, config_hash, name_clash, stage_settings
from dicer.errors import DicerError
from dicer.image import MAX_LABEL
from dicer.io.atomic import atomic_path
from dicer.mesh.frame import mirrored, to_scanner
from dicer.mesh.model import Mesh
from dicer.mesh.topology import (HEX20_FACES, HEX20_MIRROR, HEX_CORNERS, HEX_FACE_MIRROR, HEX_FACE_PLANES, HEX_FACES,
                                 HEX_MIRROR, QUAD8_SIDES, QUAD_CORNERS, QUAD_EDGES, QUAD_SIDE_PLANES)

FORMATS = {
    ".inp": "abaqus",
    ".vtu": "vtu",
    ".out": "patran",
    ".neu": "patran",
    ".k": "lsdyna",
    ".key": "lsdyna",
    ".dyn": "lsdyna",
    ".msh": "gmsh",
    ".e": "exodus",
    ".exo": "exodus",
    ".feb": "febio",
}
EXPORT_SUFFIXES = tuple(FORMATS)
"""Output file extensions ``dicer export`` accepts."""

# element type -> (dimension, order); the node order of every type is VTK's (= Abaqus's)
ELEMENT_TYPES = {
    "C3D8": (3, 1), "C3D8R": (3, 1), "C3D8I": (3, 1),
    "C3D20": (3, 2), "C3D20R": (3, 2),
    "CPS4": (2, 1), "CPS4R": (2, 1), "CPE4": (2, 1), "CPE4R": (2, 1),
    "CPS8": (2, 2), "CPS8R": (2, 2), "CPE8": (2, 2), "CPE8R": (2, 2),
}
DEFAULT_TYPES = {(3, 1): "C3D8", (3, 2): "C3D20", (2, 1): "CPS4", (2, 2): "CPS8"}



@dataclass
class SolverModel:
    """A mesh ready for a solver file: everything a writer needs, nothing format-specific.

    points : (N, 3) node coordinates; node i is written as number i + 1.
    cells : (M, n) node indices in VTK/Abaqus order (8 or 20 per hex, 4 or 8 per quad).
    material : (M,) labels 1..K; element j is written as number j + 1.
    names : label -> class name; props : label -> material dict from the config.
    element_type : Abaqus name (C3D8, C3D20, CPS4, ...); dim, order : 2|3, 1|2.
    node_sets : set name -> sorted 0-based node indices (bounding planes, material
        boundaries, interfaces). exterior : (F, 2) int64 rows (element index, face
        number 1..6 / 1..4) of the element faces on the exterior surface.
    interfaces : interface name ``<a>_<b>`` -> (F, 2) int64 rows (element index, face
        number) of the faces of material a with material b behind them (a < b), grouped
        by face number, elements ascending; for formats with face sets (Exodus, FEBio).
    heading : provenance lines (no date, no path).
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
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    exterior: np.ndarray | None = None
    interfaces: dict[str, np.ndarray] = field(default_factory=dict)
    heading: list[str] = field(default_factory=list)
    use_heading: bool = True
    cell_data: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cells.shape[0])

    def face_sets(self) -> dict[str, np.ndarray]:
        """Element-face set name -> (F, 2) rows (element index, face number): EXTERIOR, then
        the interfaces (Exodus side sets, FEBio surfaces)."""
        out = {}
        if self.exterior is not None and self.exterior.size:
            out["EXTERIOR"] = self.exterior
        out.update(self.interfaces)
        return out

    def name_list(self) -> list[str]:
        """Material names by label, 1..K (entry i names label i + 1)."""
        return [self.names[k] for k in range(1, max(self.names) + 1)]

    def labels(self) -> list[int]:
        """Material labels present, ascending."""
        return [int(k) for k in np.unique(self.material)]

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


def file_sha256(path: str | os.PathLike | None) -> str | None:
    """SHA-256 of a file, or of a folder's files in sorted order (DICOM series); None if absent."""
    if path is None:
        return None
    p = Path(path)
    h = hashlib.sha256()
    if p.is_file():
        files = [p]
    elif p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
    else:
        return None
    block = bytearray(1 << 24)  # one buffer, refilled: no fresh memory per block
    view = memoryview(block)
    for f in files:
        if p.is_dir():
            h.update(str(f.relative_to(p)).encode() + b"\0")
        with open(f, "rb", buffering=0) as fh:
            while n := fh.readinto(block):
                h.update(view[:n])
    return h.hexdigest()


def _sha256_in_background(path: str | os.PathLike | None):
    """Start :func:`file_sha256` of ``path`` on a thread; returns a function that waits for the digest.

    hashlib and file reads release the GIL, so the digest of a mesh of GBs is computed
    on the second core while the model is built.
    """
    import threading

    out: list = []
    worker = threading.Thread(target=lambda: out.append(_catch(file_sha256, path)), daemon=True)
    worker.start()

    def result() -> str | None:
        worker.join()
        value = out[0]
        if isinstance(value, BaseException):
            raise value
        return value
    return result


def _catch(fn, *args):
    """``fn(*args)``, or the exception it raised (to re-raise on the caller's thread)."""
    try:
        return fn(*args)
    except BaseException as exc:  # noqa: BLE001 -- handed back to the caller, which raises it
        return exc


def provenance(source: str | os.PathLike | None, config: dict, element_type: str, order: int,
               digest: str | None = None) -> list[str]:
    """Heading lines: dicer version, the checksum of the mesh the deck is made from, the
    hash of the settings export reads; no name, path or date.

    The same for ``dicer run``, ``dicer export`` and the workflow: each exports the same
    smoothed mesh file with the same ``materials`` and ``export`` sections (what happened
    upstream is in that mesh), so the heading is the same byte for byte.
    """
    # the input is named by its content only: a file or folder name can hold a patient's
    # name (DICOM folders often do), and no identifier may reach a deck
    digest = (digest if digest is not None else file_sha256(source)) or "n/a"
    return [
        f"dicer {__version__} {element_type} model (order {order})",
        f"mesh sha256 {digest}",
        f"config sha256/16 {settings_hash(config)}",
    ]


def settings_hash(config: dict) -> str:
    """Hash of the ``materials`` and ``export`` settings that shape the file (all but ``export.verify``:
    how a file is checked does not change it)."""
    settings = stage_settings(config, "export")
    settings.get("export", {}).pop("verify", None)
    return config_hash(settings)


def resolve_element_type(mesh: Mesh, config: dict, path: Path) -> tuple[str, int]:
    """The element type and order from ``config['export']``, checked against the mesh's dimension."""
    ex = config.get("export", {})
    order = int(ex.get("order", 1))
    etype = ex.get("element_type")
    if order not in (1, 2):
        raise DicerError(f"{path}: export.order must be 1 or 2, got {order}")
    if etype is None:
        return DEFAULT_TYPES[(mesh.dim, order)], order
    etype = str(etype).upper()
    if etype not in ELEMENT_TYPES:
        raise DicerError(f"{path}: unknown element type {etype!r}; choose one of {', '.join(ELEMENT_TYPES)}")
    dim, etype_order = ELEMENT_TYPES[etype]
    if dim != mesh.dim:
        kinds = [t for t, (d, o) in ELEMENT_TYPES.items() if d == mesh.dim and o == order]
        raise DicerError(f"{path}: element type {etype} is for {dim}D meshes but the mesh is {mesh.dim}D; "
                         f"use one of {', '.join(kinds)}")
    if etype_order != order:
        kinds = [t for t, (d, o) in ELEMENT_TYPES.items() if d == mesh.dim and o == order]
        raise DicerError(f"{path}: export.order is {order} but element type {etype} has order {etype_order}; "
                         f"use one of {', '.join(kinds)} or set export.order={etype_order}")
    return etype, order


_CHUNK = 1 << 18  # elements per pass: temporaries stay small and are reused


def _neighbour_materials_by_lattice(mesh: Mesh) -> np.ndarray | None:
    """(M, F) material of the element across each face, 0 for none, from a voxel -> material grid
    (uint8, or uint16 for labels above 255).

    Valid when every element is an axis-aligned box of the lattice (voxel meshes and
    plane-merged meshes; smoothing moves points, not lattice indices); None otherwise.
    """
    dim = mesh.dim
    cells, material = mesh.cells, mesh.material
    m = cells.shape[0]
    if m == 0 or int(material.max()) > 65535:
        return None
    kind = np.uint8 if int(material.max()) < 256 else np.uint16
    offsets = HEX_CORNERS if dim == 3 else QUAD_CORNERS[:, :2]
    far = 6 if dim == 3 else 2
    shape = np.asarray(mesh.grid_shape, np.int64)[:dim]
    lattice = mesh.lattice[:, :dim]
    strides = np.array([int(np.prod(shape[i + 1 :])) for i in range(dim)], np.int64)
    nstrides = np.array([int(np.prod(shape[i + 1 :] + 1)) for i in range(dim)], np.int64)
    node_lin = lattice @ nstrides
    grid = np.zeros(int(np.prod(shape)), kind)
    covered = 0
    for start in range(0, m, _CHUNK):
        c = cells[start : start + _CHUNK]
        lo = lattice[c[:, 0]]
        ext = lattice[c[:, far]] - lo
        if ext.min() < 1 or lo.min() < 0 or np.any(lo + ext > shape) or ext.max() >= 64:
            return None
        lo_lin = node_lin[c[:, 0]]
        for k in range(1, offsets.shape[0]):  # every corner where the box puts it
            want = lo_lin + (offsets[k] * ext) @ nstrides
            if not np.array_equal(node_lin[c[:, k]], want):
                return None
        base = lo @ strides
        code = ext @ (64 ** np.arange(dim))
        mat = material[start : start + _CHUNK].astype(kind)
        for cc in np.unique(code):  # a few distinct box sizes (1 x 1 x 1 before plane merging)
            sel = code == cc
            e = [(int(cc) // 64**i) % 64 for i in range(dim)]
            b, v = base[sel], mat[sel]
            for off in np.ndindex(*e):
                grid[b + int(np.dot(off, strides))] = v
            covered += b.size * int(np.prod(e))
    if np.count_nonzero(grid) != covered:  # overlapping boxes
        return None
    axes = HEX_FACE_PLANES if dim == 3 else QUAD_SIDE_PLANES
    nb = np.empty((m, len(axes)), kind)
    for start in range(0, m, _CHUNK):
        c = cells[start : start + _CHUNK]
        lo = lattice[c[:, 0]]
        ext = lattice[c[:, far]] - lo
        base = lo @ strides
        for f, (axis, side) in enumerate(axes):
            if side == 0:
                inside = lo[:, axis] > 0
                idx = base - strides[axis]
            else:
                inside = lo[:, axis] + ext[:, axis] < shape[axis]
                idx = base + ext[:, axis] * strides[axis]
            np.putmask(idx, ~inside, 0)
            got = grid[idx]
            got[~inside] = 0
            nb[start : start + _CHUNK, f] = got
    return nb


def _neighbours_by_sort(cells: np.ndarray, dim: int, n_points: int) -> np.ndarray:
    """(M, F) element across each face, -1 for none, from a sort of face keys (any conforming mesh).

    A quad face is keyed by its smallest node and the node diagonally opposite it, an
    edge by its two nodes."""
    table = HEX_FACES if dim == 3 else QUAD_EDGES
    m, nf = cells.shape[0], table.shape[0]
    keys = np.empty((m, nf), np.int64)
    for f, face in enumerate(table):
        c = cells[:, face]
        if dim == 3:
            pos = np.argmin(c, axis=1)
            lo = np.take_along_axis(c, pos[:, None], 1)[:, 0]
            hi = np.take_along_axis(c, ((pos + 2) % 4)[:, None], 1)[:, 0]
        else:
            lo, hi = np.minimum(c[:, 0], c[:, 1]), np.maximum(c[:, 0], c[:, 1])
        keys[:, f] = lo * n_points + hi
    flat = keys.ravel()
    order = np.argsort(flat, kind="stable")
    sk = flat[order]
    first = np.flatnonzero(sk[1:] == sk[:-1])
    nb = np.full(m * nf, -1, np.int64)
    a, b = order[first], order[first + 1]
    nb[a] = b // nf
    nb[b] = a // nf
    return nb.reshape(m, nf)


def neighbour_materials(mesh: Mesh) -> np.ndarray:
    """(M, F) material label of the element across each face S1..S6 (2D: edge S1..S4), 0 for none."""
    nb = _neighbour_materials_by_lattice(mesh)
    if nb is None:
        idx = _neighbours_by_sort(np.asarray(mesh.cells, np.int64), mesh.dim, mesh.n_points)
        nb = np.where(idx >= 0, mesh.material[np.maximum(idx, 0)], 0)
    return nb


def _face_nodes(cells: np.ndarray, table: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elements (F,) and their nodes (F, c) of the faces marked in the (M, faces) bool array ``faces``."""
    e_idx, f_idx = np.nonzero(faces)
    return e_idx, cells[e_idx[:, None], table[f_idx]]


def _grouped_nodes(code: np.ndarray, nodes: np.ndarray, n_points: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Distinct codes (ascending) and, for each, the sorted distinct nodes paired with it.

    code : (F,) int64, one code per row of ``nodes``; nodes : (F, c) node indices.
    """
    key = np.unique((code[:, None] * n_points + nodes).ravel())  # int64: codes < 2**32, nodes < 2**31
    if not key.size:
        return key, []
    group, node = np.divmod(key, n_points)
    cut = np.flatnonzero(group[1:] != group[:-1]) + 1
    return group[np.r_[0, cut]], np.split(node, cut)


def _surface_sets(model: SolverModel, kinds: set[str], nb_mat: np.ndarray) -> None:
    """Exterior faces and surface, material boundary and interface node sets from neighbour materials.

    Sets come in the order EXTERIOR, <a>_BOUNDARY by label, <a>_<b> by label a then b
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
    if n >= 2**31:
        raise DicerError("node sets of models with 2**31 nodes or more are not supported; leave materials, "
                         "interfaces and exterior out of export.sets")
    exterior = np.zeros(n, bool)
    ext_e, ext_f = [], []
    bound_code, bound_nodes, pair_code, pair_nodes, pair_face = [], [], [], [], []
    for start in range(0, model.n_cells, _CHUNK):
        mat = model.material[start : start + _CHUNK].astype(np.int64)
        nbm = nb_mat[start : start + _CHUNK]
        cells = model.cells[start : start + _CHUNK]
        if "exterior" in kinds:
            f_idx, e_idx = np.nonzero((nbm == 0).T)  # grouped by face number
            ext_e.append(e_idx + start)
            ext_f.append(f_idx)
            exterior[cells[e_idx[:, None], table[f_idx]]] = True
        if "materials" in kinds:  # faces of a material with another (or none) behind them
            e_idx, nodes = _face_nodes(cells, table, nbm != mat[:, None])
            bound_code.append(mat[e_idx])
            bound_nodes.append(nodes)
        if "interfaces" in kinds:  # faces of material a with material b > a behind them
            later = nbm > mat[:, None]
            e_idx, nodes = _face_nodes(cells, table, later)
            pair_code.append(mat[e_idx] << 16 | nbm[later].astype(np.int64))  # labels <= MAX_LABEL < 2**16
            pair_nodes.append(nodes)
            pair_face.append(np.column_stack(np.nonzero(later)) + [start, 1])  # (element, face number)
    if "exterior" in kinds:
        e, f = np.concatenate(ext_e), np.concatenate(ext_f)
        order = np.lexsort((e, f))  # grouped by face number, elements ascending
        model.exterior = np.column_stack([e[order], f[order] + 1]).astype(np.int64)
        if exterior.any():
            model.node_sets["EXTERIOR"] = np.flatnonzero(exterior)
    width = table.shape[1]
    if "materials" in kinds:
        codes, groups = _grouped_nodes(np.concatenate(bound_code), np.concatenate(bound_nodes).reshape(-1, width), n)
        for k, ids in zip(codes.tolist(), groups):
            model.node_sets[f"{model.names[k]}_BOUNDARY"] = ids
    if "interfaces" in kinds:
        code = np.concatenate(pair_code)
        codes, groups = _grouped_nodes(code, np.concatenate(pair_nodes).reshape(-1, width), n)
        for c, ids in zip(codes.tolist(), groups):
            model.node_sets[f"{model.names[c >> 16]}_{model.names[c & 0xFFFF]}"] = ids
        # the same faces as (element, face number) rows per pair: by face number, elements ascending
        faces = np.concatenate(pair_face).astype(np.int64).reshape(-1, 2)
        order = np.lexsort((faces[:, 0], faces[:, 1], code))
        code, faces = code[order], faces[order]
        cut = np.flatnonzero(code[1:] != code[:-1]) + 1
        for c, rows in zip(code[np.r_[0, cut]].tolist() if code.size else [], np.split(faces, cut)):
            model.interfaces[f"{model.names[c >> 16]}_{model.names[c & 0xFFFF]}"] = rows


def prepare_model(mesh: Mesh, config: dict, source=None, path: Path | str = "model") -> SolverModel:
    """Validate ``mesh`` against ``config`` and build the SolverModel the writers share."""
    path = Path(path)
    etype, order = resolve_element_type(mesh, config, path)
    materials = config["materials"]
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
    ex = config.get("export", {})
    kinds = set(ex.get("sets", SET_KINDS))
    clash = name_clash([m["name"] for m in materials], kinds)
    if clash:
        raise DicerError(f"{path}: {clash}")
    digest = _sha256_in_background(source)
    names = {i + 1: m["name"] for i, m in enumerate(materials)}
    props = {i + 1: {"youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1.0e-9, **m}
             for i, m in enumerate(materials)}
    cells = np.asarray(mesh.cells, dtype=np.int64)
    lattice2 = None  # twice the lattice index (order 2: mid-edge nodes at half-integers)
    points = mesh.points
    nb_mat = None
    if kinds & {"materials", "interfaces", "exterior"} or (order == 2 and ex.get("midside_nodes") == "curved"):
        nb_mat = neighbour_materials(mesh)
    if order == 2:
        from dicer.mesh.quadratic import quadratic_mesh

        curved = ex.get("midside_nodes") == "curved"
        boundary = (nb_mat != mesh.material[:, None].astype(nb_mat.dtype)) if curved else None
        points, cells, lattice2 = quadratic_mesh(mesh, boundary)
    model = SolverModel(
        points=points, cells=cells, material=mesh.material.astype(np.int32), names=names, props=props,
        element_type=etype, dim=mesh.dim, order=order, thickness=float(ex.get("thickness", 1.0)),
        digits=int(ex.get("digits", 9)), use_heading=bool(ex.get("heading", True)),
    )
    if "planes" in kinds:
        g2 = 2 * np.asarray(mesh.grid_shape, np.int64)
        for axis in range(mesh.dim):
            for side, target in (("0", 0), ("1", g2[axis])):
                if lattice2 is None:
                    ids = np.flatnonzero(mesh.lattice[:, axis] == target // 2)
                else:
                    ids = np.flatnonzero(lattice2[:, axis] == target)
                if ids.size:
                    model.node_sets["XYZ"[axis] + side] = ids
    if kinds & {"materials", "interfaces", "exterior"}:
        _surface_sets(model, kinds, nb_mat)
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
    if mirrored(mesh.direction):
        model.cells = model.cells[:, HEX_MIRROR if model.order == 1 else HEX20_MIRROR]
        for rows in [model.exterior, *model.interfaces.values()]:
            if rows is not None and rows.size:
                rows[:, 1] = HEX_FACE_MIRROR[rows[:, 1]]
                rows[:] = rows[np.lexsort((rows[:, 0], rows[:, 1]))]  # grouped by face number again


def scanner_mesh(mesh: Mesh, model: SolverModel) -> Mesh:
    """The linear ``mesh`` as exported: ``model``'s points and cells, marked as scanner coordinates
    (so that reading the file back gives the lattice frame again); ``mesh`` itself if it has no direction."""
    if mesh.direction is None:
        return mesh
    out = mesh.copy()
    out.points, out.cells, out.scanner = model.points, model.cells, True
    return out


def _write(fmt: str, model: SolverModel, mesh: Mesh, tmp: Path, ex: dict) -> None:
    if fmt == "abaqus":
        from dicer.export.abaqus import write_abaqus

        write_abaqus(model, tmp)
    elif fmt == "vtu":
        from dicer.export.vtu import write_vtu

        write_vtu(model, scanner_mesh(mesh, model) if model.order == 1 else mesh, tmp)
    elif fmt == "patran":
        from dicer.export.patran import write_patran

        write_patran(model, tmp)
    elif fmt == "lsdyna":
        from dicer.export.lsdyna import write_lsdyna

        write_lsdyna(model, tmp)
    elif fmt == "exodus":
        from dicer.export.exodus import write_exodus

        write_exodus(model, tmp)
    elif fmt == "febio":
        from dicer.export.febio import write_febio

        write_febio(model, tmp, ex.get("febio_material", "isotropic elastic"))
    elif fmt == "gmsh":
        from dicer.export.vtu import write_meshio

        write_meshio(model, tmp, fmt)


def _verify(fmt: str, model: SolverModel, tmp: Path, path: Path, ex: dict) -> None:
    from dicer.export import readers

    try:
        if fmt == "abaqus" and ex.get("verify", "strict") == "meshio":
            readers.check_abaqus_meshio(tmp, model)
        elif fmt == "abaqus":
            readers.check_abaqus(tmp, model)
        elif fmt in ("vtu", "gmsh"):
            readers.check_meshio(tmp, model, fmt)
        elif fmt == "exodus":
            from dicer.export.exodus import check_exodus

            check_exodus(tmp, model)
        elif fmt == "febio":
            from dicer.export.febio import check_febio

            check_febio(tmp, model, ex.get("febio_material", "isotropic elastic"))
        elif fmt == "patran":
            readers.check_patran(tmp, model)
        elif fmt == "lsdyna":
            readers.check_lsdyna(tmp, model)
    except DicerError as exc:
        raise DicerError(f"{path}: read-back check failed: {exc}; the file was not written: check the disk "
                         "and export again") from None


def export_mesh(mesh: Mesh, path: str | os.PathLike, config: dict, source: str | os.PathLike | None = None,
                verify: bool = True) -> dict:
    """Write ``mesh`` to ``path`` in the format its extension names; returns a summary dict.

    config : the dicer configuration (``materials`` and ``export`` sections).
    source : the input the model was made from (its name and SHA-256 go into the provenance).
    verify : read the file back and check it before renaming it into place (default); an
        Abaqus deck with dicer's strict reader, or meshio's when ``export.verify`` is meshio.
    On any problem: DicerError, and no file at ``path``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise DicerError(f"{path}: unknown export format {path.suffix or '(none)'}; "
                         f"name the output with one of {', '.join(EXPORT_SUFFIXES)}")
    fmt = FORMATS[suffix]
    if fmt == "exodus":
        try:
            import netCDF4  # noqa: F401  (the Exodus writer needs it)
        except ImportError:
            raise DicerError(f"{path}: Exodus files need the netCDF4 package (pip install netCDF4); "
                             "or choose another format") from None
    if fmt == "febio" and mesh.dim != 3:
        raise DicerError(f"{path}: FEBio has no plane (2D) elements; export this {mesh.dim}D mesh "
                         "to .inp (CPS4/CPE4) or another format, or mesh a 3D volume for .feb")
    model = prepare_model(mesh, config, source, path)
    ex = config.get("export", {})
    with atomic_path(path) as tmp:
        try:
            _write(fmt, model, mesh, tmp, ex)
        except ValueError as exc:  # a number no field of the format can hold
            raise DicerError(f"{path}: cannot write the {fmt} file ({exc})") from None
        except OSError as exc:
            raise DicerError(f"{path}: cannot write ({exc.strerror}); choose a writable output path") from None
        if verify:
            _verify(fmt, model, tmp, path, ex)
        size = tmp.stat().st_size
    return {
        "format": fmt, "file": path.name, "nodes": model.n_points, "elements": model.n_cells,
        "element_type": model.element_type, "order": model.order, "bytes": size,
        "materials": {model.names[k]: int(np.count_nonzero(model.material == k)) for k in model.labels()},
        "node_sets": {name: int(ids.size) for name, ids in model.node_sets.items()},
        "exterior_faces": 0 if model.exterior is None else int(model.exterior.shape[0]),
        "verified": bool(verify),
    }


def benchmark_export(mesh: Mesh, folder: str | os.PathLike, suffix: str = ".inp", config: dict | None = None) -> dict:
    """Seconds and bytes of one export of ``mesh`` into ``folder`` (no read-back), for benchmarks.

    The file is deleted afterwards. ``config`` defaults to dicer's default configuration.
    """
    import time

    from dicer.config import load_config

    config = config or load_config()
    path = Path(folder) / f"bench_model{suffix}"
    t0 = time.perf_counter()
    info = export_mesh(mesh, path, config, source=None, verify=False)
    seconds = time.perf_counter() - t0
    path.unlink(missing_ok=True)
    return {"seconds": seconds, "bytes": info["bytes"], "elements": info["elements"], "nodes": info["nodes"]}
