"""Solver and viewer exports: the format follows the output file's extension.

``export_mesh(mesh, path, materials=..., order=..., ...)`` (the settings of
``dicer.config.stage_kwargs(config, "export")``) prepares one :class:`SolverModel`
(:mod:`dicer.export.model`), hands it to the writer of the format the suffix names
(:mod:`dicer.export.registry`), reads the file back and checks it, and only then
renames it into place. A failed check raises DicerError and leaves no file behind.

Formats: Abaqus/CalculiX ``.inp``, VTU ``.vtu`` (ParaView), PATRAN neutral
``.out``/``.neu``, LS-DYNA keyword ``.k``/``.key``/``.dyn``, Gmsh ``.msh``, Exodus II
``.e``/``.exo`` (written with netCDF4), FEBio ``.feb``.
"""

from __future__ import annotations

import importlib
import logging
import os
from pathlib import Path

import numpy as np

from dicer.config import takes_settings
from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.model import (DEFAULT_TYPES, ELEMENT_TYPES, SolverModel, prepare_model, resolve_element_type,
                                scanner_mesh)
from dicer.export.provenance import file_sha256, provenance, settings_hash
from dicer.export.registry import EXPORT_SUFFIXES, FORMATS, format_of
from dicer.export.textfmt import printed_values
from dicer.io.atomic import atomic_path, flush_meanwhile, write_error
from dicer.mesh.faces import face_neighbours, neighbour_materials
from dicer.mesh.model import Mesh

_neighbours_by_sort = face_neighbours  # the former private name
log = logging.getLogger("dicer")

__all__ = ["DEFAULT_TYPES", "ELEMENT_TYPES", "EXPORT_SUFFIXES", "FORMATS", "Format", "SolverModel", "export_mesh",
           "file_sha256", "format_of", "neighbour_materials", "prepare_model", "provenance", "resolve_element_type",
           "scanner_mesh", "settings_hash"]


def _format_for(mesh: Mesh, path: Path) -> Format:
    """The format ``path``'s suffix names, checked against the mesh and the modules it needs."""
    fmt = format_of(path)
    if fmt is None:
        raise DicerError(f"{path}: unknown export format {path.suffix or '(none)'}; "
                         f"name the output with one of {', '.join(EXPORT_SUFFIXES)}")
    if fmt.requires:
        module, hint = fmt.requires
        try:
            importlib.import_module(module)
        except ImportError:
            raise DicerError(f"{path}: {hint}") from None
    if mesh.dim not in fmt.dims:
        raise DicerError(f"{path}: {fmt.limits.format(dim=mesh.dim)}")
    return fmt


def _write_and_check(fmt: Format, model: SolverModel, tmp: Path, path: Path, ex: dict, check: bool) -> None:
    """Write ``model`` at ``tmp`` and, with ``check``, read it back; errors name ``path``."""
    try:
        fmt.write(model, tmp, **fmt.options("write", ex))
    except ValueError as exc:  # a number no field of the format can hold
        raise DicerError(f"{path}: cannot write the {fmt.name} file ({exc})") from None
    except OSError as exc:
        raise DicerError(f"{path}: cannot write ({exc.strerror}); choose a writable output path") from None
    if not check:
        return
    flushed = flush_meanwhile(tmp)  # the disk writes while the check reads
    try:
        fmt.check(tmp, model, **fmt.options("check", ex))
    except DicerError as exc:
        raise DicerError(f"{path}: read-back check failed: {exc}; the file was not written: check the disk "
                         "and export again") from None
    finally:
        try:
            flushed()
        except OSError as exc:
            raise write_error(path, exc) from None


PRINTED_SHIFT_WARNING, PRINTED_SHIFT_ERROR = 0.01, 0.25
"""Node shifts by the rounding of printed coordinates, as fractions of the smallest voxel
edge, from which the export warns and from which it refuses (elements may turn inside out)."""


def _check_printed_digits(fmt: Format, model: SolverModel, mesh: Mesh, digits: int, path: Path) -> None:
    """Warn, or refuse, where printing the coordinates with the format's significant digits
    moves nodes by a fair part of a voxel (a model far from the origin next to its voxel size:
    micro-CT voxels with the scanner's origin metres away) or turns an element inside out;
    and say when the format prints other digits than ``export.digits`` asks."""
    if not fmt.digits or not model.n_points:
        return
    printed = digits if digits in fmt.digits else fmt.digits[0]
    if printed != digits:
        log.warning("export: %s prints coordinates with %d significant digits (its fixed columns); export.digits %d "
                    "applies to .inp and .feb", path, printed, digits)
    reach = max(float(model.points.max()), -float(model.points.min()))
    bound = reach * 10.0 ** (1 - printed) / 2  # half a unit in the last digit of the largest coordinate
    spacing = np.asarray(mesh.spacing, float)[:mesh.dim]
    voxel = float(np.min(spacing))
    if bound <= PRINTED_SHIFT_WARNING * voxel:
        return
    try:
        as_printed = printed_values(model.points, printed)
    except ValueError:
        return  # no field holds them: the writer says so
    # each node's move along the voxel axes, in voxels of that axis (a voxel 1000 times
    # longer along z takes 1000 times the move along z)
    moved = as_printed - model.points
    if mesh.direction is not None:
        moved = moved @ np.asarray(mesh.direction, float)
    share = float((np.abs(moved[:, :mesh.dim]) / spacing).max())
    inverted = _inverted_as_printed(model, as_printed)
    if share <= PRINTED_SHIFT_WARNING and not inverted:
        return
    fix = ("set export.digits: 13" if max(fmt.digits) > printed else
           "export to .inp or .feb with export.digits: 13, or to .exo or .vtu (exact)")
    # an origin at the model's centre helps only where the model is small beside its distance
    span = float((model.points.max(axis=0) - model.points.min(axis=0)).max())
    if span / 2 * 10.0 ** (1 - printed) / 2 <= PRINTED_SHIFT_WARNING * voxel:
        fix += ", or place the image's origin near the model"
    text = (f"{path}: the coordinates, printed with {printed} significant digits, move nodes by up to "
            f"{float(np.abs(moved).max()):.3g} mm along a voxel axis, {100 * share:.3g} % of that axis's voxel edge: "
            f"the model lies up to {reach:.6g} mm from the origin and spans {span:.6g} mm; {fix}")
    if inverted:
        raise DicerError(text + f" ({inverted} element(s) turn inside out as printed)")
    if share > PRINTED_SHIFT_ERROR:
        raise DicerError(text + " (elements could turn inside out)")
    log.warning("export: %s", text)


