"""Benchmark: seconds and peak memory of dicer beside peer tools, same run (run from the repository's top).

    python -m bench --processes     # what users run: whole processes, 64^3 -> 256^3
    python -m bench --processes --sizes 64,128,256,512 --repeat 2
    python -m bench                 # library functions, 256^3 two-material ball, every case
    python -m bench --size 128 --cases mesh,pyvista_threshold

``--processes`` times each command a user runs (``dicer mesh``, ``merge``, ``smooth``,
``export``, ``quality``, ``run``), every one a fresh process with all its checks (read-back
verification included), next to automesh 0.3.1 doing the same job as a process of its
own (labels -> hexahedra -> VTK, Taubin smoothing -> VTK, -> Abaqus .inp, .inp -> metrics),
interleaved pair by pair; for each it reports wall seconds, CPU seconds (user + system)
and the peak resident memory of the process (``wait4``). The library cases run each
stage's function in its own process with its input built before the clock starts.
The workload is the two-material ball of the shell phantom: radius 0.45 n, inner
material radius 0.30 n (about 6.4 M hexahedra at n = 256); ``dicer run`` segments its
noisy CT. Ratios between cases of one run are what to compare: absolute times vary with load.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
"""The repository's top folder, from which ``python -m bench`` runs."""


def shell_labels(n: int):
    """(n, n, n) uint8 labels of the shell phantom (see ``dicer.phantoms.shell_labels``)."""
    from dicer.phantoms import shell_labels as phantom

    return phantom(n).array


