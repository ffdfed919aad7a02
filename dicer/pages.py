"""Memory pages of numpy's large arrays.

numpy asks the kernel for transparent huge pages for every array of 4 MiB or more. On
virtual machines that hand freed memory back to the host (free page reporting), every
fresh huge page is first faulted in by the host: writing a new 0.75 GB voxel mesh took
about three times as long as with ordinary pages, and `dicer smooth` at 256³ spent 5 s
of its 11 s in the kernel (2.2 s of 9 s with ordinary pages). The stage commands
therefore run with ordinary pages unless the environment sets ``NUMPY_MADVISE_HUGEPAGE``
(numpy's own switch: ``1`` asks for huge pages again). ``dicer run`` keeps numpy's huge
pages: its stages take again much of the memory the ones before freed, and its exports and
quality report measured 2-5 s slower with ordinary pages; its merge, which makes and drops
many fresh tables, runs with ordinary pages there too (1-2 s quicker).

Large jobs are the other way round: at 512³ (51 M elements, 9-15 GB) the stages ran
markedly quicker with huge pages (``dicer merge`` 57 -> 41 s, ``smooth`` 74 -> 46 s,
``mesh`` 26 -> 19 s; a fault per 2 MiB instead of per 4 KiB, and fewer TLB misses in
their gathers), where at 256³ the two were level within the noise. Stages whose input
holds :data:`LARGE_JOB` elements or voxels or more keep numpy's huge pages
(:func:`large_job`).

Fresh pages cost most where memory is given back and taken again: glibc's malloc returns
every freed block of 32 MB or more to the kernel, and the next array of that size is
faulted in and zeroed page by page again. A stage makes and drops such arrays hundreds
of times: ``dicer run``, ``merge``, ``smooth``, ``export`` and ``quality`` keep freed memory in the
process for the next arrays (:func:`reuse_freed_memory`), unless the environment tunes
glibc's malloc itself.
Measured at 256³: ``dicer run`` 37-38 s with 16-17 s in the kernel -> 31-34 s with 8 s,
``dicer merge`` 10-11 s -> 7-9 s, peaks 2.5 and 2.0 -> 2.6 and 2.4 GB.
"""

from __future__ import annotations

import ctypes
import mmap
import os
import platform
from collections.abc import Iterator
from contextlib import contextmanager


LARGE_JOB = 20_000_000
"""Elements of a mesh (or voxels of a label volume) from which a stage keeps numpy's huge
pages: between the 6.4 M of 256³, where they made no clear difference, and the 51 M of
512³, where they saved 25-40 %."""

_VTU_BYTES_PER_ELEMENT = 76
"""Bytes of a stage file per element (a voxel mesh at 256³: 490 MB for 6.4 M elements)."""


def large_job(paths) -> bool:
    """Whether the inputs of a stage make a job of :data:`LARGE_JOB` elements or more.

    Parameters
    ----------
    paths : iterable of str or os.PathLike
        The stage's inputs: a mesh file counts its bytes / 76 (a VTU stage file's bytes per
        element), an image or label volume its voxels (from its header); anything else
        (a config, a folder) counts nothing.

    Returns
    -------
    bool
    """
    from pathlib import Path

    for path in map(Path, paths):
        try:
            if path.suffix in (".vtu", ".xdmf", ".h5", ".vtk"):
                size = path.stat().st_size // _VTU_BYTES_PER_ELEMENT
            elif path.is_file() and path.suffix in (".npy", ".nii", ".gz", ".nrrd", ".nhdr", ".mha", ".mhd"):
                from dicer.resources import scan_voxels

                size = scan_voxels(path)
            else:
                continue
        except (OSError, ValueError, EOFError):
            continue  # the stage itself says what is wrong with it
        if size >= LARGE_JOB:
            return True
    return False


def _switch():
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:  # numpy < 2
        try:
            from numpy.core.multiarray import _set_madvise_hugepage
        except ImportError:
            return None
    return _set_madvise_hugepage


@contextmanager
def ordinary_pages(unless_set: bool = False) -> Iterator[None]:
    """Allocate the arrays made inside the block in ordinary (4 KiB) pages.

    Parameters
    ----------
    unless_set : bool, optional
        Leave numpy's choice alone when ``NUMPY_MADVISE_HUGEPAGE`` is set (a user's own).
    """
    switch = _switch()
    if switch is None or (unless_set and "NUMPY_MADVISE_HUGEPAGE" in os.environ):
        yield
        return
    previous = switch(False)
    try:
        yield
    finally:
        switch(previous)


# mallopt's parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8


def reuse_freed_memory() -> bool:
    """Keep the memory of freed arrays in the process for the next ones (glibc's malloc).

    Large blocks come from the heap instead of a mapping of their own each, freed memory
    stays there (up to 2 GiB free at the heap's top), and all threads share one heap, so
    a thread's array can reuse what another freed. Call it first thing in a process,
    before any thread allocates: the heap limit applies to heaps made later. A no-op (False)
    where the C library is not glibc, or where the environment already sets ``MALLOC_*``
    or ``GLIBC_TUNABLES`` (a user's own tuning).

    Returns
    -------
    bool
        Whether the settings were applied.
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    if "GLIBC_TUNABLES" in os.environ or any(k.startswith("MALLOC_") for k in os.environ):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_ARENA_MAX, 1) & mallopt(_M_MMAP_MAX, 0) & mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))


def map_readonly(fileno: int) -> mmap.mmap:
    """A whole open file mapped read-only, its pages mapped at once where the system can
    (Linux ``MAP_POPULATE``): one call instead of a page fault per 64 KiB when a reader then
    goes through all of it (490 MB: 0.08-0.11 s -> 0.02 s).

    Parameters
    ----------
    fileno : int
        A file descriptor open for reading, of a file that is not empty.

    Returns
    -------
    mmap.mmap
    """
    populate = getattr(mmap, "MAP_POPULATE", 0)
    if populate:
        return mmap.mmap(fileno, 0, flags=mmap.MAP_SHARED | populate, prot=mmap.PROT_READ)
    return mmap.mmap(fileno, 0, access=mmap.ACCESS_READ)
