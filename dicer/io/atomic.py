"""Atomic writes: write to a temporary file beside the target, then rename over it."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from dicer.errors import DicerError


def _suffixes(path: Path) -> str:
    # keep the full extension (".nii.gz", ".vtu") so format-sniffing writers still work
    return "".join(path.suffixes[-2:]) if path.name.endswith(".gz") else path.suffix


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; on success rename it to ``path``, else delete it.

    Missing parent folders are created; a folder that cannot be written raises DicerError.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{_suffixes(path)}", dir=parent)
        os.close(fd)
    except OSError as exc:
        raise DicerError(f"{path}: cannot write to folder {parent} ({exc.strerror}); choose a writable output path") from None
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        try:
            os.replace(tmp, path)
        except OSError as exc:  # e.g. a folder of that name: say so instead of a traceback
            raise DicerError(f"{path}: cannot write the file there ({exc.strerror}); give the path of a file "
                             "that can be replaced") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (text is UTF-8 encoded) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
