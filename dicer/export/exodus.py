"""Exodus II (``.e`` / ``.exo``), written with the netCDF4 package as the Exodus II
netCDF mapping lays it out (the "large model" layout: one variable per coordinate).

::

    title                  dicer version, element type and order (no path, no input name)
    coordx coordy [coordz] node coordinates (float64), coor_names X Y [Z]
    connect<i>             one element block per material, elem_type HEX8 / HEX20 / QUAD4 / QUAD8,
                           eb_names = material names, eb_prop1 (ID) = material label
    elem_num_map           the element numbers of the Abaqus deck (dicer's element order)
    node_ns<i>             the node sets of the Abaqus deck, ns_names = set names
    elem_ss<i>, side_ss<i> side sets EXTERIOR, CAVITIES (walls of enclosed voids) and <a>_<b>
                           (interfaces): element and local side
    info_records           input SHA-256 and config hash

Elements are stored block by block, so an element's position in the file (what side
sets refer to) is its position in the block order; ``elem_num_map`` gives back dicer's
element number. Exodus numbers the sides of a hexahedron 1: y-, 2: x+, 3: y+, 4: x-,
5: z-, 6: z+ (Abaqus S1..S6 are z-, z+, y-, x+, y+, x-) and the edges of a quad as
Abaqus does. The 20-node hexahedron lists its mid-edge nodes as PATRAN does (bottom
edges, vertical edges, top edges), not as VTK and Abaqus do (bottom, top, vertical).

The file is netCDF classic with 64-bit offsets (CDF-2), which every Exodus reader
opens and which holds no timestamps, so reruns are byte-identical. No variable may
exceed 4 GiB in that format (about 27 M 20-node hexahedra in one block).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dicer import __version__
from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.mesh.topology import HEX20_EXODUS

EXODUS_TYPES = {(3, 1): "HEX8", (3, 2): "HEX20", (2, 1): "QUAD4", (2, 2): "QUAD8"}
HEX_SIDE = np.array([5, 6, 1, 2, 3, 4])
"""Exodus side number of the Abaqus faces S1..S6 of a hexahedron."""
QUAD_SIDE = np.array([1, 2, 3, 4])
"""Exodus side number of the Abaqus edges S1..S4 of a quad (the same)."""
NETCDF_FORMAT = "NETCDF3_64BIT_OFFSET"
_LIMIT = 2**32 - 4  # bytes of one variable in CDF-2
_MAX_ARRAYS = 8000  # netCDF variables (blocks, sets) an Exodus file may hold: their definition slows with the count


def node_order(dim: int, order: int) -> np.ndarray:
    """Position in dicer's node order of each node of the Exodus element.

    Parameters
    ----------
    dim, order : int
        2 or 3; 1 or 2.

    Returns
    -------
    int ndarray
        An index array.
    """
    if (dim, order) == (3, 2):
        return HEX20_EXODUS
    return np.arange({(3, 1): 8, (2, 1): 4, (2, 2): 8}[(dim, order)])


def side_numbers(dim: int) -> np.ndarray:
    """Exodus side number of each Abaqus face (edge) number.

    Parameters
    ----------
    dim : int
        2 (quad edges) or 3 (hexahedron faces).

    Returns
    -------
    (F,) int ndarray
        At index f - 1, the side of Abaqus face f.
    """
    return HEX_SIDE if dim == 3 else QUAD_SIDE


def title(model) -> str:
    """The file title: program, element type and order only (no input name: it may name a patient).

    Parameters
    ----------
    model : SolverModel

    Returns
    -------
    str
    """
    return f"dicer {__version__} {EXODUS_TYPES[(model.dim, model.order)]} model (order {model.order})"


def _name_table(names: list[str], width: int) -> np.ndarray:
    """(len(names), width) S1: each name's characters, NUL-padded."""
    data = np.zeros((len(names), width), "S1")
    for i, name in enumerate(names):
        raw = np.frombuffer(name.encode("ascii"), "S1")
        data[i, : raw.size] = raw
    return data


