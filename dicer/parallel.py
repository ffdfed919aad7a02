"""Chunked array work on the cores the process may use, results in order.

numpy runs its loops over large arrays without holding the interpreter lock, so the
chunks of a text deck (formatting rows, checking them when read back) run side by side
in threads; the caller consumes them in order, so files and errors are the same as one
thread gives.
"""

from __future__ import annotations

import itertools
import math
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

MAX_WORKERS = 2
"""Threads at most: the formats' chunk work scales to two, then the single writer limits."""


def cores() -> int:
    """Cores this process may use, at least 1: the fewest of its CPU affinity, a cgroup's CPU
    quota (a container) and the CPUs a SLURM job gave each task (``SLURM_CPUS_PER_TASK``),
    so a one-core job works in one thread even where its allocation is not pinned."""
    if hasattr(os, "sched_getaffinity"):
        limits = [len(os.sched_getaffinity(0))]
    else:
        limits = [os.cpu_count() or 1]
    try:  # cgroup v2: "<quota> <period>" in microseconds, or "max <period>"
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text(encoding="ascii").split()[:2]
        if quota != "max" and int(period) > 0:
            limits.append(math.ceil(int(quota) / int(period)))
    except (OSError, ValueError):
        pass
    per_task = os.environ.get("SLURM_CPUS_PER_TASK", "")
    if per_task.isdigit() and int(per_task) > 0:
        limits.append(int(per_task))
    return max(1, min(limits))


def one_blas_thread():
    """A context in which numpy's matrix products (BLAS) run in one thread.

    dicer's own threads work beside its matrix products (a stage's file checked and hashed
    while the next stage runs, the quality report beside the export, a deck's chunks), and
    so do other jobs on a shared node; OpenBLAS's threads wait for their cores by spinning,
    and the products are thin (20 shape functions), so its threads gained nothing and took
    the cores from the others (docs/benchmark.md). Also where ``OPENBLAS_NUM_THREADS`` or
    ``OMP_NUM_THREADS`` name more: Snakemake sets them to each job's threads."""
    import numpy  # noqa: F401 -- loads numpy's BLAS, which the limit reaches only once loaded
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def ordered_map(fn: Callable, items: Iterable, workers: int | None = None) -> Iterator:
    """``fn(item)`` for each item, yielded in the items' order.

    Parameters
    ----------
    fn : callable
        Must be safe to call from several threads at once (reads shared arrays, writes
        only its own).
    items : iterable
    workers : int, optional
        Threads; default ``min(MAX_WORKERS, cores())``. With one, ``fn`` runs in the
        caller's thread, item by item.

    Yields
    ------
    The results in order. An exception raised by ``fn`` is raised when its item's turn
    comes, so the first failing item in order is the one reported; at most ``2 * workers``
    items are in flight (memory stays a few chunks). After a stop signal
    (:func:`dicer.io.atomic.check_stop`) its exception is raised before the next item, also
    in a thread other than the main one (a table written beside a report).
    """
    from dicer.io.atomic import check_stop  # a stop signal ends the work between items, in any thread

    # one item (a small block of a deck: an atlas's thousands of sets) runs here, without
    # a pool's threads or the look at the cores
    items = iter(items)
    head = list(itertools.islice(items, 2))
    if len(head) < 2:
        for item in head:
            check_stop()
            yield fn(item)
        return
    items = itertools.chain(head, items)
    workers = min(MAX_WORKERS, cores()) if workers is None else workers
    if workers <= 1:
        for item in items:
            check_stop()
            yield fn(item)
        return
    with ThreadPoolExecutor(workers) as pool:
        flight: deque = deque()
        try:
            for item in items:
                check_stop()
                flight.append(pool.submit(fn, item))
                if len(flight) >= 2 * workers:
                    yield flight.popleft().result()
            while flight:
                check_stop()
                yield flight.popleft().result()
        finally:
            for future in flight:  # an error or an abandoned generator: drop the work not started
                future.cancel()


def meanwhile(fn: Callable, *args) -> Callable:
    """Start ``fn(*args)`` on a thread; return a function that waits for its result.

    For work that leaves the interpreter lock (numpy, hashlib, file reads) and whose result
    is needed later: the caller goes on with other work meanwhile.

    Parameters
    ----------
    fn : callable
    *args
        Passed to ``fn``.

    Returns
    -------
    callable
        ``result()`` waits for ``fn`` and returns what it returned, or raises what it
        raised, on the caller's thread; later calls return the same.
    """
    import threading

    out: list = []

    def run() -> None:
        try:
            out.append((True, fn(*args)))
        except BaseException as exc:  # noqa: BLE001 -- handed back to the caller, which raises it
            out.append((False, exc))

    worker = threading.Thread(target=run, daemon=True)
    worker.start()

    def result():
        worker.join()
        ok, value = out[0]
        if not ok:
            raise value
        return value
    return result


def import_meanwhile(*names: str) -> None:
    """Import the modules ``names`` on a thread, for a stage that needs them only later.

    Loading scipy's compiled modules reads and maps files for a few tenths of a second;
    the caller's array work goes on meanwhile. A later ``import`` of the same module
    waits for this one (Python's import lock) and an import error is raised there, by
    that import, as without this call.
    """
    import sys

    missing = [name for name in names if name not in sys.modules]
    if missing:
        meanwhile(_import_quietly, missing)


def _import_quietly(names: list[str]) -> None:
    import importlib

    for name in names:
        try:
            importlib.import_module(name)
        except ImportError:  # the caller's own import reports it
            pass


def contiguous(array, dtype=None):
    """A C-contiguous copy of ``array`` (any strides), e.g. of a volume's transpose.

    numpy copies a transposed volume element by element across its strides: 1.6 s for
    512³ uint8 (0.1 s at 256³), bound by cache and TLB misses. Copied in tiles of 16 x 64
    x 16 that stay in cache, on the process's cores, it takes 0.3 s.

    Parameters
    ----------
    array : ndarray
        Any shape; tiles are cut for 3D arrays of a million elements or more.
    dtype : numpy dtype, optional
        The copy's type (numpy's casting rules); default ``array``'s.

    Returns
    -------
    ndarray
        C-contiguous, ``array``'s shape; ``array`` itself when it is C-contiguous already and
        of the type asked for.
    """
    import numpy as np

    array = np.asarray(array)
    if array.ndim != 3 or array.size < 1 << 20 or array.flags.c_contiguous:
        return np.ascontiguousarray(array, dtype=dtype)
    out = np.empty(array.shape, dtype or array.dtype)
    nx, ny, nz = array.shape
    tiles = [(i, j) for i in range(0, nx, 16) for j in range(0, ny, 64)]

    def copy(tile) -> None:
        i, j = tile
        for k in range(0, nz, 16):
            out[i:i + 16, j:j + 64, k:k + 16] = array[i:i + 16, j:j + 64, k:k + 16]

    # a run of tiles per item: the pool's work per item outweighs its overhead
    runs = [tiles[s:s + 64] for s in range(0, len(tiles), 64)]
    for _ in ordered_map(lambda run: [copy(t) for t in run], runs):
        pass
    return out
