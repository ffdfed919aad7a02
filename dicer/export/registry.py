"""The table of export formats: one :class:`~dicer.export.format.Format` per format module.

To add a format, write ``dicer/export/<name>.py`` with ``write_<name>(model, path)``, a
strict ``check_<name>(path, model)`` and a module-level ``FORMAT = Format(...)``, then
add the module to :data:`FORMATS` below. ``dicer export`` picks it by suffix from then on.
"""

from __future__ import annotations

from pathlib import Path

from dicer.export import abaqus, exodus, febio, gmsh, lsdyna, patran, vtu
from dicer.export.format import Format

FORMATS: tuple[Format, ...] = (abaqus.FORMAT, vtu.FORMAT, patran.FORMAT, lsdyna.FORMAT, gmsh.FORMAT,
                               exodus.FORMAT, febio.FORMAT)
"""Every export format, in the order the suffixes are listed to users."""

BY_SUFFIX: dict[str, Format] = {s: f for f in FORMATS for s in f.suffixes}
"""Lower-case suffix -> format."""

EXPORT_SUFFIXES = tuple(BY_SUFFIX)
"""Output file extensions ``dicer export`` accepts."""


def format_of(path: str | Path) -> Format | None:
    """The format a file's suffix names (case-insensitive).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Format or None
    """
    return BY_SUFFIX.get(Path(path).suffix.lower())
