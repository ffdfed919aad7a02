"""Models of the validation cases made by dicer's own command, and the parts of their decks
the load steps need.

``build`` runs ``dicer run --labels`` on a label image (fix, mesh, merge, smooth, export
to ``model.inp``, quality) with ``--set`` overrides, then ``dicer export --order 2`` on the
smoothed mesh, exactly as a user would; given a grey-value image instead (``scan=True``) it
runs ``dicer run`` on the image (segment by a manual threshold, downsample, fix, ...), which
passes the scan to the smooth stage (``smooth.surface_from_image``). ``Deck`` reads a written deck back (dicer's strict
reader) and finds element faces: on a bounding plane of the model, or free (the exterior
less the bounding planes: a hole's rim, a bore).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.mesh.topology import HEX20_FACES, HEX_FACES, QUAD8_SIDES, QUAD_EDGES
from dicer.validation.geometry import THRESHOLD

E_MODULUS, POISSON, DENSITY = 1000.0, 0.3, 1e-9  # MPa, -, t/mm^3; stress ratios do not depend on them

BASE_SMOOTHING = """\
smooth:  # the study's base, the smoothing defaults until 5 December 2026: a row's --set changes it
  surface_from_labels: false
  min_scaled_jacobian: 0.2
  pillow: false
  label_samples: faces
  label_surface_radius: 5