class _Definitions:
    """The variables of an Exodus file, defined before any value is written. Each definition
    ends the netCDF library's define mode, which rewrites the header and moves whatever lies
    after it: with values written as each variable was defined, and the coordinates and
    connectivity before the sets, 150 materials' blocks and sets behind 240 k hexahedra took
    72 s to export."""

    def __init__(self, nc):
        self.nc = nc
        self.pending: list = []

    def variable(self, name: str, kind: str, dims: tuple, values=None, attributes: dict | None = None):
        """Define variable ``name``; ``values``: an array, or a callable giving it, written by :meth:`write`."""
        var = self.nc.createVariable(name, kind, dims)
        for key, value in (attributes or {}).items():
            var.setncattr(key, value)
        if values is not None:
            self.pending.append((var, values))
        return var

    def names(self, name: str, dims: tuple, names: list[str]) -> None:
        self.variable(name, "S1", dims, _name_table(names, len(self.nc.dimensions[dims[1]])))

    def id_table(self, kind: str, count: str, ids, names: list[str]) -> None:
        """The status, ID property and names of the blocks or sets of ``kind`` (``eb``, ``ns``, ``ss``)."""
        self.variable(f"{kind}_status", "i4", (count,), np.ones(len(names), np.int32))
        self.variable(f"{kind}_prop1", "i4", (count,), np.asarray(ids, np.int32), {"name": "ID"})
        self.names(f"{kind}_names", (count, "len_name"), names)

    def write(self) -> None:
        for var, values in self.pending:
            var[:] = values() if callable(values) else values
        self.pending = []


def least_arrays(labels: np.ndarray, sets) -> tuple[int, int, int]:
    """The fewest netCDF variables an Exodus file of a model meshed from ``labels`` holds, known
    before the mesh: a block per material, with ``sets`` (``export.sets``) a boundary node set
    per material, an interface's node set and side set (two variables) per pair of materials
    that share a face, the exterior's node set and side set. Pairs that touch at an edge only,
    the cavities' sets and the plane sets add more.

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        The fixed label volume (0: background).
    sets : sequence of str

    Returns
    -------
    (variables, materials, pairs) : tuple of int
    """
    labels = np.asarray(labels)
    present = np.unique(labels)
    materials = int(np.count_nonzero(present))
    codes = []
    for axis in range(labels.ndim):
        a = np.moveaxis(labels, axis, 0)
        lo, hi = a[:-1], a[1:]
        touch = (lo != hi) & (lo > 0) & (hi > 0)  # in the labels' own type: only the pairs widened
        first, second = lo[touch].astype(np.int64), hi[touch].astype(np.int64)
        codes.append(np.minimum(first, second) << 32 | np.maximum(first, second))
    pairs = int(np.unique(np.concatenate(codes)).size) if codes else 0
    sets = set(sets)
    variables = (materials + (materials if "materials" in sets else 0) + (3 * pairs if "interfaces" in sets else 0)
                 + (3 if "exterior" in sets else 0))
    return variables, materials, pairs


def write_exodus(model, path: str | Path) -> None:
    """Write a SolverModel as an Exodus II file (see the module notes).

    Parameters
    ----------
    model : SolverModel
        Hexahedra or quads (order 2: 20-node hexahedra and 8-node quads).
    path : str or Path
        The ``.exo`` file.
    """
    try:
        _write(model, path)
    except RuntimeError as exc:  # what the netCDF library reports other than OSError
        raise ValueError(f"netCDF: {exc}") from None