def atlas_labels(n: int, parcels: int = 200, seed: int = 0):
    """(n, n, n) uint16 labels of an atlas: the Voronoi regions of ``parcels`` random seeds
    in a ball of radius 0.45 n (as a brain atlas's parcels), labelled 1..parcels."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    seeds = np.zeros((n, n, n), np.uint16)
    # seeds uniform in the ball, on distinct voxels
    at = rng.uniform(0, 1, (4 * parcels, 3)) * (0.9 * n) + 0.05 * n
    at = at[np.linalg.norm(at - n / 2, axis=1) < 0.45 * n].astype(np.int64)
    _, first = np.unique(at[:, 0] * n * n + at[:, 1] * n + at[:, 2], return_index=True)
    at = at[np.sort(first)[:parcels]]
    seeds[tuple(at.T)] = np.arange(1, at.shape[0] + 1)
    _, index = ndimage.distance_transform_edt(seeds == 0, return_indices=True)
    labels = seeds[tuple(index)]
    grid = np.indices((n, n, n), sparse=True)
    labels[sum((g + 0.5 - n / 2) ** 2 for g in grid) >= (0.45 * n) ** 2] = 0
    return labels


def _mesh(n):
    from dicer.mesh.voxel import voxel_mesh

    return voxel_mesh(shell_labels(n))


@functools.lru_cache(maxsize=1)
def _config():
    from dicer.config import load_config

    return load_config()


def _warm_up() -> None:
    """Import dicer's stages and load the default config before the clock starts, as the
    peer cases import their libraries in their setup."""
    import dicer.connectivity  # noqa: F401
    import dicer.export  # noqa: F401
    import dicer.mesh.merge  # noqa: F401
    import dicer.mesh.smooth  # noqa: F401
    import dicer.mesh.voxel  # noqa: F401
    import dicer.segment  # noqa: F401

    _config()


# Each case: (setup(n) -> state, run(state, tmpdir) -> extra dict or None, what it measures)
def _case_segment():
    def setup(n):
        from dicer.phantoms import make_phantom

        return make_phantom("shell", size=n)

    def run(image, tmp):
        from dicer.segment import segment

        labels, info = segment(image, _config())
        return {"thresholds": info["thresholds"]}

    return setup, run, "dicer segment: threshold search + morphology (noisy CT of the ball)"


def _case_fix():
    def run(labels, tmp):
        from dicer.connectivity import fix_connectivity

        _, report = fix_connectivity(labels)
        return {"changed_voxels": report["changed_voxels"]}

    return shell_labels, run, "dicer fix: connectivity fixes A, B, C"


def _case_mesh():
    def run(labels, tmp):
        from dicer.mesh.voxel import voxel_mesh

        m = voxel_mesh(labels)
        return {"elements": m.n_cells, "nodes": m.n_points}

    return shell_labels, run, "dicer voxel mesh (labels -> hexahedra)"


def _case_pyvista_threshold():
    def setup(n):
        import pyvista as pv

        labels = shell_labels(n)
        grid = pv.ImageData(dimensions=tuple(s + 1 for s in labels.shape))
        grid.cell_data["material"] = labels.ravel(order="F")
        return grid

    def run(grid, tmp):
        out = grid.threshold(0.5, scalars="material")
        return {"elements": int(out.n_cells), "nodes": int(out.n_points)}

    return setup, run, "PyVista ImageData.threshold (VTK, same volume)"


def _case_merge():
    def run(mesh, tmp):
        from dicer.mesh.merge import merge_planes

        merged, _ = merge_planes(mesh, passes=(1, 1, 1))
        return {"elements": merged.n_cells, "nodes": merged.n_points}

    return _mesh, run, "dicer merge, passes [1,1,1]"


def _case_smooth():
    def run(mesh, tmp):
        from dicer.mesh.smooth import smooth_mesh

        _, report = smooth_mesh(mesh, _config().get("smooth"))
        return {"min_scaled_jacobian": report.get("min_scaled_jacobian")}

    return _mesh, run, "dicer smooth: boundary + interior solves with the quality guard"


def _case_automesh_smooth():
    def setup(n):
        import automesh

        labels = shell_labels(n)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "labels.npy"
            np.save(path, labels)
            return automesh.Voxels.from_npy(str(path)).as_finite_elements(remove=[0])

    def run(fem, tmp):
        fem.smooth(method="Taubin", hierarchical=True, iterations=10)

    return setup, run, "automesh 0.3.1 (Rust) smooth: Taubin, hierarchical, 10 iterations (same ball)"


def _export_case(suffix: str, what: str):
    def case():
        def run(mesh, tmp):
            info = benchmark_export(mesh, tmp, suffix=suffix, config=_config())
            return {"bytes": info["bytes"]}

        return _mesh, run, what

    return case


def benchmark_export(mesh, folder, suffix: str = ".inp", config: dict | None = None) -> dict:
    """Seconds and bytes of one export of ``mesh`` into ``folder`` (no read-back); the file is deleted.

    config : dicer's default configuration if None.
    """
    from dicer.config import load_config
    from dicer.export import export_mesh

    path = Path(folder) / f"bench_model{suffix}"
    t0 = time.perf_counter()
    info = export_mesh(mesh, path, config or load_config(), source=None, check=False)
    seconds = time.perf_counter() - t0
    path.unlink(missing_ok=True)
    return {"seconds": seconds, "bytes": info["bytes"], "elements": info["elements"], "nodes": info["nodes"]}


def _case_meshio_abaqus():
    def setup(n):
        import meshio

        m = _mesh(n)
        return meshio.Mesh(m.points, [("hexahedron", m.cells)])

    def run(mesh, tmp):
        import meshio

        path = Path(tmp) / "model.inp"
        meshio.write(path, mesh, file_format="abaqus")
        return {"bytes": path.stat().st_size}

    return setup, run, "meshio.write(..., 'abaqus') (same mesh)"


CASES = {
    "segment": _case_segment,
    "fix": _case_fix,
    "mesh": _case_mesh,
    "pyvista_threshold": _case_pyvista_threshold,
    "merge": _case_merge,
    "smooth": _case_smooth,
    "automesh_smooth": _case_automesh_smooth,
    "export_abaqus": _export_case(".inp", "dicer Abaqus/CalculiX .inp writer (order 1, all sets)"),
    "meshio_abaqus": _case_meshio_abaqus,
    "export_patran": _export_case(".out", "dicer PATRAN neutral writer (order 1)"),
    "export_lsdyna": _export_case(".k", "dicer LS-DYNA keyword writer"),
    "export_vtu": _export_case(".vtu", "dicer VTU writer (with scaled Jacobian cell data)"),
}


# --- whole processes ----------------------------------------------------------------------

# automesh 0.3.1 jobs, each run as its own process through automesh's Python module (the
# same Rust library its command line uses): {npy, out, inp} are filled in
_AUTOMESH = {
    "mesh_vtk": "v = automesh.Voxels.from_npy({npy!r}).as_finite_elements(remove=[0]); v.write_vtk({out!r})",
    "smooth_vtk": ("v = automesh.Voxels.from_npy({npy!r}).as_finite_elements(remove=[0]); "
                   "v.smooth(method='Taubin', hierarchical=True, iterations=10); v.write_vtk({out!r})"),
    "inp": "v = automesh.Voxels.from_npy({npy!r}).as_finite_elements(remove=[0]); v.write_inp({out!r})",
    "metrics": "v = automesh.HexahedralFiniteElements.from_inp({inp!r}); v.write_metrics({out!r})",
}

# (name, what, command as a function of the work folder, peer job name or None)
PROCESS_JOBS = [
    ("mesh", "dicer mesh ball.npy -o mesh.vtu", lambda d: ["mesh", d / "ball.npy", "-o", d / "mesh.vtu"]),
    ("automesh mesh", "npy -> hexahedra -> VTK", "mesh_vtk"),
    ("merge", "dicer merge mesh.vtu -o merged.vtu (default planes)",
     lambda d: ["merge", d / "mesh.vtu", "-o", d / "merged.vtu"]),
    ("merge templates", "dicer merge mesh.vtu -o graded.vtu --set merge.method=templates (graded)",
     lambda d: ["merge", d / "mesh.vtu", "-o", d / "graded.vtu", "--set", "merge.method=templates"]),
    ("smooth", "dicer smooth mesh.vtu -o smoothed.vtu (the voxel mesh, as automesh)",
     lambda d: ["smooth", d / "mesh.vtu", "-o", d / "smoothed.vtu"]),
    ("automesh smooth", "npy -> hexahedra -> Taubin, hierarchical, 10 iterations -> VTK", "smooth_vtk"),
    ("export .inp", "dicer export smoothed.vtu -o model.inp", lambda d: ["export", d / "smoothed.vtu", "-o",
                                                                         d / "model.inp"]),
    ("automesh .inp", "npy -> hexahedra -> .inp", "inp"),
    ("export .vtu", "dicer export smoothed.vtu -o model.vtu", lambda d: ["export", d / "smoothed.vtu", "-o",
                                                                         d / "model.vtu"]),
    ("quality", "dicer quality smoothed.vtu -o quality.json --labels ball.npy",
     lambda d: ["quality", d / "smoothed.vtu", "-o", d / "quality.json", "--labels", d / "ball.npy"]),
    ("quality --csv", "dicer quality smoothed.vtu -o q.json --csv metrics.csv (automesh's columns)",
     lambda d: ["quality", d / "smoothed.vtu", "-o", d / "q.json", "--csv", d / "metrics.csv"]),
    ("automesh metrics", "its .inp -> metrics CSV", "metrics"),
    ("run", "dicer run ct.nii.gz -o out/ (segment ... quality)", lambda d: ["run", d / "ct.nii.gz", "-o", d / "out"]),
    ("run atlas", "dicer run --labels atlas.npy -o atlas/ (200 Voronoi parcels in a ball, default materials)",
     lambda d: ["run", "--labels", d / "atlas.npy", "-o", d / "atlas"]),
]

# each dicer process next to the automesh process doing the same job
PEERS = {"mesh": "automesh mesh", "smooth": "automesh smooth", "export .inp": "automesh .inp",
         "quality": "automesh metrics", "quality --csv": "automesh metrics"}


# Starts one command and reports its wall and CPU seconds, peak memory (KB) and exit
# status. The bench's own process forks this small launcher, never the command: a forked
# child starts its peak-memory count at its parent's size.
_LAUNCH = """import json, os, sys, time
t = time.perf_counter()
pid = os.posix_spawn(sys.argv[1], sys.argv[1:], os.environ,
                     file_actions=[(os.POSIX_SPAWN_OPEN, 1, os.devnull, os.O_WRONLY, 0)])