def _inverted_as_printed(model: SolverModel, as_printed: np.ndarray) -> int:
    """Elements of ``model`` inside out at the coordinates ``as_printed`` and not at its own:
    a corner's scaled Jacobian (order 1), the determinant at the quadratic check points
    (order 2)."""
    if model.order == 2:
        from dicer.mesh.quadratic import folded_elements

        before = folded_elements(model.points, model.cells, model.dim)
        return int(np.count_nonzero(folded_elements(as_printed, model.cells, model.dim) & ~before))
    from dicer.mesh.metrics import scaled_jacobian

    before = scaled_jacobian(model.points, model.cells) <= 0
    return int(np.count_nonzero((scaled_jacobian(as_printed, model.cells) <= 0) & ~before))


@takes_settings("export")
def export_mesh(mesh: Mesh, path: str | os.PathLike, *, materials: list[dict], order: int, element_type: str | None,
                midside_nodes: str, thickness: float, digits: int, sets: list[str], heading: bool,
                febio_material: str, verify: str, source: str | os.PathLike | None = None,
                check: bool = True, neighbours=None, quadratic=None) -> dict:
    """Write a mesh in the format its file extension names.

    The settings are keyword-only with no defaults here: the command line passes
    ``dicer.config.stage_kwargs(config, "export")``. A library call may instead give a
    configuration as the third argument (and ``source`` fourth), or leave settings out;
    the schema's defaults fill them (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    mesh : Mesh
        The mesh to export.
    path : str or os.PathLike
        The output file; its suffix names the format (:data:`EXPORT_SUFFIXES`).
    materials : list of dict
        The ``materials`` section.
    order, element_type, midside_nodes, thickness, digits, sets, heading, febio_material, verify
        The ``export:`` section (see the schema); ``verify`` names the reader of the
        read-back check of an Abaqus deck (strict or meshio).
    source : str or os.PathLike, optional
        The input the model was made from (its SHA-256 goes into the provenance).
    check : bool, optional
        Read the file back and check it before renaming it into place (default).
    neighbours : callable, optional
        Returns the element across each face of ``mesh`` (see :func:`prepare_model`).
    quadratic : callable, optional
        Returns the quadratic mesh for an ``export.midside_nodes`` (see :func:`prepare_model`).

    Returns
    -------
    dict
        Summary: format, file, nodes, elements, element type, order, bytes, elements per
        material, nodes per node set, exterior and cavity faces (formats that hold sets), verified.

    Raises
    ------
    DicerError
        On any problem; no file is left at ``path``.
    """
    ex = {"order": order, "element_type": element_type, "midside_nodes": midside_nodes, "thickness": thickness,
          "digits": digits, "sets": sets, "heading": heading, "febio_material": febio_material, "verify": verify}
    path = Path(path)
    fmt = _format_for(mesh, path)
    model = prepare_model(mesh, {"materials": materials, "export": ex}, source, path, build_sets=fmt.holds_sets,
                          neighbours=neighbours, quadratic=quadratic)
    if model.order not in fmt.orders:
        raise DicerError(f"{path}: {fmt.limits.format(dim=model.dim, order=model.order)}")
    _check_printed_digits(fmt, model, mesh, digits, path)
    if fmt.warn is not None:
        fmt.warn(model, path)
    with atomic_path(path) as tmp:
        _write_and_check(fmt, model, tmp, path, ex, check)
        size = tmp.stat().st_size
    return {
        "format": fmt.name, "file": path.name, "nodes": model.n_points, "elements": model.n_cells,
        "element_type": model.element_type, "order": model.order, "bytes": size,
        "materials": {model.names[k]: int(np.count_nonzero(model.material == k)) for k in model.labels()},
        # a format with no sets (VTU) reports none rather than empty ones
        **({"node_sets": {name: int(ids.size) for name, ids in model.node_sets.items()},
            "exterior_faces": 0 if model.exterior is None else int(model.exterior.shape[0]),
            "cavity_faces": 0 if model.cavities is None else int(model.cavities.shape[0])} if fmt.holds_sets else {}),
        "verified": bool(check),
    }
