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
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager


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
