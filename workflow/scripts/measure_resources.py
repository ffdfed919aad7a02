"""Measure each workflow stage's wall time and peak memory on one scan.

    python workflow/scripts/measure_resources.py IMAGE|phantom:NAME:SIZE OUTDIR [--set KEY=VALUE ...]

Runs the stages as the workflow's rules do (phantom when asked, segment, labels on the
segmented labels, downsample, fix, mesh, merge, smooth, export .inp and .vtu, quality), each
in a fresh process, and prints one TSV line per stage:
stage, scan voxels, mesh elements, seconds, peak resident memory in MB (the process's own
maximum RSS from wait4, as `/usr/bin/time -v` reports it). The resource formula in
workflow/rules/resources.smk (docs/cluster.md) was fitted to such lines.
"""

import argparse
import subprocess
import sys
from pathlib import Path


# A small interpreter forks and runs the command, then reports its child's peak: a child
# forked straight from a big process (pytest, or this script after importing numpy and
# SimpleITK) would count the parent's resident memory in its own peak (Linux keeps the
# pre-exec high-water mark in ru_maxrss).
_HELPER = """
import os, sys, time
start = time.perf_counter()
pid = os.fork()
if pid == 0:
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    try:
        os.execvp(sys.argv[1], sys.argv[1:])
    finally:
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
print(os.waitstatus_to_exitcode(status), time.perf_counter() - start, usage.ru_maxrss)
"""


def run_measured(argv: list[str]) -> tuple[float, float]:
    """(seconds, peak RSS in MB) of one command, as `/usr/bin/time -v` reports them (the
    process's maximum resident set size from wait4); raises on a non-zero exit."""
    proc = subprocess.run([sys.executable, "-S", "-c", _HELPER, *argv], capture_output=True, text=True)
    code, seconds, max_rss_kb = proc.stdout.split()
    if int(code) != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({code}): {proc.stderr.strip()[-500:]}")
    return float(seconds), int(max_rss_kb) / 1024.0  # ru_maxrss: kB on Linux


def stage_commands(image: Path, out: Path, sets: list[str], dicer: str = "dicer") -> list[tuple[str, list[str]]]:
    o = lambda name: str(out / name)  # noqa: E731
    return [
        ("segment", [dicer, "segment", str(image), "-o", o("labels.nii.gz"), "--overlay", o("segmentation.png"),
                     "--info", o("segmentation.json")]),
        ("labels", [dicer, "labels", o("labels.nii.gz"), "-o", o("relabelled.nii.gz"), "--materials",
                    o("materials.json")]),
        ("downsample", [dicer, "downsample", o("labels.nii.gz"), "-o", o("labels_ds.nii.gz")]),
        ("fix", [dicer, "fix", o("labels_ds.nii.gz"), "-o", o("labels_fixed.nii.gz"), "--report", o("fix.json")]),
        ("mesh", [dicer, "mesh", o("labels_fixed.nii.gz"), "-o", o("mesh.vtu")]),
        ("merge", [dicer, "merge", o("mesh.vtu"), "-o", o("merged.vtu"), "--report", o("merge.json")]),
        ("smooth", [dicer, "smooth", o("merged.vtu"), "-o", o("smoothed.vtu"), "--report", o("smooth.json"),
                    "--labels", o("labels_fixed.nii.gz")]),
        ("export_inp", [dicer, "export", o("smoothed.vtu"), "-o", o("model.inp")]),
        ("export_vtu", [dicer, "export", o("smoothed.vtu"), "-o", o("model.vtu")]),
        ("quality", [dicer, "quality", o("smoothed.vtu"), "--labels", o("labels_fixed.nii.gz"),
                     "--original", o("labels.nii.gz"), "-o", o("quality.json"), "--html", o("report.html"),
                     "--histogram", o("jacobian.png"), "--model-picture", o("model.png"),
                     "--node-classes", o("node_classes.png"), "--picture", o("segmentation.png"),
                     "--stage-report", o("fix.json"), "--stage-report", o("merge.json"),
                     "--stage-report", o("smooth.json")]),
    ]


def measure(image: Path | str, out: Path, sets: list[str], dicer: str = "dicer") -> list[dict]:
    """One row per stage: stage, voxels, voxels_ds, elements, seconds, max_rss_mb."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from dicer.resources import scan_voxels, mesh_elements

    out.mkdir(parents=True, exist_ok=True)
    commands = []
    if str(image).startswith("phantom:"):
        _, name, size = str(image).split(":")
        image = out / f"{name}.nii.gz"
        commands.append(("phantom", [dicer, "phantom", name, "--size", size, "-o", str(image)]))
    commands += stage_commands(Path(image), out, sets, dicer)
    rows = []
    for stage, argv in commands:
        options = [x for s in sets for x in ("--set", s)] if stage != "phantom" else []
        seconds, peak = run_measured(argv + options + ["-q"])
        rows.append({"stage": stage, "seconds": round(seconds, 2), "max_rss_mb": round(peak, 1)})
    voxels = scan_voxels(image)
    voxels_ds = scan_voxels(out / "labels_ds.nii.gz")
    elements = mesh_elements(out / "mesh.vtu")
    return [{"stage": r["stage"], "voxels": voxels, "voxels_ds": voxels_ds,
             "elements": elements if r["stage"] in ("merge", "smooth", "export_inp", "export_vtu", "quality") else 0,
             "seconds": r["seconds"], "max_rss_mb": r["max_rss_mb"]} for r in rows]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("image", help="a scan, or phantom:NAME:SIZE (made by dicer phantom, measured too)")
    parser.add_argument("outdir", type=Path)
    parser.add_argument("--set", dest="sets", action="append", default=[])
    args = parser.parse_args()
    for row in measure(args.image, args.outdir, args.sets):
        print("\t".join(str(v) for v in row.values()), flush=True)


if __name__ == "__main__":
    main()