def _write(model, path: str | Path) -> None:
    import netCDF4

    if max(model.n_points, model.n_cells) >= 2**31:
        raise ValueError("models with 2**31 nodes or elements or more do not fit Exodus's 32-bit ids")
    blocks = model.blocks()
    largest = max(e.size for _, e in blocks) * model.cells.shape[1] * 4
    if max(largest, model.n_points * 8) > _LIMIT:
        raise ValueError("a block or coordinate array above 4 GiB does not fit netCDF classic files; "
                         "downsample or crop the model")
    node_sets = model.node_sets
    side_sets = model.face_sets()
    arrays = len(blocks) + len(node_sets) + 2 * len(side_sets)
    if arrays > _MAX_ARRAYS:
        raise ValueError(f"{len(blocks)} element blocks, {len(node_sets)} node sets and {len(side_sets)} side sets "
                         f"make {arrays} netCDF variables, and the netCDF library's time to define them grows "
                         "with the square of their count (6,490 took 40 s here): export fewer sets (e.g. --set "
                         "'export.sets=[exterior]') or write an Abaqus deck (.inp)")
    dim = model.dim
    perm = node_order(dim, model.order)
    block_order = np.concatenate([e for _, e in blocks])
    position = np.empty(model.n_cells, np.int64)  # element index -> 1-based position in the file
    position[block_order] = np.arange(1, model.n_cells + 1)
    all_names = [model.names[k] for k, _ in blocks] + list(node_sets) + list(side_sets)
    len_name = max([32] + [len(n) for n in all_names]) + 1
    # provenance without the input's name (it may name a patient): its checksum and the config hash
    info = [line if not line.startswith("input ") else "input sha256 " + line.rsplit(" ", 1)[-1]
            for line in model.heading[1:]]
    # built in netCDF's memory (its moves at each definition are copies there) and written at once
    # by Python, whose write raises on a full disk (the library's own write at close did not)
    nc = netCDF4.Dataset(str(path), "w", format=NETCDF_FORMAT, memory=1)
    try:
        nc.set_fill_on()  # in memory, the gaps between variables would hold whatever the memory held
        nc.title = title(model)
        nc.api_version = np.float32(8.03)
        nc.version = np.float32(8.03)
        nc.floating_point_word_size = np.int32(8)
        nc.file_size = np.int32(1)
        nc.maximum_name_length = np.int32(len_name - 1)
        nc.int64_status = np.int32(0)
        for name, size in (("len_string", 33), ("len_line", 81), ("four", 4), ("len_name", len_name),
                           ("time_step", None), ("num_dim", dim), ("num_nodes", model.n_points),
                           ("num_elem", model.n_cells), ("num_el_blk", len(blocks))):
            nc.createDimension(name, size)
        if node_sets:
            nc.createDimension("num_node_sets", len(node_sets))
        if side_sets:
            nc.createDimension("num_side_sets", len(side_sets))
        if info:
            nc.createDimension("num_info", len(info))
        define = _Definitions(nc)
        # the sets first, the coordinates and connectivity last (the file's largest arrays, moved
        # at every definition after them), every value once all are defined
        define.variable("time_whole", "f8", ("time_step",))
        define.names("coor_names", ("num_dim", "len_name"), ["X", "Y", "Z"][:dim])
        define.id_table("eb", "num_el_blk", [k for k, _ in blocks], [model.names[k] for k, _ in blocks])
        if node_sets:
            define.id_table("ns", "num_node_sets", np.arange(1, len(node_sets) + 1), list(node_sets))
            for i, ids in enumerate(node_sets.values(), start=1):
                nc.createDimension(f"num_nod_ns{i}", ids.size)
                define.variable(f"node_ns{i}", "i4", (f"num_nod_ns{i}",), lambda ids=ids: (ids + 1).astype(np.int32))
        if side_sets:
            sides = side_numbers(dim)
            define.id_table("ss", "num_side_sets", np.arange(1, len(side_sets) + 1), list(side_sets))
            for i, faces in enumerate(side_sets.values(), start=1):
                nc.createDimension(f"num_side_ss{i}", faces.shape[0])
                count = (f"num_side_ss{i}",)
                define.variable(f"elem_ss{i}", "i4", count, lambda f=faces: position[f[:, 0]].astype(np.int32))
                define.variable(f"side_ss{i}", "i4", count, lambda f=faces: sides[f[:, 1] - 1].astype(np.int32))
        if info:
            define.names("info_records", ("num_info", "len_line"), [s[:80] for s in info])
        etype = EXODUS_TYPES[(dim, model.order)]
        for i, (k, elements) in enumerate(blocks, start=1):
            nc.createDimension(f"num_el_in_blk{i}", elements.size)
            nc.createDimension(f"num_nod_per_el{i}", perm.size)
            define.variable(f"connect{i}", "i4", (f"num_el_in_blk{i}", f"num_nod_per_el{i}"),
                            lambda e=elements: (model.cells[e][:, perm] + 1).astype(np.int32), {"elem_type": etype})
        define.variable("elem_num_map", "i4", ("num_elem",), lambda: (block_order + 1).astype(np.int32))
        for j, axis in enumerate("xyz"[:dim]):
            define.variable(f"coord{axis}", "f8", ("num_nodes",), lambda j=j: model.points[:, j])
        define.write()
    finally:
        image = nc.close()  # the file's bytes
    with open(path, "wb") as f:
        f.write(image)


