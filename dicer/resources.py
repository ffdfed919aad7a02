"""Cluster resources of the workflow's stages, estimated from the input's size.

Sizes are read from headers only (no voxel data): the scan's voxel count, and the mesh's
element count once a mesh exists. The formula and the peaks it was fitted to are in
docs/cluster.md; workflow/rules/resources.smk turns them into Snakemake resources.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np


def scan_header(path: str | os.PathLike) -> tuple[int, tuple[float, ...] | None]:
    """Voxel count and voxel size of an image or label volume, from its header.

    NIfTI, NRRD, MetaImage: SimpleITK's header read; ``.npy``: the array header; a folder
    of slices (DICOM, TIFF, PNG) or an unreadable file: its size in bytes / 2 (2 bytes a
    voxel).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    voxels : int
    spacing : tuple of float or None
        mm; None when the header does not say.
    """
    path = Path(path)
    if path.is_dir():
        return max(1, sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) // 2), None
    shape, spacing = scan_shape(path)
    if shape is None:  # not an image this reads (the stage will say why)
        return max(1, path.stat().st_size // 2), None
    return int(np.prod(shape)), spacing


def scan_shape(path: str | os.PathLike) -> tuple[tuple[int, ...] | None, tuple[float, ...] | None]:
    """Voxels per axis and voxel size of an image or label file, from its header.

    Parameters
    ----------
    path : str or os.PathLike
        A file: ``.npy`` (its array header) or what SimpleITK reads.

    Returns
    -------
    shape : tuple of int or None
        None for a folder or a file whose header cannot be read.
    spacing : tuple of float or None
        mm; None when the header does not say.
    """
    path = Path(path)
    if path.is_dir():
        return None, None
    if path.suffix == ".npy":
        try:
            return tuple(np.load(path, mmap_mode="r").shape), None
        except (OSError, ValueError, EOFError):  # EOFError: an empty file
            return None, None
    from dicer.io.images import image_header

    reader = image_header(path)
    if reader is None:
        return None, None
    return tuple(reader.GetSize()), tuple(reader.GetSpacing())


def scan_voxels(path: str | os.PathLike) -> int:
    """Voxel count of an image or label volume, from its header.

    Parameters
    ----------
    path : str or os.PathLike
        As in :func:`scan_header`.

    Returns
    -------
    int
    """
    return scan_header(path)[0]


_CELLS = re.compile(rb'NumberOfCells="(\d+)"')


def mesh_elements(path: str | os.PathLike) -> int:
    """Element count of a VTU mesh, from its <Piece> header (in the first 4 kB, or after the
    field data that names each material: up to 64 MB for 65,535 of them).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    int
    """
    with open(path, "rb") as handle:
        head = handle.read(4096)
        match = _CELLS.search(head)
        while match is None and len(head) < 1 << 26:
            more = handle.read(1 << 20)
            if not more:
                break
            head += more
            match = _CELLS.search(head, max(0, len(head) - len(more) - 64))  # the new part, and a tag cut
    if match is None:
        raise ValueError(f"{path}: no NumberOfCells in the VTU header")
    return int(match.group(1))


#: the size each stage's memory and time grow with: the scan's voxels, the voxels after
#: downsampling, or the mesh's elements
SIZE_OF = {
    "phantom": "voxels", "segment": "voxels", "labels": "voxels", "downsample": "voxels",
    "fix": "voxels_ds", "mesh": "voxels_ds", "merge": "elements", "smooth": "elements",
    "export_inp": "elements", "export_vtu": "elements", "quality": "elements",
    "export_inp_order2": "elements", "export_vtu_order2": "elements",
}

#: stage -> (baseline MB, MB per million of its size, baseline s, s per million), fitted by
#: workflow/scripts/fit_resources.py to docs/cluster-measurements.tsv: the baseline is the
#: smallest measured peak (the interpreter with numpy, scipy, SimpleITK and meshio loaded,
#: which dominates small scans), the slope the steepest growth seen over the cases
COEFFICIENTS = {
    "phantom": (135, 23.2, 0.4, 1.0),
    "segment": (198, 21.4, 1.8, 5.2),
    "labels": (138, 27.5, 0.5, 1.2),
    "downsample": (157, 16.4, 0.8, 1.5),
    "fix": (170, 18.9, 0.9, 5.3),
    "mesh": (164, 91.3, 0.7, 1.5),
    "merge": (99, 504.2, 0.9, 4.9),
    "smooth": (322, 789.7, 2.2, 60.9),
    "export_inp": (86, 525.8, 0.5, 1.6),
    "export_vtu": (63, 281.9, 0.3, 1.4),
    "quality": (242, 456.5, 1.6, 4.9),
    "export_inp_order2": (111, 1537.7, 1.6, 18.0),
    "export_vtu_order2": (88, 1145.9, 0.6, 8.9),
}
#: smooth with the scan (smooth.surface_from_image): the image reader's libraries at import
#: and the scan (float32, its smoothed crop) on top of the mesh, per million scan voxels;
#: added to the smooth request of a patient with a scan (``estimate(..., scan=True)``;
#: taken from the segment stage's fit, which reads the same scan)
SMOOTH_SCAN = (119, 21.3, 0.8, 5.8)
#: elements per coarse voxel assumed before the mesh exists (a patient's group job is sized
#: before any of its stages ran): measured 0.30 (head phantoms, head CT) to 0.52 (long
#: bone); a fuller scan runs out of memory on the first attempt and gets twice on the retry
ELEMENT_FRACTION = 0.5
#: dicer run's peak from its mesh stage on: (baseline MB, MB per million elements of the
#: voxel mesh, MB per million faces of its surfaces). One process holds the mesh from stage
#: to stage, so its peak is not the largest stage process's; smoothing's surface work (the
#: labels' fit, the fit to the scan, the boundary solves) grows with the faces, so thin bone
#: needs more per element than a solid ball. The smallest upper bound of `dicer run`'s
#: measured peaks on thirteen scans (docs/robustness.md, "Memory": the shell phantom 64^3 to
#: 512^3, the head, long-bone, sphere and block phantoms, the head CT at factors 1 and 2 and
#: its labels), rounded up: `python workflow/scripts/fit_resources.py docs/run-memory.tsv`
RUN_MESH = (300, 380, 2155)
#: with ``export.order`` 2, added to RUN_MESH: MB per million elements and per million surface
#: faces for the quadratic mesh the exports hold (its mid-edge nodes placed and, curved, checked
#: for folds), the smallest upper bound of the same scans run with curved C3D20 decks
#: (docs/run-memory.tsv's order 2 rows: 1.00-1.54 times their peaks, the head CT's 3.86 GB as
#: 3.86 GB). Until then the export_inp_order2 row's 1,538 MB per million elements stood here:
#: 1.20 times the head CT's peak, 2.15 times the long-bone phantom's.
RUN_MESH_ORDER2 = (550, 1440)
#: added to RUN_MESH where the smooth stage relaxes a label volume's staircase (``dicer run
#: --labels`` at the defaults, ``smooth.label_samples: relaxed``): MB per million surface faces,
#: the smallest that bounds docs/run-memory.tsv's label-volume rows (its scan rows fit RUN_MESH)
RUN_RELAXED = 110
#: surface faces per element assumed where a caller knows only the elements: the most of the
#: measured scans (the head CT at factor 2: 0.32)
FACE_FRACTION = 0.35
#: requested memory over the fitted peak: room for other library versions and inputs
MEMORY_MARGIN = 1.15
#: the baseline again over the fitted one: the same library versions installed afresh on
#: the same machine measured up to 19-22 % more at import (SimpleITK 142 against 119 MB,
#: numpy 31 against 26 MB), and a small scan's peak is mostly its baseline
BASELINE_FACTOR = 1.15
#: requested time over the fitted seconds (a shared, loaded node), plus a minute for
#: Snakemake's own start-up inside the job
TIME_MARGIN = 3.0
START_UP_MINUTES = 1


def _stage_key(stage: str, order: int = 1) -> str:
    """export_<ext>: text decks (inp, out, neu, k, msh, feb) and binary files (exo, e) as
    export_inp (the heavier), VTU as export_vtu; with ``order`` 2 their _order2 rows (the
    quadratic mesh's mid-edge nodes, placed and checked: two to three times the memory)."""
    if stage.startswith("export_") and stage not in COEFFICIENTS:
        stage = "export_inp"
    if stage not in COEFFICIENTS:
        raise ValueError(f"no resource formula for stage {stage!r}; stages: {', '.join(COEFFICIENTS)}")
    if order == 2 and stage.startswith("export_") and not stage.endswith("_order2"):
        stage = f"{stage}_order2"
    return stage


def estimate(stage: str, voxels: int, voxels_ds: int | None = None, elements: int | None = None,
             attempt: int = 1, scan: bool = False, order: int = 1) -> tuple[int, int]:
    """Memory and run time to request for one stage, ``attempt`` times the first.

    mem_mb = ceil(MEMORY_MARGIN * (BASELINE_FACTOR * base_mb + mb_per_million * size / 1e6)) * attempt
    runtime = ceil(START_UP_MINUTES + TIME_MARGIN * (base_s + s_per_million * size / 1e6) / 60) * attempt

    size is the stage's SIZE_OF: the scan's voxel count, the voxel count after downsampling
    or the mesh's element count.

    Parameters
    ----------
    stage : str
        A command name.
    voxels : int
        Voxels of the scan.
    voxels_ds : int, optional
        Voxels after downsampling (default: ``voxels``).
    elements : int, optional
        Elements of the mesh (default, before the mesh exists: ELEMENT_FRACTION *
        ``voxels_ds``).
    attempt : int, optional
        The attempt of the job, 1 first.
    scan : bool, optional
        The smooth stage reads the scan too (a segmented patient: SMOOTH_SCAN added).
    order : int, optional
        ``export.order``: 2 takes an export's _order2 row.

    Returns
    -------
    mem_mb : int
    runtime : int
        Minutes.
    """
    key = _stage_key(stage, order)
    voxels_ds = voxels if voxels_ds is None else voxels_ds
    elements = max(1, int(ELEMENT_FRACTION * voxels_ds)) if elements is None else elements
    size = {"voxels": voxels, "voxels_ds": voxels_ds, "elements": elements}[SIZE_OF[key]] / 1e6
    base_mb, mb_per_m, base_s, s_per_m = COEFFICIENTS[key]
    attempt = max(1, int(attempt))
    if key == "smooth" and scan:
        scan_mb, scan_mb_per_m, scan_s, scan_s_per_m = SMOOTH_SCAN
        base_mb, base_s = base_mb + scan_mb, base_s + scan_s
        extra_mb, extra_s = scan_mb_per_m * voxels / 1e6, scan_s_per_m * voxels / 1e6
    else:
        extra_mb = extra_s = 0.0
    mem = math.ceil(MEMORY_MARGIN * (BASELINE_FACTOR * base_mb + mb_per_m * size + extra_mb)) * attempt
    minutes = math.ceil(START_UP_MINUTES + TIME_MARGIN * (base_s + s_per_m * size + extra_s) / 60) * attempt
    return mem, minutes


def voxel_reduction(factor) -> int:
    """How many voxels become one at a downsampling factor.

    Parameters
    ----------
    factor : int or sequence of int
        One factor for all three axes, or one per axis.

    Returns
    -------
    int
    """
    factor = np.asarray(factor, dtype=np.int64)
    return max(1, int(factor ** 3 if factor.ndim == 0 else np.prod(factor)))


def surface_faces(labels: np.ndarray) -> int:
    """Voxel faces between two different labels, or a label and the background or the
    volume's edge: the faces of the voxel mesh's exterior and interfaces.

    Parameters
    ----------
    labels : (X, Y, Z) or (X, Y) integer ndarray
        0 background.

    Returns
    -------
    int
    """
    labels = np.asarray(labels)
    count = 0
    for axis in range(labels.ndim):
        v = np.moveaxis(labels, axis, 0)  # a view: faces between neighbours along v's first axis
        ends = v[[0, -1]] if len(v) else v
        count += int(np.count_nonzero(v[:-1] != v[1:])) + int(np.count_nonzero(ends))
    return count


def run_peak_mb(voxels: int, factor=1, elements: int | None = None, order: int = 1,
                faces: int | None = None, relaxed: bool = False) -> int:
    """Fitted peak memory of ``dicer run``.

    Without ``elements`` (before the scan is segmented): the stages that read the scan or
    its label volume (segment, downsample, fix), whose size the header gives. With the
    mesh's element count and its surface faces (known once the labels are fixed,
    :func:`surface_faces`): also the stages from the mesh on, by RUN_MESH (without
    ``faces``, FACE_FRACTION of the elements); with ``order`` 2 the exports then hold the
    quadratic mesh besides what the run holds, RUN_MESH_ORDER2 on top of RUN_MESH.

    Parameters
    ----------
    voxels : int
        Voxels of the scan.
    factor : int or sequence of int, optional
        Downsampling factor, one or one per axis.
    elements : int, optional
        Elements of the voxel mesh (the fixed labels' non-zero voxels).
    order : int, optional
        ``export.order``.
    faces : int, optional
        Surface faces of the voxel mesh.
    relaxed : bool, optional
        The smooth stage relaxes a label volume's staircase (RUN_RELAXED on top).

    Returns
    -------
    int
        MB.
    """
    voxels_ds = max(1, voxels // voxel_reduction(factor))
    peaks = [estimate(stage, voxels, voxels_ds)[0] / MEMORY_MARGIN for stage in ("segment", "downsample", "fix")]
    if elements is not None:
        base_mb, mb_per_m, mb_per_face_m = RUN_MESH
        if order == 2:
            mb_per_m, mb_per_face_m = mb_per_m + RUN_MESH_ORDER2[0], mb_per_face_m + RUN_MESH_ORDER2[1]
        faces = FACE_FRACTION * elements if faces is None else faces
        mb_per_face_m += RUN_RELAXED if relaxed else 0
        peaks.append(base_mb + mb_per_m * elements / 1e6 + mb_per_face_m * faces / 1e6)
    return int(max(peaks))


def machine_memory_mb() -> int | None:
    """Memory this process may use: the smaller of the machine's physical memory and a
    cgroup (container, cluster job) limit.

    Returns
    -------
    int or None
        MB; None where neither can be read.
    """
    limits = []
    try:
        limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2**20)
    except (ValueError, OSError, AttributeError):
        pass
    for name in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(name).read_text(encoding="utf-8").strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2**60:
            limits.append(int(text) // 2**20)
    return min(limits) if limits else None
