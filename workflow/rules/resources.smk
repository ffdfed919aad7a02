# Cluster resources per rule: memory (mem_mb) and time limit (runtime, minutes) from the size
# of the patient's input, by the formula in dicer/resources.py (docs/cluster.md gives the
# measured peaks it was fitted to). Each stage asks for threads 1: dicer then works in one
# thread (SLURM_CPUS_PER_TASK=1), in two only where its process may use a second core. A job that fails (out of memory, out of time) and is retried (--retries, on in
# the SLURM profile) asks for `attempt` times as much.

from functools import lru_cache

from dicer.phantoms import DEFAULT_SIZE
from dicer.resources import estimate, mesh_elements, scan_header


def _scan_size(patient):
    """(voxels, voxels after downsampling) of a patient's scan or label volume, from headers.
    A demo phantom not made yet counts as a cube of its size (an upper bound)."""
    row = PATIENTS[patient]
    path = Path(row.get("image") or row["labels"])
    return _scan_size_of(patient, path.exists())


@lru_cache(maxsize=None)
def _scan_size_of(patient, exists):
    row = PATIENTS[patient]
    path = Path(row.get("image") or row["labels"])
    if exists:
        voxels, spacing = scan_header(path)
    else:  # a phantom the workflow makes
        name = path.name.split(".")[0]
        size = CONFIG["workflow"]["phantom_size"] or DEFAULT_SIZE.get(name, 256)
        voxels, spacing = size ** 3, None
    settings = patient_config(patient)
    coarse = voxels
    if patient not in LABEL_PATIENTS or downsample_applies(settings):
        down = settings["downsample"]
        if down.get("voxel_size") is not None and spacing is not None:
            target = down["voxel_size"]
            target = target if isinstance(target, list) else [target] * len(spacing)
            ratio = 1.0
            for have, want in zip(spacing, target):
                ratio *= min(1.0, have / want)
            coarse = max(1, int(voxels * ratio))
        else:
            factor = down["factor"]
            factor = factor if isinstance(factor, list) else [factor] * 3
            for f in factor:
                coarse = coarse // max(1, int(f))
    return voxels, max(1, coarse)


def _elements(patient):
    """The mesh's element count once mesh.vtu exists; before, None (the formula assumes
    dicer.resources.ELEMENT_FRACTION of the coarse voxels)."""
    mesh = Path(patient_file("mesh.vtu").format(patient=patient))
    try:
        return mesh_elements(mesh)
    except (OSError, ValueError):
        return None


def _estimate(stage, wildcards, attempt):
    if stage == "phantom":
        size = CONFIG["workflow"]["phantom_size"] or DEFAULT_SIZE.get(wildcards.name, 256)
        return estimate("phantom", voxels=size ** 3, attempt=attempt)
    order = 1
    if stage == "export":
        stage = f"export_{wildcards.ext}"
        order = patient_config(wildcards.patient)["export"]["order"]  # order 2: the quadratic mesh besides
    voxels, coarse = _scan_size(wildcards.patient)
    return estimate(stage, voxels=voxels, voxels_ds=coarse, elements=_elements(wildcards.patient),
                    attempt=attempt, scan=wildcards.patient not in LABEL_PATIENTS, order=order)


def mem_mb(stage):
    """resources: mem_mb of `stage` (MB), scaled by the attempt."""
    return lambda wildcards, attempt: _estimate(stage, wildcards, attempt)[0]


def runtime(stage):
    """resources: runtime of `stage` (minutes), scaled by the attempt."""
    return lambda wildcards, attempt: _estimate(stage, wildcards, attempt)[1]


def benchmark_file(stage):
    """benchmark: seconds and peak memory of one stage of one patient, in its results folder (two
    results folders in one working folder keep their own)."""
    return os.path.join(RESULTS, "benchmarks", "{patient}", f"{stage}.tsv")


def log_file(stage):
    """log: the output and errors of one stage of one patient, in its results folder."""
    return os.path.join(RESULTS, "logs", "{patient}", f"{stage}.log")