def _text(var) -> list[str]:
    var.set_auto_mask(False)
    return [b"".join(row).rstrip(b"\0").decode("ascii", "replace") for row in np.asarray(var[:])]


def read_exodus(path: str | Path) -> dict:
    """Read an Exodus II file as dicer writes it, with netCDF4 directly.

    Parameters
    ----------
    path : str or Path
        Written by :func:`write_exodus` (netCDF-4, Exodus II).

    Returns
    -------
    dict
        ``dim``, ``title``, ``points`` (N, 3) float64, ``element_type``, ``blocks`` (list
        of (name, ID, (m, k) 0-based connectivity in the file's node order)),
        ``elem_num_map`` (M,) 1-based, ``node_sets`` (name -> 0-based node indices) and
        ``side_sets`` (name -> (F, 2) int rows of 1-based element position and side
        number).

    Raises
    ------
    DicerError
        Anything missing or malformed.
    """
    import netCDF4

    try:
        nc = netCDF4.Dataset(path, "r")
    except OSError as exc:
        raise DicerError(f"netCDF4 cannot open the file ({exc})") from None
    with nc:
        v, d = nc.variables, nc.dimensions
        for key in ("num_dim", "num_nodes", "num_elem", "num_el_blk"):
            if key not in d:
                raise DicerError(f"dimension {key} missing")
        dim, n, m, nblk = (len(d[k]) for k in ("num_dim", "num_nodes", "num_elem", "num_el_blk"))
        if dim not in (2, 3):
            raise DicerError(f"num_dim is {dim}")
        coord = []
        for axis in "xyz"[:dim]:
            if f"coord{axis}" not in v:
                raise DicerError(f"coord{axis} missing")
            coord.append(np.asarray(v[f"coord{axis}"][:], np.float64))
        points = np.zeros((n, 3))
        points[:, :dim] = np.column_stack(coord)
        names = _text(v["eb_names"]) if "eb_names" in v else [""] * nblk
        ids = np.asarray(v["eb_prop1"][:]).tolist() if "eb_prop1" in v else [0] * nblk
        blocks, types = [], set()
        for i in range(1, nblk + 1):
            if f"connect{i}" not in v:
                raise DicerError(f"connect{i} missing")
            var = v[f"connect{i}"]
            types.add(str(var.getncattr("elem_type")).upper())
            blocks.append((names[i - 1], int(ids[i - 1]), np.asarray(var[:], np.int64) - 1))
        if sum(b[2].shape[0] for b in blocks) != m:
            raise DicerError(f"the blocks hold {sum(b[2].shape[0] for b in blocks)} elements, num_elem is {m}")
        if len(types) > 1:
            raise DicerError(f"element types {sorted(types)} in one model")
        out = {"dim": dim, "title": str(getattr(nc, "title", "")), "points": points,
               "element_type": types.pop() if types else "", "blocks": blocks,
               "elem_num_map": np.asarray(v["elem_num_map"][:], np.int64) if "elem_num_map" in v else None,
               "node_sets": {}, "side_sets": {}, "coor_names": _text(v["coor_names"]) if "coor_names" in v else []}
        if "num_node_sets" in d:
            ns_names = _text(v["ns_names"])
            for i, name in enumerate(ns_names, start=1):
                out["node_sets"][name] = np.asarray(v[f"node_ns{i}"][:], np.int64) - 1
        if "num_side_sets" in d:
            ss_names = _text(v["ss_names"])
            for i, name in enumerate(ss_names, start=1):
                out["side_sets"][name] = np.column_stack([np.asarray(v[f"elem_ss{i}"][:], np.int64),
                                                          np.asarray(v[f"side_ss{i}"][:], np.int64)])
    return out


