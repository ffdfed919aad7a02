"""Atomic writes: write to a temporary file beside the target, flush it to disk, then
rename it over the target.

Temporary files are named ``.NAME.PID.XXXXXX.tmpSUFFIX``: a run that was killed (kill -9,
out of memory) leaves one behind, and the next write of the same target removes those of
processes that no longer run.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from pathlib import Path

from dicer.errors import DicerError


def _suffixes(path: Path) -> str:
    # keep the full extension (".nii.gz", ".vtu") so format-sniffing writers still work
    return "".join(path.suffixes[-2:]) if path.name.endswith(".gz") else path.suffix


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Delete the temporary files of ``path`` left by processes that no longer run; return them."""
    parent = path.parent if str(path.parent) else Path(".")
    removed = []
    for tmp in parent.glob(f".{path.name}.*.*.tmp*"):
        pid = tmp.name[len(path.name) + 2:].split(".", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            with contextlib.suppress(OSError):
                tmp.unlink()
                removed.append(tmp)
    return removed


def _fsync(path: Path) -> None:
    # the data must be on disk before the rename makes it the result (a full disk can show
    # only here, when the written pages are flushed)
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _os_error(path: Path, exc: OSError) -> DicerError:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return DicerError(f"{path}: the disk is full ({exc.strerror}); free space or write elsewhere, "
                          "nothing was written")
    return DicerError(f"{path}: cannot write the file ({exc.strerror or exc}); check the output folder "
                      "and the disk, nothing was written")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; on success flush it to disk and rename it to
    ``path``, else delete it.

    Missing parent folders are created; a folder that cannot be written, a full disk and any
    other OS error while writing raise DicerError (the target is left as it was).
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=f".tmp{_suffixes(path)}",
                                   dir=parent)
        os.close(fd)
    except OSError as exc:
        raise DicerError(f"{path}: cannot write to folder {parent} ({exc.strerror}); choose a writable output path") from None
    tmp = Path(tmp)
    try:
        try:
            yield tmp
            os.chmod(tmp, 0o644)
            _fsync(tmp)
        except OSError as exc:
            raise _os_error(path, exc) from None
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
