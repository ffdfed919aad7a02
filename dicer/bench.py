"""Benchmark: seconds and peak memory of dicer's stages beside peer tools, same run.

    python -m dicer.bench                 # 256^3 two-material ball, every case
    python -m dicer.bench --size 128 --cases mesh,pyvista_threshold

Each case runs in its own process (so peak memory is its own); the input is built
before the clock starts. The workload is the two-material ball of the shell phantom:
radius 0.45 n, inner material radius 0.30 n (about 6.4 M hexahedra at n = 256).
Ratios between cases of one run are what to compare: absolute times vary with load.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def shell_labels(n: int):
    """(n, n, n) uint8 labels of the shell phantom (see ``dicer.phantoms.shell_labels``)."""
    from dicer.phantoms import shell_labels as phantom

    return phantom(n).array


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
            from dicer.export import benchmark_export

            info = benchmark_export(mesh, tmp, suffix=suffix, config=_config())
            return {"bytes": info["bytes"]}

        return _mesh, run, what

    return case


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
    parser = argparse.ArgumentParser(prog="python -m dicer.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="n of the n^3 workload (default 256)")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated cases (default: all)")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # child process: run one case
    args = parser.parse_args(argv)
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
        proc = subprocess.run([sys.executable, "-m", "dicer.bench", "--case", name, "--size", str(args.size)],
                              capture_output=True, text=True, env=os.environ)
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


if __name__ == "__main__":
    raise SystemExit(main())