_, status, use = os.wait4(pid, 0)
print(json.dumps([time.perf_counter() - t, use.ru_utime + use.ru_stime, use.ru_maxrss,
                  os.waitstatus_to_exitcode(status)]))
"""


def run_process(cmd: list) -> dict:
    """Run ``cmd`` (its first item a full path) to its end: its wall seconds, CPU seconds
    (user + system) and peak resident memory in MB (``wait4``)."""
    proc = subprocess.run([sys.executable, "-S", "-c", _LAUNCH, *[str(c) for c in cmd]], capture_output=True,
                          text=True)
    try:
        seconds, cpu, peak_kb, code = json.loads(proc.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        seconds, cpu, peak_kb, code = float("nan"), float("nan"), float("nan"), proc.returncode or 1
    out = {"seconds": round(seconds, 2), "cpu_seconds": round(cpu, 2), "peak_rss_mb": round(peak_kb / 1024, 1)}
    if code != 0:
        tail = (proc.stderr.strip().splitlines() or ["failed"])[-1]
        out["error"] = f"exit {code}: {tail[:200]}"
    return out


def _job_command(job, work: Path) -> list:
    name, what, cmd = job
    if callable(cmd):
        return [sys.executable, "-m", "dicer.cli", *cmd(work), "-q"]
    suffix = {"mesh_vtk": "vtk", "smooth_vtk": "vtk", "inp": "inp", "metrics": "csv"}[cmd]
    code = "import automesh; " + _AUTOMESH[cmd].format(npy=str(work / "ball.npy"), out=str(work / f"am_{cmd}.{suffix}"),
                                                        inp=str(work / "am_inp.inp"))
    return [sys.executable, "-c", code]


def _prepare(n: int, work: Path) -> None:
    """The inputs, before any clock: the ball's labels (.npy) and its noisy CT (.nii.gz)."""
    from dicer.io.images import write_image
    from dicer.phantoms import make_phantom

    work.mkdir(parents=True, exist_ok=True)
    np.save(work / "ball.npy", shell_labels(n))
    np.save(work / "atlas.npy", atlas_labels(n))
    write_image(make_phantom("shell", size=n), work / "ct.nii.gz")


