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
import sys
import tempfile
import threading
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


def flush_meanwhile(tmp: str | os.PathLike):
    """Start flushing a written file to disk on a thread, so that its read-back check runs
    while the disk writes; :func:`atomic_path` flushes it again before the rename (by then
    a call with nothing left to write).

    Parameters
    ----------
    tmp : str or os.PathLike
        The temporary file :func:`atomic_path` yielded, closed.

    Returns
    -------
    callable
        Waits for the flush; raises its OSError (a full disk can show only then).
    """
    from dicer.parallel import meanwhile

    return meanwhile(_fsync, Path(tmp))


def write_error(path: Path, exc: OSError) -> DicerError:
    """The one-line error of an OSError while writing ``path`` (a full disk said as such)."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return DicerError(f"{path}: the disk is full ({exc.strerror}); free space or write elsewhere, "
                          "nothing was written")
    return DicerError(f"{path}: cannot write the file ({exc.strerror or exc}); check the output folder "
                      "and the disk, nothing was written")


#: the exception of a stop signal (SIGTERM) once its handler ran: CPython can lose the
#: exception a signal handler raises inside some C code (while it compiles a module being
#: imported, for one), so it is raised again before any file replaces its target
stop_requested: list[type[BaseException]] = []


def check_stop() -> None:
    """Raise the stop signal's exception if one arrived (see stop_requested)."""
    if stop_requested:
        raise stop_requested[0]()


#: per thread (dicer run makes its quality report beside the exports), the open
#: all_or_nothing() block: ``pending``, its writes as (temporary file, target), renamed at
#: its end (None: no block), and ``made``, the folders made for them, removed again when
#: the block fails
_block = threading.local()


def _pending() -> list[tuple[Path, Path]] | None:
    return getattr(_block, "pending", None)


def _missing_folders(parent: Path) -> list[Path]:
    """``parent`` and its ancestors that do not exist yet, innermost first."""
    out = []
    for folder in [parent, *parent.parents]:
        if folder.exists() or folder.is_symlink():
            break
        out.append(folder)
    return out


def _remove_folders(folders) -> None:
    for folder in folders:  # innermost first; only when empty
        with contextlib.suppress(OSError):
            folder.rmdir()


def pending(path: str | os.PathLike) -> Path:
    """Where the content written to ``path`` is now: its temporary file while an
    all_or_nothing() block holds it back, else ``path`` itself."""
    path = Path(path)
    for tmp, target in _pending() or ():
        if target == path:
            return tmp
    return path


@contextlib.contextmanager
def all_or_nothing():
    """Writes inside this block (through atomic_path) replace their targets only when the
    whole block succeeds: a command that writes several files (a labels volume and its
    info, a mesh and its report) leaves all of them as they were when any write or any
    later step fails. Each file is still written, read back and flushed to disk as it comes;
    only the renames wait for the end. Nested blocks join the outer one."""
    if _pending() is not None:
        yield
        return
    _block.pending, _block.made = [], []
    try:
        yield
        check_stop()
        items, _block.pending = _block.pending, None
        for tmp, path in items:
            try:
                os.replace(tmp, path)
            except OSError as exc:
                _block.pending = [(t, p) for t, p in items if t.exists()]
                raise DicerError(f"{path}: cannot write the file there ({exc.strerror}); give the path of a file "
                                 "that can be replaced") from None
    except BaseException:
        for tmp, _ in _pending() or ():
            with contextlib.suppress(OSError):
                tmp.unlink()
        _remove_folders(_block.made)
        raise
    finally:
        _block.pending, _block.made = None, []


def in_this_block(fn):
    """``fn`` to run in another thread as part of the caller's all_or_nothing() block: its
    writes are held back and renamed (or deleted) with the block's. The caller must wait for
    the thread before its block ends."""
    pending, made = _pending(), getattr(_block, "made", [])

    def run(*args, **kwargs):
        if pending is None:
            return fn(*args, **kwargs)
        _block.pending, _block.made = pending, made  # the caller's lists: appends are atomic
        try:
            return fn(*args, **kwargs)
        finally:
            _block.pending, _block.made = None, []
    return run


def _file_mode() -> int:
    """0o666 less the process's umask (read once: setting and restoring it is not thread-safe later)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


def _new_temporary(path: Path, parent: Path, names: list) -> Path:
    """Create an empty temporary file for ``path`` in ``parent``; its name goes into
    ``names`` before the file exists, so a SIGTERM arriving at any moment (its handler runs
    between any two steps) finds it to delete."""
    for _ in range(100):
        tmp = parent / f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}.tmp{_suffixes(path)}"
        names.append(tmp)
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            return tmp
        except FileExistsError:
            names.pop()
    raise FileExistsError(errno.EEXIST, "no free temporary file name", str(parent))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; on success flush it to disk and rename it to
    ``path`` (inside all_or_nothing(): at the end of that block), else delete it.

    Missing parent folders are created (and removed again when the write fails); a folder
    that cannot be written, a full disk and any other OS error while writing raise
    DicerError (the target is left as it was).
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    made: list[Path] = []
    names: list[Path] = []  # the temporary file, named before it is made
    try:
        try:
            made.extend(_missing_folders(parent))
            parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temporaries(path)
            tmp = _new_temporary(path, parent, names)
        except OSError as exc:
            raise DicerError(f"{path}: cannot write to folder {parent} ({exc.strerror}); choose a writable "
                             "output path") from None
        try:
            yield tmp
            os.chmod(tmp, _FILE_MODE)  # as a plain open() would make it: 0o666 less the umask
            _fsync(tmp)
        except OSError as exc:
            raise write_error(path, exc) from None
        if _pending() is not None:
            _block.pending.append((tmp, path))
            _block.made.extend(made)
            return
        check_stop()
        try:
            os.replace(tmp, path)
        except OSError as exc:  # e.g. a folder of that name: say so instead of a traceback
            raise DicerError(f"{path}: cannot write the file there ({exc.strerror}); give the path of a file "
                             "that can be replaced") from None
    except BaseException:
        for tmp in names:
            with contextlib.suppress(OSError):
                tmp.unlink()
        _remove_folders(made)
        raise


def disk_full(folder: str | os.PathLike) -> bool:
    """Whether the file system holding ``folder`` has no block left for an ordinary user."""
    try:
        return os.statvfs(folder).f_bavail == 0
    except OSError:
        return False


@contextlib.contextmanager
def captured_stderr():
    """Collect what C libraries (ITK, its NIfTI and MetaImage writers) print straight to the
    process's standard error while the block runs; yields a list that holds the text
    afterwards. dicer reports problems in its own one line."""
    out: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (embedded): nothing to capture
        yield out
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield out
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            out.append(sink.read().decode(errors="replace"))


def write_bytes_atomic(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (text is UTF-8 encoded) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
