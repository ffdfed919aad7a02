"""Closed STL surfaces, one per material, for CAD and for viewing (``dicer surface``).

A material's surface is the set of its elements' faces with another material, or none,
behind them: each quad face split into two triangles along its 0-2 diagonal, the corners
in the order that makes the normal point out of the material. Faces shared by two
elements of the material are left out, so the surface of a conforming mesh is closed:
every edge belongs to exactly two triangles, which run along it in opposite directions.
Where two materials meet, each surface holds the interface, oppositely oriented.

Files are binary STL (80-byte header, triangle count, 50 bytes per triangle: normal and
three corners as float32, attribute 0), in the model's coordinates (scanner coordinates,
mm, as every export; docs/coordinates.md). Each file is read back before it is renamed
into place: its corners welded by exact value must give a closed, consistently oriented
surface whose enclosed volume matches the one computed in float64.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from dicer import __version__
from dicer.arrays import nonzero, norm
from dicer.errors import DicerError
from dicer.io.atomic import atomic_path
from dicer.mesh.frame import mirrored, to_scanner
from dicer.mesh.metrics import element_volumes
from dicer.mesh.model import Mesh
from dicer.mesh.topology import HEX_FACES

_RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
assert _RECORD.itemsize == 50


def material_triangles(mesh: Mesh, label: int, nb_mat: np.ndarray) -> np.ndarray:
    """The outward triangles of one material's surface.

    Triangles come face by face in element order.

    Parameters
    ----------
    mesh : Mesh
    label : int
    nb_mat : (M, 6) int ndarray
        Material across each face (0 for none), from
        :func:`dicer.mesh.faces.neighbour_materials`.

    Returns
    -------
    (T, 3) int64 ndarray
        Node indices.
    """
    own = mesh.material == label
    faces = own[:, None] & (nb_mat != label)
    e_idx, f_idx = nonzero(faces)
    quads = mesh.cells[e_idx[:, None], HEX_FACES[f_idx]]  # (F, 4)
    tris = np.empty((quads.shape[0], 2, 3), np.int64)
    tris[:, 0] = quads[:, [0, 1, 2]]
    tris[:, 1] = quads[:, [0, 2, 3]]
    return tris.reshape(-1, 3)


def enclosed_volume(points: np.ndarray, tris: np.ndarray) -> float:
    """Volume a closed, outward triangle surface encloses (divergence theorem).

    Summed about the centre of the points, so that far-off scanner coordinates lose no digits.

    Parameters
    ----------
    points : (N, 3) float ndarray
    tris : (T, 3) int ndarray

    Returns
    -------
    float
        mm^3.
    """
    centre = points.mean(axis=0) if len(points) else np.zeros(3)
    a, b, c = (points[tris[:, k]] - centre for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def open_edges(tris: np.ndarray) -> int:
    """How many directed edges break a closed, consistently oriented surface.

    Edges used twice in one direction, or with no partner running the other way.

    Parameters
    ----------
    tris : (T, 3) int ndarray

    Returns
    -------
    int
    """
    if tris.size == 0:
        return 0
    a = tris.ravel()
    b = tris[:, [1, 2, 0]].ravel()
    n = int(tris.max()) + 1
    key = np.sort(a * n + b)
    twice = int(np.count_nonzero(key[1:] == key[:-1]))
    back = b * n + a
    pos = np.searchsorted(key, back)
    pos[pos == key.size] = 0
    return twice + int(np.count_nonzero(key[pos] != back))


def _header(name: str) -> bytes:
    # a binary STL must not start with "solid" (readers would take it for ASCII)
    text = f"dicer {__version__} surface of material {name} (mm)".encode()[:80]
    return text.ljust(80, b" ")


def write_stl(path: Path, points: np.ndarray, tris: np.ndarray, name: str) -> None:
    """Write triangles as a binary STL file.

    Parameters
    ----------
    path : Path
    points : (N, 3) float64 ndarray
    tris : (T, 3) int ndarray
        Node indices.
    name : str
        Goes into the header.
    """
    corners = points[tris]  # (T, 3, 3) float64
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = norm(normal, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = np.where(length > 0, normal / length, 0.0)
    records = np.zeros(tris.shape[0], _RECORD)
    records["normal"] = normal
    records["corners"] = corners
    with open(path, "wb") as f:
        f.write(_header(name))
        f.write(np.uint32(tris.shape[0]).astype("<u4").tobytes())
        f.write(records.tobytes())


def read_stl(path: str | os.PathLike) -> tuple[bytes, np.ndarray]:
    """The header and the triangle corners of a binary STL file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    header : bytes
    corners : (T, 3, 3) float32 ndarray
    """
    data = Path(path).read_bytes()
    if len(data) < 84:
        raise DicerError(f"{path}: not a binary STL file (shorter than its 84-byte header)")
    count = int(np.frombuffer(data, "<u4", 1, 80)[0])
    if len(data) != 84 + 50 * count:
        raise DicerError(f"{path}: binary STL of {count} triangles must hold {84 + 50 * count} bytes, "
                         f"it holds {len(data)}")
    return data[:80], np.frombuffer(data, _RECORD, count, 84)["corners"]


def weld(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles from triangle corners, corners equal bit for bit made one vertex
    (as STL readers weld them).

    Parameters
    ----------
    corners : (T, 3, 3) ndarray

    Returns
    -------
    vertices : (V, 3) ndarray
    triangles : (T, 3) int ndarray
    """
    flat = np.ascontiguousarray(corners.reshape(-1, 3))
    rows = flat.view(np.dtype((np.void, flat.dtype.itemsize * 3))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    return flat[first], inverse.reshape(-1, 3).astype(np.int64)


def check_stl(path: Path, name: str, triangles: int, volume: float) -> None:
    """Check that an STL file holds a closed, outward surface of the expected size.

    Parameters
    ----------
    path : Path
    name : str
        The material, named in error messages.
    triangles : int
        Triangles expected.
    volume : float
        Enclosed volume expected, mm^3 (to float32 precision).

    Raises
    ------
    DicerError
        Anything else.
    """
    header, corners = read_stl(path)
    if header != _header(name) or corners.shape[0] != triangles:
        raise DicerError(f"{corners.shape[0]} triangles read back, {triangles} written")
    points, tris = weld(corners)
    bad = open_edges(tris)
    if bad:
        raise DicerError(f"{bad} triangle edge(s) of the file are not shared by exactly two triangles")
    got = enclosed_volume(points.astype(np.float64), tris)
    if abs(got - volume) > 1e-5 * abs(volume) + 1e-9:
        raise DicerError(f"the file encloses {got:.6g} mm^3, the surface written {volume:.6g} mm^3")


def write_surfaces(mesh: Mesh, folder: str | os.PathLike, names: list[str], only: list[str] | None = None) -> dict:
    """Write ``<folder>/<name>.stl`` for each material (or those named in ``only``).

    Every surface is made and checked before any file is renamed into place.

    Parameters
    ----------
    mesh : Mesh
        3D.
    folder : str or os.PathLike
    names : list of str
        Material names by label (names[0] is label 1's).
    only : list of str, optional
        The materials wanted; default all present.

    Returns
    -------
    dict
        Per material: file, triangles, enclosed and element volume (mm^3).

    Raises
    ------
    DicerError
        On any problem; no file is written.
    """
    from dicer.mesh.faces import neighbour_materials

    folder = Path(folder)
    if mesh.dim != 3:
        raise DicerError(f"{folder}: STL surfaces are made of 3D elements' faces, but the mesh is 2D; "
                         "mesh a 3D volume")
    present = [int(k) for k in np.unique(mesh.material)]
    if max(present) > len(names):
        raise DicerError(f"{folder}: the mesh has material label {max(present)} but {len(names)} material "
                         "name(s) are known; give the materials (--materials or the config)")
    wanted = present if only is None else []
    for name in only or []:
        if name not in names:
            raise DicerError(f"{folder}: no material named {name!r}; choose from {', '.join(names)}")
        if names.index(name) + 1 not in present:
            raise DicerError(f"{folder}: material {name!r} has no elements in the mesh; choose from "
                             f"{', '.join(names[k - 1] for k in present)}")
        wanted.append(names.index(name) + 1)
    nb_mat = neighbour_materials(mesh)
    points = mesh.points
    if mesh.direction is not None:
        points = to_scanner(points, mesh.spacing, mesh.origin, mesh.direction)
    flip = mirrored(mesh.direction)
    element_volume = np.bincount(mesh.material, weights=element_volumes(mesh.points, mesh.cells))
    info, surfaces = {}, []
    for label in sorted(set(wanted)):
        name = names[label - 1]
        tris = material_triangles(mesh, label, nb_mat)
        if flip:  # a reflection turns the outward order inward
            tris = tris[:, ::-1]
        bad = open_edges(tris)
        if bad:
            raise DicerError(f"{folder}: the surface of material {name} is not closed: {bad} triangle edge(s) "
                             "are not shared by exactly two triangles (elements of the material that touch "
                             "along an edge only); run 'dicer fix' on the labels before meshing")
        volume = enclosed_volume(points, tris)
        info[name] = {"file": f"{name}.stl", "triangles": int(tris.shape[0]), "volume_mm3": volume,
                      "element_volume_mm3": float(element_volume[label])}
        surfaces.append((name, tris, volume))
    with contextlib.ExitStack() as stack:
        for name, tris, volume in surfaces:
            path = folder / f"{name}.stl"
            tmp = stack.enter_context(atomic_path(path))
            write_stl(tmp, points, tris, name)
            try:
                check_stl(tmp, name, tris.shape[0], volume)
            except DicerError as exc:
                raise DicerError(f"{path}: read-back check failed: {exc}; check the disk and write again") from None
    return info
