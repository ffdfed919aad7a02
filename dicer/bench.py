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
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def shell_labels(n: int):
    """(n, n, n) uint8: 2 inside radius 0.30 n, 1 out to 0.45 n, 0 outside (1 mm voxels)."""
    import numpy as np

    c = (np.arange(n, dtype=np.float32) - n / 2 + 0.5) ** 2
    r2 = c[:, None, None] + c[None, :, None] + c[None, None, :]
    return ((r2 < (0.45 * n) ** 2).astype(np.uint8) + (r2 < (0.30 * n) ** 2)).astype(np.uint8)


def _mesh(n):
    from dicer.mesh.voxel import voxel_mesh

    return voxel_mesh(shell_labels(n))


def _config():
    from dicer.config import load_config

    return load_config()


# Each case: (setup(n) -> state, run(state, tmpdir) -> extra dict or None, what it measures)
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


def _case_export_abaqus():
    def run(mesh, tmp):
        from dicer.export import export_mesh

        path = Path(tmp) / "model.inp"
        export_mesh(mesh, path, _config(), source="bench", verify=False)
        return {"bytes": path.stat().st_size}

    return _mesh, run, "dicer Abaqus .inp writer (order 1)"


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
    "mesh": _case_mesh,
    "pyvista_threshold": _case_pyvista_threshold,
    "export_abaqus": _case_export_abaqus,
    "meshio_abaqus": _case_meshio_abaqus,
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