"""
"""The smoothing every case starts from: the labels' smoothing alone at the floor 0.2, without
the pillow layer (the defaults until 5 December 2026; those until 7 December 2026, the labels'
fit and the floor 0.3, are the row ``labels fit+merge, min SJ 0.3``, and today's add the layer,
a label volume's staircase relaxed and the fit over 7 voxels: ``dicer.validation.study.DEFAULTS``)."""

CONFIG = f"""\
labels:
  map: {{1: solid}}
materials:
  - {{name: solid, youngs_modulus: {E_MODULUS}, poissons_ratio: {POISSON}, density: {DENSITY}}}
export:
  thickness: 1.0
  midside_nodes: midpoint  # the study's base: a row's --set changes it
{BASE_SMOOTHING}"""

SCAN_CONFIG = f"""\
materials:
  - {{name: solid, youngs_modulus: {E_MODULUS}, poissons_ratio: {POISSON}, density: {DENSITY}}}
segment:
  method: manual
  thresholds: [{THRESHOLD}]
  opening_radius: 0
  closing_radius: 0
  keep: all
smooth:
  surface_from_image: true
  min_scaled_jacobian: 0.2  # the study's base (BASE_SMOOTHING)
  pillow: false
  label_samples: faces
  label_surface_radius: 5
export:
  thickness: 1.0
  midside_nodes: midpoint
"""
"""A grey-value image: one material above the threshold, no morphology (the threshold alone
decides, as the label images' voxel-centre rule does), and the smoothing pulls the surface
onto the image's iso-line."""


def build(labels: np.ndarray, folder: str | os.PathLike, sets: list[str] = (), orders=(1, 2),
          scan: bool = False) -> dict:
    """Make the models of a label image (or a grey-value image) in a folder.

    Parameters
    ----------
    labels : uint8 or float ndarray
        [x, y(, z)], 1 mm voxels: labels, or with ``scan`` grey values (segmented at
        ``THRESHOLD``).
    folder : str or os.PathLike
    sets : list of str, optional
        ``--set KEY=VALUE`` overrides (e.g. ``smooth.coefficient=0.8``).
    orders : sequence of int, optional
        Element orders of the decks.
    scan : bool, optional
        ``labels`` is a scan: written as ``scan.nii.gz`` and given to ``dicer run`` with
        ``SCAN_CONFIG``.

    Returns
    -------
    dict
        ``{"decks": {order: path of the deck}, "quality": quality.json, "smooth": the
        smooth stage's report}``.

    Raises
    ------
    DicerError
        A stage fails.
    """
    from dicer.cli import main

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if scan:
        from dicer.image import Volume
        from dicer.io.images import write_image

        write_image(Volume(np.asarray(labels, np.float32), (1.0,) * labels.ndim), folder / "scan.nii.gz")
        source = [str(folder / "scan.nii.gz")]
    else:
        np.save(folder / "labels.npy", labels)
        source = ["--labels", str(folder / "labels.npy")]
    (folder / "config.yaml").write_text(SCAN_CONFIG if scan else CONFIG)
    out = folder / "run"
    common = ["--config", str(folder / "config.yaml")] + [a for s in sets for a in ("--set", s)] + ["-q"]
    if main(["run", *source, "-o", str(out), *common]) != 0:
        raise DicerError(f"{folder}: dicer run failed")
    decks = {}
    for order in orders:
        deck = out / ("model.inp" if order == 1 else f"model_order{order}.inp")
        # the export reads its own section only (the others would be warned of as unread)
        export_sets = [a for s in sets if s.startswith(("export.", "materials")) for a in ("--set", s)]
        if order != 1 and main(["export", str(out / "smoothed.vtu"), "-o", str(deck), "--order", str(order),
                                "--config", str(folder / "config.yaml"), *export_sets, "-q"]) != 0:
            raise DicerError(f"{folder}: dicer export --order {order} failed")
        decks[order] = deck
    return {"decks": decks, "quality": json.loads((out / "quality.json").read_text(encoding="utf-8")),
            "smooth": json.loads((out / "smooth.json").read_text(encoding="utf-8"))}


@dataclass
class Deck:
    """A deck dicer wrote.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        mm.
    cells : (M, k) int ndarray
        0-based.
    dim, order : int
    face_elements : (F,) int ndarray
        Element index of each free face (EXTERIOR and CAVITIES).
    face_numbers : (F,) int ndarray
        Its face number 1.. (Abaqus S1..S6 / S1..S4).
    """

    points: np.ndarray
    cells: np.ndarray
    dim: int
    order: int
    face_elements: np.ndarray
    face_numbers: np.ndarray

    @classmethod
    def read(cls, path: str | os.PathLike) -> "Deck":
        """Read a deck with :func:`dicer.export.abaqus.read_abaqus`."""
        from dicer.export.model import ELEMENT_TYPES
        from dicer.export.abaqus import read_abaqus

        d = read_abaqus(path)
        dim, order = ELEMENT_TYPES[d["element_type"]]
        sets = d["element_sets"]
        names = [f"{s}_S{k}" for s in ("EXTERIOR", "CAVITIES") for k in range(1, 7) if f"{s}_S{k}" in sets]
        elements = np.concatenate([sets[n] for n in names]).astype(np.int64)
        numbers = np.concatenate([np.full(sets[n].size, int(n[-1])) for n in names])
        return cls(d["points"], np.asarray(d["cells"], np.int64), dim, order, elements, numbers)

    def face_nodes(self, corners_only: bool = False) -> np.ndarray:
        """(F, k) node indices of the exterior faces (corners first, then mid-edge nodes)."""
        if self.dim == 3:
            table = HEX20_FACES if self.order == 2 and not corners_only else HEX_FACES
        else:
            table = QUAD8_SIDES if self.order == 2 and not corners_only else QUAD_EDGES
        return self.cells[self.face_elements[:, None], table[self.face_numbers - 1]]

    def _in_plane(self, axis: int, value: float) -> np.ndarray:
        extent = float(np.ptp(self.points[:, : self.dim], axis=0).max())
        coord = self.points[self.face_nodes(corners_only=True), axis]
        return np.all(np.abs(coord - value) <= 1e-9 * extent, axis=1)

    def plane_faces(self, axis: int, side: int) -> np.ndarray:
        """Boolean (F,): exterior faces lying in the model's low (side 0) or high (1) bounding
        plane normal to ``axis``."""
        col = self.points[:, axis]
        return self._in_plane(axis, float(col.max() if side else col.min()))

    def free_faces(self) -> np.ndarray:
        """Boolean (F,): exterior faces in none of the bounding planes."""
        on = np.zeros(self.face_elements.size, bool)
        for axis in range(self.dim):
            for side in (0, 1):
                on |= self.plane_faces(axis, side)
        return ~on


def dload(elements: np.ndarray, numbers: np.ndarray, pressure: float) -> str:
    """``*DLOAD`` lines: a uniform pressure on element faces.

    Parameters
    ----------
    elements : (F,) int ndarray
        0-based element indices.
    numbers : (F,) int ndarray
        Face numbers 1...
    pressure : float
        MPa; negative pulls.

    Returns
    -------
    str
    """
    rows = np.char.add(np.char.add((elements + 1).astype(str), ", P"), numbers.astype(str))
    return "*DLOAD\n" + "\n".join(np.char.add(rows, f", {float(pressure)!r}").tolist()) + "\n"


def write_moved(deck_path: str | os.PathLike, points: np.ndarray, out_path: str | os.PathLike) -> Path:
    """A copy of a deck dicer wrote with its nodes at other positions (the rest as written).

    Parameters
    ----------
    deck_path : str or os.PathLike
        The deck; its ``*NODE`` block holds nodes 1..N in order, as dicer writes it.
    points : (N, 3) float ndarray
        The new positions, mm.
    out_path : str or os.PathLike

    Returns
    -------
    Path
        ``out_path``.
    """
    import io

    text = Path(deck_path).read_text(encoding="utf-8")
    start = text.index("*NODE\n") + len("*NODE\n")
    end = text.index("\n*", start) + 1
    rows = io.StringIO()
    np.savetxt(rows, np.column_stack([np.arange(1, len(points) + 1), points]), fmt="%7d, %.12e, %.12e, %.12e")
    Path(out_path).write_text(text[:start] + rows.getvalue() + text[end:])
    return Path(out_path)
