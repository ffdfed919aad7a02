"""The record by which an export format registers itself (see :mod:`dicer.export.registry`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable


@dataclass(frozen=True)
class Format:
    """One export format: its file suffixes, its writer and its strict read-back check.

    Parameters
    ----------
    name : str
        Short name, reported in the export summary (``abaqus``, ``vtu``, ...).
    suffixes : tuple of str
        Lower-case file extensions with their dot; the first is the usual one.
    write : callable
        ``write(model, path, **options)``: writes the SolverModel ``model`` at ``path``;
        raises ValueError for a number no field of the format holds.
    check : callable
        ``check(path, model, **options)``: reads the file back and raises DicerError on
        the first difference from ``model``.
    dims, orders : tuple of int
        Mesh dimensions (2, 3) and element orders (1, 2) the format holds.
    limits : str
        What the format cannot hold and what to do instead, for the error message;
        ``{dim}`` and ``{order}`` are filled in.
    write_options, check_options : dict
        Keyword of ``write`` / ``check`` -> the name of the ``export`` setting it takes
        (the schema gives its default).
    requires : tuple of str
        A module the writer needs and the hint given when it is missing, or empty.
    holds_sets : bool
        Whether the file holds node sets and surfaces (``export.sets``); a format that
        does not is spared building them.
    digits : tuple of int
        The significant digits a text format prints coordinates with: the values of
        ``export.digits`` it honours (the first when it honours none); empty where the
        coordinates are stored exactly (binary, or printed in full).
    warn : callable or None
        ``warn(model, path)``: logs what the format changes of the model as it prints it
        (LS-DYNA's rounded material constants), before the file is written.
    """

    name: str
    suffixes: tuple[str, ...]
    write: Callable
    check: Callable
    dims: tuple[int, ...] = (2, 3)
    orders: tuple[int, ...] = (1, 2)
    limits: str = ""
    write_options: dict[str, str] = field(default_factory=dict)
    check_options: dict[str, str] = field(default_factory=dict)
    requires: tuple[str, ...] = ()
    holds_sets: bool = True
    digits: tuple[int, ...] = ()
    warn: Callable | None = None

    def options(self, which: str, export: dict) -> dict:
        """Keyword arguments of ``write`` or ``check`` from the ``export`` settings.

        Parameters
        ----------
        which : {"write", "check"}
        export : dict
            The ``export`` settings, every key present (:func:`dicer.config.stage_kwargs`).

        Returns
        -------
        dict
        """
        table = self.write_options if which == "write" else self.check_options
        return {kw: export[key] for kw, key in table.items()}