def check_exodus(path: str | Path, model) -> None:
    """Re-read an Exodus II file with :func:`read_exodus` and compare it with the model.

    Counts, coordinates (exact), blocks (names, IDs, connectivity), element numbers,
    node sets and side sets.

    Parameters
    ----------
    path : str or Path
        The Exodus file.
    model : SolverModel
        What it should hold.

    Raises
    ------
    DicerError
        The first difference.
    """
    got = read_exodus(path)
    if got["dim"] != model.dim:
        raise DicerError(f"num_dim is {got['dim']}, expected {model.dim}")
    if got["points"].shape[0] != model.n_points:
        raise DicerError(f"{got['points'].shape[0]} nodes read back, expected {model.n_points}")
    if not np.array_equal(got["points"][:, : model.dim], model.points[:, : model.dim]):
        raise DicerError("node coordinates differ")
    if got["coor_names"] != ["X", "Y", "Z"][: model.dim]:
        raise DicerError(f"coor_names are {got['coor_names']}")
    want_type = EXODUS_TYPES[(model.dim, model.order)]
    if got["element_type"] != want_type:
        raise DicerError(f"element type {got['element_type']} read back, expected {want_type}")
    blocks = model.blocks()
    if len(got["blocks"]) != len(blocks):
        raise DicerError(f"{len(got['blocks'])} element blocks read back, expected {len(blocks)} (one per material)")
    perm = node_order(model.dim, model.order)
    for (k, elements), (name, ident, conn) in zip(blocks, got["blocks"]):
        if name != model.names[k] or ident != k:
            raise DicerError(f"block {name!r} (ID {ident}) read back, expected {model.names[k]!r} (ID {k})")
        if not np.array_equal(conn, model.cells[elements][:, perm]):
            raise DicerError(f"connectivity of block {name} differs")
    block_order = np.concatenate([e for _, e in blocks])
    if got["elem_num_map"] is None or not np.array_equal(got["elem_num_map"], block_order + 1):
        raise DicerError("elem_num_map differs")
    if list(got["node_sets"]) != list(model.node_sets):
        raise DicerError(f"node sets {list(got['node_sets'])} read back, expected {list(model.node_sets)}")
    for name, ids in model.node_sets.items():
        if not np.array_equal(got["node_sets"][name], ids):
            raise DicerError(f"node set {name} differs")
    position = np.empty(model.n_cells, np.int64)
    position[block_order] = np.arange(1, model.n_cells + 1)
    want = model.face_sets()
    if list(got["side_sets"]) != list(want):
        raise DicerError(f"side sets {list(got['side_sets'])} read back, expected {list(want)}")
    sides = side_numbers(model.dim)
    for name, faces in want.items():
        rows = np.column_stack([position[faces[:, 0]], sides[faces[:, 1] - 1]])
        if not np.array_equal(got["side_sets"][name], rows):
            raise DicerError(f"side set {name} differs")


FORMAT = Format("exodus", (".e", ".exo"), write_exodus, check_exodus,
                requires=("netCDF4", "Exodus files need the netCDF4 package (pip install netCDF4); "
                                     "or choose another format"))