def _byte_compile() -> None:
    """Compile dicer's modules to bytecode, as ``pip install`` does: an editable install
    compiles them on first import, or never where PYTHONDONTWRITEBYTECODE is set, and then
    every timed process would compile dicer from source (0.1-0.2 s each)."""
    import compileall

    import dicer

    compileall.compile_dir(Path(dicer.__file__).parent, quiet=1)


def bench_processes(sizes, repeat: int = 1, workdir: str | None = None, jobs=None, log=print) -> list[dict]:
    """Time PROCESS_JOBS at every size; one row per job and size (the fastest of ``repeat``
    runs by wall time, its CPU time, and the largest peak)."""
    chosen = [j for j in PROCESS_JOBS if jobs is None or j[0] in jobs]
    _byte_compile()
    rows = []
    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)  # a new folder is the usual wish
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        for n in sizes:
            work = Path(tmp) / str(n)
            _prepare(n, work)
            runs: dict[str, list[dict]] = {}
            for r in range(repeat):
                for job in chosen:
                    res = run_process(_job_command(job, work))
                    runs.setdefault(job[0], []).append(res)
                    log(f"{n:4d}^3 {job[0]:18s} {res['seconds']:8.2f} s wall {res['cpu_seconds']:8.2f} s cpu "
                        f"{res['peak_rss_mb']:7.0f} MB  {res.get('error', '')}")
            for job in chosen:
                res = runs[job[0]]
                best = min(res, key=lambda x: x["seconds"])
                rows.append({"size": n, "case": job[0], "what": job[1], **best,
                             "peak_rss_mb": max(x["peak_rss_mb"] for x in res),
                             "wall_all": [x["seconds"] for x in res]})
            shutil.rmtree(work, ignore_errors=True)
    return rows


