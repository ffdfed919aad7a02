"""Provenance of exported files: the SHA-256 of the source mesh and the hash of the settings.

A deck's heading names its content only (no path, no date), so reruns are byte-identical
and no identifier held in a file or folder name reaches a deck.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from dicer import __version__
from dicer.config import config_hash, stage_kwargs
from dicer.parallel import meanwhile


def file_sha256(path: str | os.PathLike | None) -> str | None:
    """SHA-256 of a file, or of a folder's files in sorted order (DICOM series).

    Parameters
    ----------
    path : str or os.PathLike or None

    Returns
    -------
    str or None
        Hex digest; None if absent.
    """
    if path is None:
        return None
    p = Path(path)
    if p.is_file():
        # a file hashed before in this process and unchanged since (dicer run exports one
        # mesh twice): the same digest, not a second pass over GBs
        st = p.stat()
        key = (str(p.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        if key not in _DIGESTS:
            _DIGESTS[key] = _sha256_of(p, [p])
        return _DIGESTS[key]
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
    else:
        return None
    return _sha256_of(p, files)


_DIGESTS: dict[tuple, str] = {}
"""Digests of files by (path, device, inode, size, modification and change times)."""


def _sha256_of(p: Path, files: list[Path]) -> str:
    """SHA-256 of ``files`` in turn (of a folder ``p``: each preceded by its relative name)."""
    h = hashlib.sha256()
    block = bytearray(1 << 24)  # one buffer, refilled: no fresh memory per block
    view = memoryview(block)
    for f in files:
        if p.is_dir():
            h.update(str(f.relative_to(p)).encode() + b"\0")
        with open(f, "rb", buffering=0) as fh:
            while n := fh.readinto(block):
                h.update(view[:n])
    return h.hexdigest()


def sha256_in_background(path: str | os.PathLike | None):
    """Start :func:`file_sha256` of a file on a thread.

    hashlib and file reads release the GIL, so the digest of a mesh of GBs is computed
    on the second core while the model is built.

    Parameters
    ----------
    path : str or os.PathLike or None

    Returns
    -------
    callable
        Waits for the digest and returns it.
    """
    return meanwhile(file_sha256, path)


def provenance(source: str | os.PathLike | None, config: dict, element_type: str, order: int,
               digest: str | None = None) -> list[str]:
    """Heading lines: dicer version, the checksum of the mesh the deck is made from, the
    hash of the settings export reads; no name, path or date.

    The same for ``dicer run``, ``dicer export`` and the workflow: each exports the same
    smoothed mesh file with the same ``materials`` and ``export`` sections (what happened
    upstream is in that mesh), so the heading is the same byte for byte.

    Parameters
    ----------
    source : str or os.PathLike or None
        The mesh file.
    config : dict
        A configuration, or its ``materials`` and ``export`` sections (:func:`settings_hash`).
    element_type : str
    order : int
    digest : str, optional
        The SHA-256 of ``source`` when already known.

    Returns
    -------
    list of str
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
    """Hash of the ``materials`` and ``export`` settings that shape the file.

    All but ``export.verify``: how a file is checked does not change it. The sections are
    those the export stage reads, completed from the schema's defaults
    (:func:`dicer.config.stage_kwargs`), so ``dicer run``, ``dicer export``, the workflow's
    rule and a library call give one hash for the same settings.

    Parameters
    ----------
    config : dict
        A configuration, or its ``materials`` and ``export`` sections (in part or whole).

    Returns
    -------
    str
        As :func:`dicer.config.config_hash`.
    """
    export = stage_kwargs(config, "export")
    materials = export.pop("materials")
    export.pop("verify")
    return config_hash({"materials": materials, "export": export})
