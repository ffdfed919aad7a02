"""Shared parts of the read-back checks: comparing what was read with the model, meshio's
check of VTU and Gmsh files, and fixed-column access to the lines of a text file.

The strict readers of dicer's text decks live with their writers: ``read_abaqus`` in
:mod:`dicer.export.abaqus`, ``read_patran`` in :mod:`dicer.export.patran`, ``read_lsdyna``
in :mod:`dicer.export.lsdyna` (also importable from here). Every ``check_*`` compares node
count, coordinates (to print precision), connectivity and materials with the model that
was written, and the sets the file holds, and raises DicerError on the first difference.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.textparse import FormatError, parse_column
from dicer.mesh.topology import MESHIO_TYPES

# the readers and checks that moved to their format's module, still importable from here
_MOVED = {"read_abaqus": "abaqus", "check_abaqus": "abaqus", "check_abaqus_meshio": "abaqus",
          "_meshio_abaqus_types": "abaqus", "NODES_PER_ELEMENT": "abaqus",
          "read_patran": "patran", "check_patran": "patran", "read_lsdyna": "lsdyna", "check_lsdyna": "lsdyna"}


def __getattr__(name: str):
    if name in _MOVED:
        return getattr(importlib.import_module(f"dicer.export.{_MOVED[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def tolerance(model, digits: int) -> float:
    """The largest coordinate difference a read-back may show.

    Parameters
    ----------
    model : SolverModel
    digits : int
        Significant digits the file holds.

    Returns
    -------
    float
        mm: one unit in the last digit of the largest coordinate.
    """
    # the largest and the smallest: no temporary of the size of the points (157 MB at 6.5 M nodes)
    scale = max(float(model.points.max()), -float(model.points.min())) if model.n_points else 1.0
    return max(scale, 1e-30) * 10.0 ** (1 - digits)


def compare(model, points: np.ndarray, cells: np.ndarray, material: np.ndarray, what: str,
            digits: int | None = None) -> None:
    """Check what a reader got against the model.

    Parameters
    ----------
    model : SolverModel
    points : (N, 3) float64 ndarray
        Nodes read; compared to ``digits`` significant digits.
    cells : (M, n) int ndarray
        Connectivity read, 0-based, file order = element number order.
    material : (M,) int ndarray
        Labels read.
    what : str
        The file, named in error messages.
    digits : int, optional
        Default: the model's.

    Raises
    ------
    DicerError
        At the first difference.
    """
    if points.shape[0] != model.n_points:
        raise DicerError(f"{what} has {points.shape[0]} nodes, expected {model.n_points}")
    if cells.shape != model.cells.shape:
        raise DicerError(f"{what} has elements of shape {cells.shape}, expected {model.cells.shape}")
    dim = model.dim
    err = np.abs(points[:, :dim] - model.points[:, :dim]).max() if model.n_points else 0.0
    if not err <= tolerance(model, digits or model.digits):
        raise DicerError(f"{what}: node coordinates differ by {err:.3g} mm")
    if not np.array_equal(cells, model.cells):
        bad = int(np.flatnonzero((cells != model.cells).any(axis=1))[0])
        raise DicerError(f"{what}: connectivity of element {bad + 1} differs")
    if not np.array_equal(material, model.material):
        raise DicerError(f"{what}: element materials differ")


def check_meshio(path: str | Path, model, file_format: str) -> None:
    """Re-read a VTU or Gmsh file with meshio and compare it with the model (cell data ``material``).

    Parameters
    ----------
    path : str or Path
    model : SolverModel
    file_format : str
        meshio's name of the format.

    Raises
    ------
    DicerError
        A file meshio cannot read, or one that differs from ``model``.
    """
    import meshio

    try:
        m = meshio.read(path, file_format=file_format)
    except Exception as exc:
        raise DicerError(f"meshio cannot read the file ({type(exc).__name__}: {str(exc)[:100]})") from None
    want = MESHIO_TYPES[(model.dim, model.order)]
    types = {b.type for b in m.cells}
    if types != {want}:
        raise DicerError(f"element types {sorted(types)} read back, expected {want}")
    cells = np.concatenate([b.data for b in m.cells]).astype(np.int64)
    key = "material" if "material" in m.cell_data else "gmsh:physical"
    if key not in m.cell_data:
        raise DicerError("no material cell data read back")
    material = np.concatenate(m.cell_data[key]).astype(np.int32)
    compare(model, np.asarray(m.points, float), cells, material, "the file")
    if file_format == "vtu":
        from dicer.mesh.metrics import QUALITY_DATA

        for name in QUALITY_DATA:
            got = np.concatenate(m.cell_data.get(name, [np.empty(0)]))
            if got.shape != (model.n_cells,):
                raise DicerError(f"cell data {name} read back with {got.size} values for {model.n_cells} elements")
    # the material names (VTU field data, Gmsh $PhysicalNames) are part of the file too
    names = {name: int(np.asarray(v).ravel()[0]) for name, v in m.field_data.items()
             if np.asarray(v).size == 2 and name not in ("spacing", "origin", "grid_shape")}
    want = {model.names[k]: k for k in (model.labels() if file_format == "gmsh" else model.names)}
    if names != want:
        raise DicerError(f"material names {names} read back, expected {want}")


# --- strict fixed-width readers -------------------------------------------------------------


class Lines:
    """A text file as byte lines, with vectorised access to fixed columns of many lines.

    Parameters
    ----------
    path : str or Path

    Raises
    ------
    DicerError
        A file that ends in the middle of a line.
    """

    def __init__(self, path: str | Path):
        self.data = Path(path).read_bytes()
        if not self.data.endswith(b"\n"):
            raise DicerError("the file ends in the middle of a line (truncated?)")
        self.arr = np.frombuffer(self.data, np.uint8)
        self.ends = np.flatnonzero(self.arr == 10)
        self.starts = np.concatenate([[0], self.ends[:-1] + 1])
        self.lengths = self.ends - self.starts

    def __len__(self) -> int:
        return int(self.ends.size)

    def text(self, i: int) -> str:
        """Line ``i`` as text."""
        return self.data[self.starts[i] : self.ends[i]].decode("ascii", "replace")

    def columns(self, rows: np.ndarray, first: int, width: int) -> np.ndarray:
        """(n, width) uint8: columns first..first+width-1 (0-based) of the lines ``rows``."""
        if rows.size == 0:
            return np.zeros((0, width), np.uint8)
        if rows.max() >= len(self) or np.any(self.lengths[rows] < first + width):
            raise DicerError(f"lines too short for columns {first + 1}-{first + width}")
        at = self.starts[rows] + first
        step = int(at[1] - at[0]) if at.size > 1 else 1
        if step > 0 and np.all(np.diff(at) == step):  # evenly spaced lines (fixed-length packets): a view
            view = np.lib.stride_tricks.as_strided(self.arr[at[0] :], shape=(at.size, width), strides=(step, 1))
            return view
        return self.arr[at[:, None] + np.arange(width)]

    def _convert(self, rows: np.ndarray, first: int, width: int, dtype, what: str, kind: str) -> np.ndarray:
        view = self.columns(rows, first, width)
        if rows.size > 64:  # the fields as dicer writes them, at array speed (dicer.export.textparse)
            try:
                values = parse_column(view)
                if values.dtype.kind == np.dtype(dtype).kind:
                    return values.astype(dtype, copy=False)
            except FormatError:
                pass  # a negative integer or a bad field: numpy's conversion takes or names it
        cols = np.ascontiguousarray(view).view(f"S{width}").ravel()
        try:
            return cols.astype(dtype)
        except ValueError:
            pass
        # name the first line that does not convert: find its chunk, then the line (error path only)
        for start in range(0, cols.size, 1 << 12):
            try:
                cols[start : start + (1 << 12)].astype(dtype)
            except ValueError:
                for i in range(start, min(start + (1 << 12), cols.size)):
                    try:
                        cols[i : i + 1].astype(dtype)
                    except ValueError:
                        text = cols[i].decode("ascii", "replace")
                        raise DicerError(f"line {int(rows[i]) + 1}: {what}: {text!r} in columns "
                                         f"{first + 1}-{first + width} is not {kind}") from None
        raise DicerError(f"{what}: not {kind} in columns {first + 1}-{first + width}")

    def ints(self, rows: np.ndarray, first: int, width: int, what: str) -> np.ndarray:
        """(n,) int64: the integers in columns first..first+width-1 of the lines ``rows``."""
        return self._convert(rows, first, width, np.int64, what, "an integer")

    def floats(self, rows: np.ndarray, first: int, width: int, what: str) -> np.ndarray:
        """(n,) float64: the numbers in columns first..first+width-1 of the lines ``rows``."""
        return self._convert(rows, first, width, np.float64, what, "a number")

    def expect(self, rows: np.ndarray, first: int, text: bytes, what: str) -> None:
        """Raise DicerError unless the lines ``rows`` hold ``text`` from column ``first`` on."""
        got = self.columns(rows, first, len(text))
        if not np.all(got == np.frombuffer(text, np.uint8)):
            bad = int(rows[np.flatnonzero((got != np.frombuffer(text, np.uint8)).any(axis=1))[0]])
            raise DicerError(f"line {bad + 1}: expected {text.decode()!r} for {what}")

    def lengths_are(self, rows: np.ndarray, n: int, what: str) -> None:
        """Raise DicerError unless the lines ``rows`` exist and have ``n`` columns each."""
        if rows.size and rows.max() >= len(self):
            raise DicerError(f"the file ends after {len(self)} lines, before its {what} cards (truncated?)")
        if rows.size and np.any(self.lengths[rows] != n):
            bad = int(rows[np.flatnonzero(self.lengths[rows] != n)[0]])
            raise DicerError(f"line {bad + 1}: {what} card has {self.lengths[bad]} columns, expected {n}")


def named(reader, path: str | Path) -> dict:
    """Call a reader with the file's name at the head of its error message.

    Parameters
    ----------
    reader : callable
        ``reader(path)`` -> dict.
    path : str or Path

    Returns
    -------
    dict
        What ``reader`` returns.

    Raises
    ------
    DicerError
        The reader's, with the name and a hint.
    """
    try:
        return reader(path)
    except DicerError as exc:
        raise DicerError(f"{path}: {exc}; dicer's strict readers read files exactly as dicer writes them: "
                         "export the mesh again") from None