def process_tables(rows: list[dict]) -> str:
    """Markdown: per size the jobs with seconds, CPU seconds, peak MB and the ratio to the
    automesh process doing the same job; then the scaling of each job over the sizes."""
    out = []
    sizes = sorted({r["size"] for r in rows})
    for n in sizes:
        at = {r["case"]: r for r in rows if r["size"] == n}
        out += [f"n = {n} ({n}^3 voxels)", "", "| process | wall s | CPU s | peak MB | vs automesh (wall / CPU) |",
                "|---|---|---|---|---|"]
        for name, r in at.items():
            peer = at.get(PEERS.get(name, ""))
            ratio = (f"{r['seconds'] / peer['seconds']:.2f} / {r['cpu_seconds'] / peer['cpu_seconds']:.2f}"
                     if peer and peer["seconds"] and peer["cpu_seconds"] and "error" not in r else "")
            out.append(f"| {name} | {r['seconds']:.2f} | {r['cpu_seconds']:.2f} | {r['peak_rss_mb']:.0f} | {ratio} |"
                       + (f" {r['error']}" if "error" in r else ""))
        four = [at.get(k) for k in ("automesh mesh", "automesh smooth", "automesh .inp", "automesh metrics")]
        if all(four) and "run" in at:
            total = sum(x["seconds"] for x in four)
            cpu = sum(x["cpu_seconds"] for x in four)
            out.append(f"| automesh's four added up | {total:.2f} | {cpu:.2f} | | run: "
                       f"{at['run']['seconds'] / total:.2f} / {at['run']['cpu_seconds'] / cpu:.2f} |")
        out.append("")
    if len(sizes) > 1:
        a, b = sizes[-2], sizes[-1]
        out += ["| process | " + " | ".join(f"{n}^3 s (MB)" for n in sizes) + f" | exponent {a}^3 -> {b}^3 |",
                "|---|" + "---|" * (len(sizes) + 1)]
        for name in dict.fromkeys(r["case"] for r in rows):
            by = {r["size"]: r for r in rows if r["case"] == name}
            cells = [f"{by[n]['seconds']:.2f} ({by[n]['peak_rss_mb']:.0f})" if n in by else "" for n in sizes]
            lo, hi = by.get(a), by.get(b)
            exp = (f"{np.log(hi['seconds'] / lo['seconds']) / np.log((b / a) ** 3):.2f}"
                   if lo and hi and lo["seconds"] > 0 else "")
            out.append(f"| {name} | " + " | ".join(cells) + f" | {exp} |")
        out.append("")
        out.append("exponent: time ~ voxels^exponent between the two largest sizes (wall seconds; at small sizes "
                   "the start of a process, about a second, dominates)")
    return "\n".join(out) + "\n"


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _run_case(name: str, n: int) -> dict:
    import resource

    setup, run, what = CASES[name]()
    state = setup(n)
    _warm_up()
    base = _rss_mb()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        extra = run(state, tmp) or {}
        seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"case": name, "what": what, "seconds": round(seconds, 3), "peak_rss_mb": round(peak, 1),
            "input_rss_mb": round(base, 1), **extra}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="n of the n^3 workload (default 256)")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated cases (default: all)")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    parser.add_argument("--processes", action="store_true",
                        help="time whole processes (dicer's commands and automesh's) instead of library cases")
    parser.add_argument("--sizes", default="64,128,256",
                        help="with --processes: the n of each n^3 workload (default 64,128,256; add 512 for the "
                             "largest, which takes long and needs about 24 GB)")
    parser.add_argument("--jobs", help="with --processes: comma-separated jobs (default: all; names as printed)")
    parser.add_argument("--repeat", type=int, default=1, help="with --processes: runs of each job (fastest kept)")
    parser.add_argument("--workdir", help="with --processes: folder for the temporary files (default: the system's)")
    parser.add_argument("--markdown", metavar="FILE", help="with --processes: also write the tables as Markdown")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # child process: run one case
    args = parser.parse_args(argv)
    if args.processes:
        return _main_processes(args)
    if args.case:
        print(json.dumps(_run_case(args.case, args.size)))
        return 0
    names = [c for c in args.cases.split(",") if c]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        print(f"error: unknown case(s) {', '.join(unknown)}; known: {', '.join(CASES)}", file=sys.stderr)
        return 2
    rows = []
    print(f"workload: two-material ball, {args.size}^3 voxels", flush=True)
    for name in names:
        proc = subprocess.run([sys.executable, "-m", "bench", "--case", name, "--size", str(args.size)],
                              capture_output=True, text=True, env=os.environ, cwd=ROOT)
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["failed"])[-1]
            rows.append({"case": name, "what": tail[:90], "seconds": None, "peak_rss_mb": None})
        else:
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        secs = f"{r['seconds']:9.2f}" if r["seconds"] is not None else "      n/a"
        peak = f"{r['peak_rss_mb']:9.0f}" if r["peak_rss_mb"] is not None else "      n/a"
        print(f"{name:22s} {secs} s {peak} MB  {r['what']}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"size": args.size, "results": rows}, indent=2) + "\n")
    return 0


def _main_processes(args) -> int:
    try:
        sizes = [int(v) for v in args.sizes.split(",") if v]
    except ValueError:
        print(f"error: --sizes {args.sizes!r}: give comma-separated integers, e.g. 64,128,256", file=sys.stderr)
        return 2
    jobs = [j for j in args.jobs.split(",") if j] if args.jobs else None
    known = [j[0] for j in PROCESS_JOBS]
    if jobs and any(j not in known for j in jobs):
        print(f"error: unknown job(s) {', '.join(j for j in jobs if j not in known)}; known: {', '.join(known)}",
              file=sys.stderr)
        return 2
    load = os.getloadavg()
    print(f"whole processes on the two-material ball, sizes {sizes}, {os.cpu_count()} cores, load average "
          f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}", flush=True)
    rows = bench_processes(sizes, max(1, args.repeat), args.workdir, jobs, log=lambda m: print(m, flush=True))
    tables = process_tables(rows)
    print(tables)
    if args.markdown:
        Path(args.markdown).write_text(tables)
    if args.json:
        Path(args.json).write_text(json.dumps({"sizes": sizes, "load_average": load, "results": rows}, indent=2) + "\n")
    return 0
