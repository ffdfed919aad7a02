"""The ``dicer`` command: a thin layer over the library stages.

Every sub-command reads its input, runs one stage (``run``: all of them) and
writes its output atomically. Bad input ends in one line ``error: ...`` on
standard error and exit status 2, with no output file left behind.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from dicer import __version__, library_versions
from dicer.brief import brief_json, brief_names
from dicer.errors import DicerError
from dicer.io import LABEL_SUFFIXES
from dicer.io.atomic import all_or_nothing, check_stop, stop_requested
from dicer.pages import LARGE_JOB, large_job, ordinary_pages, reuse_freed_memory
from dicer.parallel import one_blas_thread

log = logging.getLogger("dicer")


def _config(args) -> dict:
    from dicer.config import load_config

    settings = None
    if getattr(args, "settings", None):
        try:
            settings = json.loads(args.settings)
        except json.JSONDecodeError as exc:
            raise DicerError(f"--settings: not valid JSON ({exc.msg}); pass a JSON object") from None
        if not isinstance(settings, dict):
            raise DicerError("--settings: pass a JSON object of config sections")
    sets, named = list(args.set or ()), "--set"
    if getattr(args, "order", None) is not None:  # dicer export --order: read with the rest (the element type fits it)
        sets.append(f"export.order={args.order}")
        named = "--set and --order" if args.set else "--order"
    command = getattr(args, "command", None)
    # the workflow's labels rule gives the names alone: its materials.json holds no properties
    used = command in ("run", "export", "quality") or (command == "labels" and not _names_only(args))
    config = load_config(args.config, sets, settings, sets_named=named, properties_used=used)
    if getattr(args, "command", None) in ("smooth", "run"):  # the commands that smooth
        from dicer.config import unused_smooth_settings

        for sentence in unused_smooth_settings(config["smooth"]):
            log.warning("smooth: %s", sentence)
    if getattr(args, "materials", None):
        # the file gives the materials of the mapped labels, in order; a material the user's
        # own config also lists takes its properties from there (the workflow's label patients:
        # a stiffness study re-runs the exports alone, not the labels that wrote the file)
        listed = {m["name"]: m for m in config["materials"]} if _lists_materials(args, settings) else {}
        config["materials"] = [listed.get(m.get("name"), m) if isinstance(m, dict) else m
                               for m in _read_materials(args.materials)]
        from dicer.config import validate

        validate(config, args.materials)
    return config


def _lists_materials(args, settings: dict | None) -> bool:
    """Whether the command's own configuration (--settings, --set or --config) lists the
    materials, rather than taking the defaults'."""
    from dicer.config import read_config_file

    if settings is not None and "materials" in settings:
        return True
    if any(item.split("=", 1)[0].strip().split(".")[0] == "materials" for item in args.set or ()):
        return True
    return bool(getattr(args, "config", None)) and "materials" in read_config_file(args.config)


def _warn_of_unused_settings(args) -> None:
    """Warn of --set keys the command does not read (``image.crop`` to 'dicer mesh': the crop
    is made when the scan or the label volume is read, by segment and labels)."""
    from dicer.config import STAGE_KEYS, STAGE_SECTIONS

    stage = args.command
    if stage not in STAGE_SECTIONS or not getattr(args, "set", None):
        return
    reads = STAGE_SECTIONS[stage] + STAGE_KEYS.get(stage, ())
    unused = []
    for item in args.set:
        key = item.split("=", 1)[0].strip()
        if key != "preset" and not any(key == r or key.startswith(r + ".") for r in reads):  # a preset: every stage's
            unused.append(key)
    if unused:
        log.warning("%s: --set %s is not read by dicer %s (it reads %s); give it to the stage that uses it, or to "
                    "dicer run", stage, ", ".join(unused), stage, ", ".join(reads))


def _read_materials(path: str) -> list[dict]:
    """The materials list of a materials file written by ``dicer labels`` (--materials)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DicerError(f"{path}: materials file not found; write it with dicer labels --materials") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DicerError(f"{path}: cannot read the materials file ({exc}); write it again with "
                         "dicer labels --materials") from None
    if not isinstance(data, dict) or not isinstance(data.get("materials"), list):
        raise DicerError(f"{path}: not a materials file (no materials list); write it with dicer labels --materials")
    return data["materials"]


class _Stage:
    """Log a stage's end with its wall time (nothing before: bad input stays one error line)."""

    current = ""  # the stage running, named in the lines of the library's own loggers

    def __init__(self, name: str):
        self.name = name

    def __enter__(self):
        self.t0 = time.perf_counter()
        _Stage.current = self.name
        return self

    def __exit__(self, exc_type, exc, tb):
        _Stage.current = ""
        if exc_type is None:
            log.info("%s: done in %.2f s", self.name, time.perf_counter() - self.t0)


def _check_output(path: str, suffixes: tuple[str, ...], what: str) -> Path:
    out = Path(path)
    if not out.name.lower().endswith(suffixes):
        raise DicerError(f"{out}: {what} must be one of {', '.join(suffixes)}; rename the output")
    return out


#: argparse destinations holding output files, with the option that sets them
OUTPUT_OPTIONS = {"output": "-o", "overlay": "--overlay", "plot": "--plot", "info": "--info", "report": "--report",
                  "html": "--html", "materials_out": "--materials", "csv": "--csv", "histogram": "--histogram",
                  "model_picture": "--model-picture", "node_classes": "--node-classes", "tsv": "--tsv"}
#: argparse destinations holding input files or folders
INPUT_OPTIONS = ("image", "labels", "mesh", "config", "picture", "stage_report", "materials", "thresholds",
                 "original", "reports")


def _input_paths(args) -> list[Path]:
    """The paths a command reads (its options of :data:`INPUT_OPTIONS`)."""
    inputs = []
    for dest in INPUT_OPTIONS:
        value = getattr(args, dest, None)
        for item in value if isinstance(value, list) else [value]:
            if item:
                inputs.append(Path(item))
    return inputs


def _same(a: Path, b: Path) -> bool:
    """Whether paths ``a`` (an input) and ``b`` (an output) name the same file or folder.

    ``b`` may not exist yet under its spelling (``new/../input.nii``) and still land
    on ``a`` once its parent folders are made, so it is also compared resolved.
    """
    try:
        if not a.exists():
            return False
        if b.exists():
            return os.path.samefile(a, b)
        return os.path.realpath(a) == os.path.realpath(b)
    except OSError:
        return False


def _check_paths(args) -> None:
    """Refuse, before any work, outputs that would hit a folder, an input or each other.

    Every command goes through here, so no command can replace its own input (the
    input would be gone if the stage then failed) or end in a traceback when an
    output path names a folder. ``run`` writes into a folder: its fixed file names are
    checked instead.
    """
    inputs = _input_paths(args)
    if args.command == "surface":
        outdir = Path(args.output)
        if outdir.exists() and not outdir.is_dir():
            raise DicerError(f"{outdir}: exists and is not a folder; dicer surface writes <material>.stl files "
                             "into the folder given with -o")
        return
    if args.command == "run":
        outdir = Path(args.output)
        for inp in inputs:
            if _same(inp, outdir):
                raise DicerError(f"{outdir}: the output (-o) is the input itself; give a new output folder "
                                 "with -o so the input stays as it is")
        if outdir.is_dir():
            for name in RUN_OUTPUTS:
                target = outdir / name
                if target.is_dir():
                    raise DicerError(f"{target}: is a folder where dicer run writes its {name} file; remove or "
                                     "rename it, or give another output folder with -o")
                for inp in inputs:
                    if _same(inp, target):
                        raise DicerError(f"{target}: the input is one of the files dicer run writes into this "
                                         "folder; give another output folder with -o")
        return
    outputs = [(OUTPUT_OPTIONS[dest], Path(getattr(args, dest))) for dest in OUTPUT_OPTIONS
               if getattr(args, dest, None)]
    for k, (option, out) in enumerate(outputs):
        if out.is_dir():
            raise DicerError(f"{out}: the output ({option}) is an existing folder; give the path of a file "
                             "to write (inside that folder if you meant it)")
        for inp in inputs:
            if _same(inp, out):
                raise DicerError(f"{out}: the output ({option}) is the input file itself; write to a new file "
                                 "so the input stays as it is")
        for other_option, other in outputs[:k]:
            if out.resolve() == other.resolve():
                raise DicerError(f"{out}: given as the output of both {other_option} and {option}; give each "
                                 "output its own file")


def _stable(report):
    """The report without timings, so report files are the same on every rerun."""
    if isinstance(report, dict):
        return {str(k): _stable(v) for k, v in report.items() if not str(k).endswith("seconds")}
    if isinstance(report, (list, tuple)):
        return [_stable(v) for v in report]
    if hasattr(report, "item"):  # numpy scalars
        return report.item()
    return report


def _write_report(path, report) -> None:
    from dicer.io.atomic import write_bytes_atomic

    if path:
        write_bytes_atomic(path, json.dumps(_stable(report), indent=1, sort_keys=True) + "\n")


# --- stages ---------------------------------------------------------------------------


def _check_labels(labels, path: str, config: dict) -> None:
    """Stop before a stage's work when the config does not name every label of the volume:
    meshing and the exports need a material per label (at most 65535, as a label volume
    holds), and finding that out after the fix or the mesh would waste them."""
    top = int(labels.array.max(initial=0))
    k = len(config["materials"])
    if top > k:
        raise DicerError(f"{path}: label {top} found but the config names only {k} material(s); "
                         f"list one material per label 1..{top} under materials: in the config, or, for a label "
                         "volume made elsewhere (an atlas), map its values with dicer labels first (or dicer run "
                         "--labels)")


def _crop(volume, config: dict, source: str):
    """``volume`` cut to ``image.crop`` (if set), logged; (volume, summary or None)."""
    from dicer.crop import crop_volume

    volume, info = crop_volume(volume, config["image"]["crop"], source)
    if info:
        log.info("crop: %s voxels -> %s (voxels %s to %s, max exclusive)", "x".join(map(str, info["shape_before"])),
                 "x".join(map(str, info["shape"])), info["start"], info["stop"])
    return volume, info


def do_segment(image_path: str, out: Path, config: dict, overlay: Path | None = None, info_path: Path | None = None,
               plot: Path | None = None, plot_if_any: bool = False):
    """The segment stage; ``plot_if_any``: draw the criterion where the method has one, and
    say nothing where it has none (``dicer run``, whose user asked for no plot)."""
    from dicer.config import material_names, stage_kwargs
    from dicer.io.atomic import write_bytes_atomic
    from dicer.io.images import read_image
    from dicer.labels import write_mapped_labels
    from dicer.segment import segment

    with _Stage("segment"):
        image = read_image(image_path, spacing=config["image"]["spacing"],
                           allow_irregular_slices=config["image"]["allow_irregular_slices"])
        image, cropped = _crop(image, config, image_path)
        labels, info = segment(image, **stage_kwargs(config, "segment"), source=image_path)
        if cropped:
            info["crop"] = cropped
        if "padding" in info:
            log.info("segment: %d voxels hold the padding value %g outside the scan's field of view: air for the "
                     "thresholds, background in the labels", info["padding"]["voxels"], info["padding"]["value"])
        for warning in info.get("warnings", []):
            log.warning("segment: %s", warning)
        # a NIfTI scan lends its header: the labels overlay it with exactly its affine
        write_mapped_labels(labels, image_path, out)
        names = list(material_names(config).values())
        if overlay or plot:
            from dicer.io.pictures import save_overlay_png, save_threshold_plot  # matplotlib: 0.3 s to import
        if overlay:
            title = f"{info['method']} thresholds " + ", ".join(f"{n} {t:g}" for n, t in zip(names, info["thresholds"]))
            save_overlay_png(image, labels, overlay, title, len(names), names)
        if plot and info.get("criterion"):
            save_threshold_plot(info, plot)
        elif plot and not plot_if_any:
            log.warning("segment: --plot draws the criterion of the shape-connectivity search; segment.method %s has "
                        "none, so %s is not written", info["method"], plot)
        if info_path:
            # timings go to the log only: the file must be the same on every rerun
            stable = {k: v for k, v in info.items() if not k.endswith("seconds")}
            write_bytes_atomic(info_path, json.dumps(stable, indent=1, sort_keys=True) + "\n")
        fractions = {name: info["classes"][name]["fraction"] for name in names if name in info["classes"]}
        log.info("segment: wrote %s (method %s, thresholds %s, class fractions %s)", out, info["method"],
                 info["thresholds"], json.dumps(fractions))
    return labels


def do_labels(labels_path: str, out: Path, config: dict, materials_path: Path | None = None,
              names_only: bool = False) -> list[dict]:
    """Map a label volume made elsewhere to materials 1..K (config ``labels``); returns the
    materials. ``names_only``: the materials file holds their names, not properties."""
    from dicer.config import stage_kwargs
    from dicer.io.atomic import write_bytes_atomic
    from dicer.io.images import read_labels
    from dicer.labels import map_labels, write_mapped_labels

    with _Stage("labels"):
        labels, _ = _crop(read_labels(labels_path, config["image"]["spacing"]), config, labels_path)
        settings = stage_kwargs(config, "labels")
        if not settings["map"]:  # a 3D Slicer segmentation names its segments: so are its materials
            from dicer.io.images import segment_names
            from dicer.labels import segment_map

            settings["map"] = segment_map(segment_names(labels_path), labels_path)
            if settings["map"]:
                log.info("labels: the segment names of %s name its materials (%s); labels.map replaces them",
                         labels_path, brief_json(settings["map"]))
        mapped, materials, info = map_labels(labels, **settings, source=labels_path)
        if mapped.array.size > 1 and mapped.array.min() > 0:  # a box of solid: its background given a value
            import numpy as np

            values = np.unique(labels.array)
            log.warning("labels: every voxel of %s is a material (values %s), so the model fills the whole image "
                        "box; if the background has a value of its own (a header's scl_inter, an atlas's 'unknown'), "
                        "set labels.drop: [value]", labels_path,
                        brief_names([f"{v:.10g}" if isinstance(v, float) else str(v) for v in values.tolist()]))
        write_mapped_labels(mapped, labels_path, out)
        if materials_path:
            written = [{"name": m["name"]} for m in materials] if names_only else materials
            text = json.dumps({"materials": written, "values": info["values"]}, indent=1, sort_keys=True)
            write_bytes_atomic(materials_path, text + "\n")
        log.info("labels: wrote %s (%d material(s): %s; values %s)", out, len(materials),
                 brief_json(info["voxels"]), brief_json(info["values"]))
    return materials


def _npy_spacing(path, config: dict):
    """image.spacing for a .npy label volume, which carries none (a file with a header keeps
    its own: the stages after labels read dicer's NIfTI files)."""
    return config["image"]["spacing"] if str(path).lower().endswith(".npy") else None


def do_downsample(labels_path: str, out: Path, config: dict):
    from dicer.config import coarsening, stage_kwargs
    from dicer.downsample import downsample
    from dicer.io.images import read_labels
    from dicer.labels import write_mapped_labels

    with _Stage("downsample"):
        settings = stage_kwargs(config, "downsample")
        if settings["voxel_size"] is not None and coarsening(settings["factor"]):
            log.warning("downsample: downsample.voxel_size %s replaces downsample.factor %s, which is not used; give "
                        "one of them", settings["voxel_size"], settings["factor"])
        labels = read_labels(labels_path, _npy_spacing(labels_path, config))
        reduced, info = downsample(labels, **settings, source=labels_path)
        # factor 1 keeps the grid, and then the input's header (exactly its affine)
        write_mapped_labels(reduced, labels_path, out)
        log.info("downsample: wrote %s (%s)", out, json.dumps(info, sort_keys=True))
        changed = {n: v for n, v in info.get("volume_change_percent", {}).items()
                   if abs(v) > DOWNSAMPLE_VOLUME_WARNING}
        if changed:  # thin parts lost to the vote and the opening, or a label outvoted by its neighbours
            rule = ("the most frequent class takes a block its classes fill to downsample.min_fraction"
                    if info["vote"] == "plurality" else
                    "a class filling downsample.min_fraction of a block takes it (first in segment.priority)")
            thin = ("parts thinner than about two coarse voxels are removed" if info["morphology"] else
                    "a part thinner than a coarse voxel keeps only the blocks it fills")
            mend = "" if not info["morphology"] else ", or set downsample.morphology=false to keep thin parts"
            log.warning("downsample: material volume changed by more than %g %% (%s): %s, and %s; lower the factor "
                        "(or voxel_size), or raise downsample.min_fraction toward 0.5 to keep volumes%s",
                        DOWNSAMPLE_VOLUME_WARNING, brief_json({n: f"{v:+.1f} %" for n, v in changed.items()}),
                        rule, thin, mend)
        lost = [n for n, v in info["voxels_before"].items() if v and not info["voxels_after"].get(n)]
        if set(lost) - set(list(changed)[:8]):  # counted in full: the volume warning above names eight
            log.warning("downsample: %d material(s) have no voxels left and no elements in the model: %s; lower the "
                        "factor (or voxel_size)%s", len(lost), brief_names(lost),
                        ", or set downsample.morphology=false for a label volume made elsewhere"
                        if info["morphology"] else "")
        _warn_of_grid_growth(info)
    return reduced


def _warn_of_grid_growth(info: dict) -> None:
    """Warn when the coarse grid reaches beyond the image with material in that layer (a shape
    that is no multiple of the factor, material at the image's far faces: a cut model)."""
    axes = [d for d, grown in enumerate(info.get("material_beyond_image", [])) if grown]
    if not axes:
        return
    shape, factor = info["shape_before"], info["factor"]
    said = ", ".join(f"{'xyz'[d]} by {info['beyond_image_mm'][d]:g} mm ({shape[d]} voxels, factor {factor[d]})"
                     for d in axes)
    fits = {d: [f for f in range(2, shape[d] // 2 + 1) if shape[d] % f == 0][:4] for d in axes}
    hint = "; ".join(f"{'xyz'[d]}: {', '.join(map(str, f)) or 'none'}" for d, f in fits.items())
    log.warning("downsample: the coarse grid reaches beyond the image along %s, and material at the image's far "
                "face grows into it; crop the image to a multiple of the factor (image.crop) or use a factor that "
                "divides the voxel count (%s)", said, hint)


DOWNSAMPLE_VOLUME_WARNING = 20.0
"""Percent change of a material's volume through downsampling above which the stage warns
(a coarse voxel at a surface adds or drops up to a block of fine ones)."""


def do_fix(labels_path: str, out: Path, config: dict, report_path: Path | None = None):
    import numpy as np

    from dicer.config import stage_kwargs
    from dicer.connectivity import fix_stage
    from dicer.image import Volume, enclosed_voids
    from dicer.io.images import read_labels
    from dicer.labels import write_mapped_labels

    with _Stage("fix"):
        labels = read_labels(labels_path, _npy_spacing(labels_path, config))
        _check_labels(labels, labels_path, config)
        settings = stage_kwargs(config, "fix")
        try:
            fixed, report = fix_stage(labels.array, **settings)
        except DicerError as exc:
            raise DicerError(f"{labels_path}: {exc}") from None
        removed = report["islands"]["removed_by_material"]
        if report["islands"]["removed_parts"]:
            log.info("fix: removed %d floating part(s) below %d voxels (%d voxels: %s)",
                     report["islands"]["removed_parts"], settings["min_component_voxels"],
                     report["islands"]["removed_voxels"], brief_json(removed))
        if not fixed.any():
            if not np.any(labels.array):
                raise DicerError(f"{labels_path}: every voxel is 0 (background): there is nothing to fix or mesh; "
                                 "give the label volume of the part (labelled voxels 1 or more)")
            if report["islands"]["removed_parts"]:
                raise DicerError(f"{labels_path}: every part of the model is smaller than fix.min_component_voxels="
                                 f"{settings['min_component_voxels']} (voxels joined by faces, edges or corners, and "
                                 "by faces after the connectivity fixes); lower it (0 keeps every part)")
            raise DicerError(f"{labels_path}: the connectivity fixes left no voxel (a part one voxel thin is "
                             "filled by its neighbours' class in the type C majority rounds); set "
                             "fix.majority_rounds=0 or fix.type_c=false to keep it")
        if report["lost_materials"]:  # the deck would have no element set for them
            log.warning("fix: %d material(s) have no voxels left and no elements in the model: %s (removed as "
                        "floating parts below fix.min_component_voxels=%d, or too small to keep through the "
                        "connectivity fixes: a part of 1-3 voxels inside another material is filled by the type C "
                        "fix); lower fix.min_component_voxels, set fix.type_c=false, or merge them into a neighbour",
                        len(report["lost_materials"]), brief_names(report["lost_materials"]),
                        settings["min_component_voxels"])
        labelled = int(np.count_nonzero(labels.array))
        _warn_of_a_filled_box(labels.array.size, labelled, int(np.count_nonzero(fixed)))
        if report["changed_voxels"] > _REWRITTEN * labelled:  # layers thinner than the fixes keep
            log.warning("fix: changed %d of the %d labelled voxels (%.1f %%): parts and layers about a voxel thin "
                        "are rewritten by the connectivity fixes (the type C rounds fill or thicken them), and the "
                        "model is not the segmentation; %s", report["changed_voxels"], labelled,
                        100.0 * report["changed_voxels"] / labelled, _finer_voxels(config))
        voids, walls = enclosed_voids(fixed)
        report["enclosed_voids"], report["void_wall_faces"] = voids, walls  # for a cohort's decks
        if voids:  # a dropped label may be one: said, and the decks hold their walls apart
            log.info("fix: the model encloses %d void(s) (background with no way out of the image: a dropped "
                     "label, a sinus, a marrow cavity; %d voxel faces of wall); decks with sets hold the faces that "
                     "face them in the set and surface CAVITIES, apart from the outer surface EXTERIOR (a void "
                     "merging fills, about two voxels across, leaves none: the export's cavity_faces says)",
                     voids, walls)
        if not report["converged"] and any(report["remaining"].values()):
            log.warning("fix: stopped at a round cap with %s left; raise fix.max_iterations or "
                        "fix.max_type_c_rounds", report["remaining"])
        _warn_of_fixed_volumes(labels.array, fixed, config, report)
        _warn_of_fixed_shape(report, config)
        # same grid: the input's NIfTI header is kept, so the affine stays exactly the input's
        write_mapped_labels(Volume(fixed, labels.spacing, labels.origin, labels.direction), labels_path, out)
        _write_report(report_path, report)
        log.info("fix: wrote %s (%d voxels changed; type A %s, type B %s, type C %s; A/B sweeps %s; "
                 "Type C rounds %d + %d, sites per round %s)", out, report["changed_voxels"], brief_json(report["type_a"]),
                 brief_json(report["type_b"]), brief_json(report["type_c"]), report["iterations"], report["majority_rounds"],
                 report["type_c_rounds"], report["type_c_sites"])
    return fixed


_REWRITTEN = 0.1
"""A fix that changes more than this share of the labelled voxels is said of as a whole (a 96³
volume of 100 shells under a voxel thick: 99.5 %, each material's change said apart only)."""


def _warn_of_fixed_volumes(before: np.ndarray, after: np.ndarray, config: dict, report: dict) -> None:
    """Warn when the connectivity fixes changed a material's voxels by more than
    STAGE_VOLUME_WARNING percent, naming the fixes that did (``report``: the fix's)."""
    from dicer.config import material_names
    from dicer.image import count_labels

    names = material_names(config)
    k = max(len(names), int(before.max(initial=0)), int(after.max(initial=0))) + 1
    was, now = count_labels(before, k), count_labels(after, k)
    percent = {str(c): round(100.0 * (int(now[c]) - int(was[c])) / int(was[c]), 2) for c in range(1, k) if was[c]}
    said = _volume_changes("fix", percent, [names.get(c, f"label_{c}") for c in range(1, k)])
    if said is None:
        return
    removed = report.get("islands", {}).get("removed_by_material", {})
    causes = []
    for c, change in percent.items():
        if abs(change) <= STAGE_VOLUME_WARNING:
            continue
        name = names.get(int(c), f"label_{c}")
        if change > 0:
            by_c = report["type_c"].get(name, 0)
            causes.append("c_raise" if by_c >= report["type_a"].get(name, 0) + report["type_b"].get(name, 0)
                          else "ab")
        else:  # most of the loss in floating parts removed, or taken by the neighbours' class
            lost = int(was[int(c)]) - int(now[int(c)])
            causes.append("islands" if 2 * removed.get(name, 0) >= lost else "majority")
    hints = {
        "c_raise": ("the raise-only type C rounds thicken parts one voxel thin (a plate doubles): "
                    f"{_finer_voxels(config)}, so that thin parts are two voxels thick"),
        "ab": ("the type A and B fixes added voxels where parts touched along an edge or at a corner only (a "
               "solid model needs face contacts); a finer segmentation has fewer such contacts"),
        "majority": ("the type C majority rounds fill parts one voxel thin with their neighbours' class and small "
                     "parts are removed: set fix.majority_rounds=0 (raise-only rounds) or lower "
                     "fix.min_component_voxels to keep them"),
        "islands": (f"floating parts smaller than fix.min_component_voxels="
                    f"{report.get('islands', {}).get('min_component_voxels', 0)} were removed: lower it to keep them"),
    }
    log.warning("%s; %s", said, "; ".join(hints[c] for c in dict.fromkeys(causes)))


def _finer_voxels(config: dict) -> str:
    """The advice for parts one voxel thin: less downsampling, or (at the scan's own voxels) a finer scan."""
    from dicer.config import downsample_applies

    if downsample_applies(config):
        return "segment more finely or lower downsample.factor (or downsample.voxel_size)"
    return "a scan of finer voxels keeps them (or less downsampling, where these labels were downsampled)"


def _warn_of_a_filled_box(voxels: int, before: int, after: int) -> None:
    """Warn when the fixes leave less than 1 % of the image background where the labels had
    more: a class of scattered voxels (noise segmented as tissue: 2.8 % background, then 0.4 %)
    is filled into a box of solid."""
    from dicer.segment import WHOLE_BOX

    if voxels and (voxels - after) < WHOLE_BOX * voxels <= voxels - before:
        log.warning("fix: after the connectivity fixes %.2f %% of the image is background (%.2f %% before): the model "
                    "fills the image box; the fixes fill the gaps of a class of scattered voxels (noise taken for "
                    "tissue, or a scan whose values the thresholds do not fit): check the labels (segmentation.png "
                    "of a scan) and the thresholds", 100.0 * (voxels - after) / voxels,
                    100.0 * (voxels - before) / voxels)


def _warn_of_fixed_shape(report: dict, config: dict) -> None:
    """Warn when the connectivity fixes grew the model into the background by more than
    STAGE_VOLUME_WARNING percent, made it reach faces of the image it did not reach, or
    joined separate parts (a gap one voxel wide filled)."""
    solid = report["solid_voxels"]
    grown = 100.0 * (solid["after"] - solid["before"]) / solid["before"] if solid["before"] else 0.0
    faces = report["faces_reached"]
    if grown > STAGE_VOLUME_WARNING or faces:
        reach = (f", and it now reaches the image's faces {', '.join(faces)} (the deck's node sets of those names "
                 "hold the grown material)" if faces else "")
        log.warning("fix: the model grew by %.1f %% into the background%s: the raise-only type C rounds thicken "
                    "every part one voxel thin, so a layer or shell one voxel thick doubles; %s, so that layers are "
                    "two voxels thick", grown, reach, _finer_voxels(config))
    if report["joined_parts"]:
        log.warning("fix: %d separate part(s) of the labels were joined to others: they touched only at an edge or "
                    "a corner, or a gap one voxel wide between them was filled (type C), so they are one body in the "
                    "model and carry load across it; to keep them apart the gap must be two voxels wide everywhere "
                    "(segment more finely, lower downsample.factor) or hold a material of its own (labels.map)",
                    report["joined_parts"])


class _InputError(DicerError):
    """A stage's error about another input than the mesh (it names that file)."""


def _now(job) -> None:
    job()


def _mesh_to_mesh(stage: str, func, mesh_path: str, out: Path, report_path: Path | None, mesh=None,
                  mapped: bool = False, write=_now):
    """Read a mesh (unless the caller has it: ``mesh``, what the file at ``mesh_path`` holds),
    apply ``func(mesh) -> (mesh, report)``, write the mesh (checked) and report. ``mapped``:
    ``func`` only reads the mesh, so its arrays may stay in the page cache (read-only views).
    ``write(job)`` runs the mesh file's writing (dicer run: beside the next stage)."""
    from dicer.io.meshes import read_mesh, write_mesh

    with _Stage(stage):
        mesh = read_mesh(mesh_path, mapped=mapped) if mesh is None else mesh
        try:
            result, report = func(mesh)
        except _InputError as exc:  # names its own file
            raise DicerError(str(exc)) from None
        except DicerError as exc:
            raise DicerError(f"{mesh_path}: {exc}") from None
        result.names = list(mesh.names)  # the stages move nodes and elements, not materials
        result.direction = mesh.direction  # nor the image's orientation (applied on export)
        write(lambda: write_mesh(result, out))
        _write_report(report_path, report)
    return result, report


def do_merge(mesh_path: str, out: Path, config: dict, report_path: Path | None = None, mesh=None, write=_now):
    from dicer.config import stage_kwargs
    from dicer.mesh.merge import merge_mesh

    settings = stage_kwargs(config, "merge")

    def advised(exc: DicerError) -> DicerError:
        floor = settings.get("min_scaled_jacobian", 0.3)
        if settings.get("method") != "planes" or floor > 0 or "degenerate or inverted" not in str(exc):
            return exc
        return DicerError(f"{exc}: merge.min_scaled_jacobian={floor:g} let merging make flat or inverted corners, "
                          "which no later stage or solver takes; give a value above 0 (default 0.3)")

    def write_advised(job):  # the file's check may run beside the next stage: its error gets the advice too
        def checked():
            try:
                job()
            except DicerError as exc:
                raise advised(exc) from None
        write(checked)

    # both methods build a new mesh and only read the input (a copy of 0.9 GB at 256^3
    # cost more than coarsening it)
    try:
        merged, report = _mesh_to_mesh("merge", lambda m: merge_mesh(m, **settings), mesh_path, out, report_path,
                                       mesh, mapped=True, write=write_advised)
    except DicerError as exc:
        raise advised(exc) from None
    smoothing = stage_kwargs(config, "smooth")
    _warn_of_volume_change(report, merged, settings,
                           smoothing["label_surface_radius"] if smoothing["surface_from_labels"] else None)
    _warn_of_flat_templates(report, merged)
    if report.get("method") == "templates" and report["elements_after"] >= report["elements_before"]:
        _warn_of_no_coarsening(report, settings["templates"], merged)
    log.info("merge: wrote %s (%d -> %d elements, %d -> %d nodes; volume %s)", out,
             report["elements_before"], report["elements_after"], report["nodes_before"],
             report["nodes_after"], brief_json(_stable(report["volume"])))  # materials in label order
    return merged


def _warn_of_no_coarsening(report: dict, templates: dict, merged) -> None:
    """Say why the transition templates made no fewer elements, by the settings that kept the
    voxels (levels 0, keep_fine naming every material, min_distance) or else the model's size."""
    import numpy as np

    counts = (report["elements_before"], report["elements_after"], report["min_scaled_jacobian"])
    if int(templates["levels"]) == 0:
        log.info("merge: merge.templates.levels is 0: the voxel mesh is kept")
        return
    materials = {int(m) for m in np.unique(merged.material)} if merged.n_cells else set()
    if materials and materials <= {int(m) for m in templates["keep_fine"]}:
        why = ("merge.templates.keep_fine lists every material of the model, so none may coarsen; leave out of it "
               "the materials that may")
    else:
        why = (f"the model is too small or its parts too thin for a coarser level with "
               f"merge.templates.min_distance={int(templates['min_distance'])} voxels of one material around a cell, "
               "and the transitions only worsen the shapes; lower min_distance, use merge.method: planes, or "
               "merge.templates.levels: 0 to keep the voxel mesh")
    log.warning("merge: the transition templates made no fewer elements (%d -> %d; min scaled Jacobian %.3f): %s",
                *counts, why)


SMOOTH_BACKOFF_WARNING = 0.25
"""Share of the boundary nodes whose smoothing the quality guard backed off above which the
smooth stage warns (the head CT at defaults: 171 of 397,774)."""

STAGE_VOLUME_WARNING = 5.0
"""Percent change of a material's volume through merging or smoothing above which the stage warns."""

SLOPED_SAMPLES_WARNING = 0.01
"""Share of the labels' fit samples on a merged mesh's slopes (chamfers), without the labels
themselves, above which the smooth stage warns (the head CT's merged mesh: 0.3 %, a merged
ball of radius 16 voxels: 55 %)."""

PLACED_SHARE_WARNING = 0.5
"""Share of the labels' faces the scan places (``smooth.fit_to_scan``) under which it is said
not to look like theirs: measured 0.69-1.0 on scans with their own segmentations (CT, MR,
cropped, downsampled, the head CT 0.93), 0.24-0.27 with another scan on the same grid."""


def _volume_changes(stage: str, percent: dict, material_names: list) -> str | None:
    """"name +x.x %" of the materials (label strings in ``percent``; names of labels 1, 2, ...
    in ``material_names``) whose volume the stage changed by more than STAGE_VOLUME_WARNING
    percent, or None."""
    names = {str(i): n for i, n in enumerate(material_names, start=1)}
    big = [(k, v) for k, v in percent.items() if abs(v) > STAGE_VOLUME_WARNING]
    if not big:
        return None
    text = ", ".join(f"{names.get(k, k)} {v:+.1f} %" for k, v in big[:8])
    return f"{stage}: material volume changed by more than {STAGE_VOLUME_WARNING:g} % ({text}" + (
        f" and {len(big) - 8} more)" if len(big) > 8 else ")")


def _in_plane_passes(spacing, passes) -> tuple[list[int], bool]:
    """``merge.passes`` with 0 across the coarse axes (voxels twice the finest or longer), and
    whether there are such axes."""
    spacing = [float(v) for v in spacing]
    coarse = [v >= 2 * min(spacing) for v in spacing]
    return [0 if c else int(p) for c, p in zip(coarse, list(passes) + [0] * 3)], any(coarse)


def _warn_of_volume_change(report: dict, mesh, settings: dict, fit_radius: float | None = None) -> None:
    """Warn when merging changed a material's volume by more than STAGE_VOLUME_WARNING percent:
    chamfers fill whole voxel steps, and across a coarse axis of anisotropic voxels (thick
    slices) a step is several times the in-plane size. ``fit_radius``: the smoothing fits the
    labels (smooth.surface_from_labels, its window in voxels of the finest axis), which takes the
    chamfers back where its window reaches across a voxel: said at INFO then, its own warning
    naming what it left."""
    import numpy as np

    said = _volume_changes("merge", {k: v["change_percent"] for k, v in report.get("volume", {}).items()},
                           mesh.names)
    if said is None:
        return
    spacing = np.asarray(mesh.spacing[:mesh.dim], float)
    passes, coarse = _in_plane_passes(spacing, settings.get("passes", (1, 1, 1)))
    hint = "set merge.passes to 0 for the axes that must keep their surface, or merge.min_thickness"
    if coarse and settings.get("method") == "planes":
        hint = (f"the voxels are {' x '.join(f'{v:g}' for v in spacing)} mm: merging across the coarse axis fills "
                f"steps of a whole slice; set merge.passes={passes} to merge in-plane only")
    if fit_radius is None:
        log.warning("%s; %s", said, hint)
    elif coarse:  # the fit's window, in units of the finest voxel, is short of a thick slice
        log.warning("%s; %s: the smoothing's fit to the labels takes back little of it, its window "
                    "(smooth.label_surface_radius %g x %g mm) being shorter than the %g mm voxels", said, hint,
                    fit_radius, spacing.min(), spacing.max())
    else:  # a 1 mm ball +9 to +12 % here, within 2.4 % of its labels after the smoothing
        log.info("%s, as merging's slopes (chamfers) fill voxel steps; the smoothing's fit to the labels takes the "
                 "surface back to theirs (smooth.surface_from_labels, as dicer run and dicer smooth --labels do) and "
                 "warns of what it leaves", said)


def _warn_of_flat_templates(report: dict, mesh) -> None:
    """Warn when graded elements fall below the templates' floor: it holds on the lattice,
    and voxels longer along one axis stretch the templates' slopes."""
    from dicer.mesh.coarsen import TEMPLATE_FLOOR

    if report.get("method") != "templates" or report["min_scaled_jacobian"] >= TEMPLATE_FLOOR:
        return
    spacing = " x ".join(f"{float(v):g}" for v in mesh.spacing[:mesh.dim])
    log.warning("merge: on %s mm voxels the transition templates reach a scaled Jacobian of %.3f, below the "
                "%g they keep on cubic voxels; use merge.method: planes, or voxels nearer cubic (downsample "
                "with a factor per axis)", spacing, report["min_scaled_jacobian"], TEMPLATE_FLOOR)


def _read_thresholds(path: str | None, config: dict, image_path: str) -> list:
    """The thresholds segmentation chose: from its info file (dicer segment --info), or
    the config's manual segment.thresholds."""
    if path is None:
        if config["segment"]["method"] == "manual" and config["segment"]["thresholds"]:
            return config["segment"]["thresholds"]
        raise DicerError(f"{image_path}: --image needs the thresholds segmentation chose; give --thresholds "
                         "segmentation.json (written by dicer segment --info)")
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DicerError(f"{path}: thresholds file not found; write it with dicer segment --info") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DicerError(f"{path}: cannot read the thresholds ({exc}); write it again with dicer segment --info") \
            from None
    thresholds = data.get("thresholds") if isinstance(data, dict) else None
    if not isinstance(thresholds, list):
        raise DicerError(f"{path}: no thresholds list in the file; give the segmentation.json of dicer segment --info")
    return thresholds


def _warn_of_short_pull(report: dict, settings: dict) -> None:
    """Warn when under half the boundary nodes between two materials reach the surface they were
    pulled onto (the scan's iso-surface, or the fit of the labels' staircase), naming the
    likeliest cause: a coefficient of 0, too few samples for the fit, small parts or the guard."""
    if "surface_from_image" in report:
        pull = report["surface_from_image"]
        on = pull["nodes_on_the_image_surface"]
        what = ("reach the scan's iso-surface, the others stop short of it (the quality guard held them back, or the "
                f"scan shows no edge near them); smooth.image_sigma={pull['image_sigma']:g} may blur the edges away"
                + (" (default 0.5)" if pull["image_sigma"] != 0.5 else "")
                + ", or the thresholds do not match the scan (--thresholds)")
    elif "surface_from_labels" in report:
        pull = report["surface_from_labels"]
        on = pull["nodes_on_the_fitted_surface"]
        radius = f"smooth.label_surface_radius={pull['label_surface_radius']:g}"
        what = "reach the surface fitted to the labels (smooth.surface_from_labels), the others stay where the labels' "
        if settings.get("coefficient") == 0 or (report.get("coefficients")
                                                  and not any(report["coefficients"].values())):
            what += ("smoothing put them: a coefficient of 0 (smooth.coefficient or smooth.coefficients) holds every "
                     "boundary node where it is")
        elif pull["nodes_moved"] < 0.5 * pull["nodes_between_two_kinds"]:
            what += (f"smoothing put them: only {pull['nodes_moved']} had samples enough for a fit within {radius} "
                     "voxels (three per coefficient of the quadric; fewer lie in the window on elongated voxels or in "
                     f"2D): a larger smooth.label_surface_radius (more than {pull['label_surface_radius']:g}) fits "
                     "them")
        else:
            what += (f"smoothing put them (parts too small for a fit within {radius} voxels, or the quality guard held "
                     "them back); a smaller smooth.label_surface_radius fits smaller parts")
    else:
        return
    if on < 0.5 * pull["nodes_between_two_kinds"]:
        log.warning("smooth: %d of the %d boundary nodes between two materials %s", on, pull["nodes_between_two_kinds"],
                    what)


def _shared_lattice_points(lattice) -> int:
    """How many of the (N, 3) lattice points repeat one before them: one integer key per point,
    sorted by radix (0.04 s on the head CT's 2.4 M nodes, where np.unique of the keys took 2 s)."""
    import numpy as np

    lattice = np.asarray(lattice, np.int64)
    if lattice.shape[0] < 2:
        return 0
    lattice = lattice - lattice.min(axis=0)
    keys = np.sort(np.ravel_multi_index(lattice.T, lattice.max(axis=0) + 1), kind="stable")
    return int(np.count_nonzero(keys[1:] == keys[:-1]))


def do_smooth(mesh_path: str, out: Path, config: dict, report_path: Path | None = None,
              image_path: str | None = None, thresholds_path: str | None = None, mesh=None, write=_now,
              labels_path: str | None = None):
    from dicer.config import places_faces_by_scan, stage_kwargs
    from dicer.mesh.model import is_graded
    from dicer.mesh.smooth import smooth_mesh

    settings = stage_kwargs(config, "smooth")
    image = thresholds = None
    # the labels' staircase before merging, for the fit (smooth.surface_from_labels) unless a
    # scan's iso-surfaces place the surface
    fits_labels = settings["surface_from_labels"] and not (image_path is not None and settings["surface_from_image"])
    labels = None
    if not fits_labels:
        labels_path = None
    elif labels_path is not None:
        from dicer.io.images import read_labels

        labels = read_labels(labels_path, _npy_spacing(labels_path, config))
    if image_path is None and settings["surface_from_image"]:
        log.warning("smooth: smooth.surface_from_image is set, but there is no scan to take the surface from (a label "
                    "volume input, or dicer smooth without --image): the surface is smoothed from the labels alone")
    # the scan: for its surface, or to place the labels' faces for the fit
    fit_to_scan = fits_labels and places_faces_by_scan(settings) and labels is not None
    if image_path is not None and (settings["surface_from_image"] or fit_to_scan):
        from dicer.io.images import read_image

        thresholds = _read_thresholds(thresholds_path, config, image_path)
        image = read_image(image_path, spacing=config["image"]["spacing"],
                           allow_irregular_slices=config["image"]["allow_irregular_slices"])
        from dicer.crop import crop_volume

        # the mesh's lattice starts at the crop's first voxel: the scan is cut as segment cut it
        image, _ = crop_volume(image, config["image"]["crop"], image_path)

    def run(m):
        if m is not mesh:  # read from a file: a mesh dicer run hands on is never smoothed yet
            from dicer.mesh.model import nodes_off_lattice

            # the layer's nodes are copies of the surface's, at their lattice points (a graded
            # mesh's templates place nodes between lattice points, at shared rounded ones)
            shared = 0 if is_graded(m) else _shared_lattice_points(m.lattice)
            if shared:
                raise _InputError(f"{mesh_path}: {shared} of the mesh's {m.n_points} nodes share a lattice point "
                                  "with another (a pillow layer's copies: it was smoothed with smooth.pillow); "
                                  "smooth the mesh of dicer mesh or dicer merge")
            moved = nodes_off_lattice(m)
            if moved:
                log.warning("smooth: %d of the mesh's %d nodes lie off their lattice points already: it was smoothed "
                            "before, and smoothing it again shrinks it further; smooth the mesh of dicer mesh or "
                            "dicer merge", moved, m.n_points)
        try:
            return smooth_mesh(m, **settings, image=image, thresholds=thresholds, image_source=image_path or "image",
                               labels=labels, labels_source=labels_path or "the labels")
        except DicerError as exc:
            text = str(exc)
            if any(source and text.startswith(source) for source in (image_path, thresholds_path, labels_path)):
                raise _InputError(text) from None
            raise

    # smoothing only reads its input mesh (new points; cells and data shared)
    smoothed, report = _mesh_to_mesh("smooth", run, mesh_path, out, report_path, mesh, mapped=True, write=write)
    log.info("smooth: wrote %s (%s)", out, json.dumps(_stable(report), sort_keys=True)[:600])
    fit = report.get("surface_from_labels", {})
    if labels is None and fit.get("samples_on_sloped_faces", 0) > SLOPED_SAMPLES_WARNING * fit.get("samples", 0):
        sloped = fit["samples_on_sloped_faces"]  # fitted to a merged mesh's faces, many of them chamfers
        log.warning("smooth: %d of the fit's %d samples lie on merging's slopes (chamfers), which stand off the "
                    "labels' surface: give --labels with the label volume the mesh was made from "
                    "(labels_fixed.nii.gz), as dicer run does", sloped, fit["samples"])
    share = fit.get("share_of_faces_placed_by_the_scan")
    if share is not None and share < PLACED_SHARE_WARNING:  # measured 0.69-1.0 with the labels' own scan
        log.warning("smooth: the scan crosses its thresholds between the voxels of only %.0f %% of the labels' faces "
                    "(the scan the labels were segmented from: 69-100 %% measured), so it may not be theirs; the "
                    "others stay where the labels put them: check %s and the thresholds, or set smooth.fit_to_scan: "
                    "false", 100 * share, image_path)
    # against the labels where the fit had them: a merge's chamfers, which the fit takes back, count
    from_labels = "volume_change_from_labels_by_material" in report
    said = _volume_changes("smooth", {k: 100 * v for k, v in report.get(
        "volume_change_from_labels_by_material" if from_labels else "volume_change_by_material", {}).items()},
        smoothed.names)
    grew = any(v > 0 for v in report.get("volume_change_from_labels_by_material", {}).values()
               if abs(v) > STAGE_VOLUME_WARNING / 100)  # the fit alone shrinks small parts; the scan can grow one
    if said and from_labels and fit.get("samples_placed_by_the_scan") and grew:  # the scan moved the fitted surface
        log.warning("%s from the labels' voxels; the labels' faces placed by the scan (smooth.fit_to_scan) move the "
                    "surface to the scan's iso-surfaces where they lie away from the labels' (a threshold low in a "
                    "thin part's edge puts its surface outside it; the segmentation's clean-up; smooth.image_sigma %g "
                    "blurring thin parts): check the thresholds and smooth.image_sigma, or set smooth.fit_to_scan: "
                    "false to follow the labels", said, settings["image_sigma"])
    elif said and from_labels and fit.get("samples_placed_by_the_scan"):  # shrank: the scan, or the fit
        log.warning("%s from the labels' voxels; the labels' faces placed by the scan (smooth.fit_to_scan) take the "
                    "surface in to the scan's iso-surfaces where the labels lie outside them (parts that downsampling "
                    "or the segmentation's clean-up enlarged), and parts a few voxels across shrink in the fit: set "
                    "smooth.fit_to_scan: false to follow the labels, or lower smooth.label_surface_radius", said)
    elif said and from_labels and grew:  # merging's chamfers left where the fit's window held too few samples
        spacing = [float(v) for v in smoothed.spacing[:smoothed.dim]]
        passes, coarse = _in_plane_passes(spacing, config["merge"]["passes"])
        how = (f"on {' x '.join(f'{v:g}' for v in spacing)} mm voxels merge in-plane only (merge.passes={passes}), "
               "or merge less (merge.min_thickness)" if coarse else
               "merge less (merge.passes, merge.min_thickness), or raise smooth.label_surface_radius")
        log.warning("%s from the labels' voxels; the fit to the labels left what merging's slopes (chamfers) added "
                    "where its window (smooth.label_surface_radius voxels of the finest axis) held too few samples: "
                    "%s", said, how)
    elif said and from_labels:  # parts too small for the fit, or held back by the quality guard
        log.warning("%s from the labels' voxels; parts a few voxels across shrink most (the fit needs "
                    "smooth.label_surface_radius voxels of surface): lower smooth.coefficient or "
                    "smooth.label_surface_radius, or merge less (merge.passes, merge.min_thickness)", said)
    elif said and "surface_from_image" in report:  # the scan's iso-surface, not the labels', set the surface
        where = Path(thresholds_path).name if thresholds_path else "segment.thresholds"  # dicer run: a staged file
        log.warning("%s; the surface went onto the scan's iso-surfaces (smooth.surface_from_image) at the "
                    "thresholds %s (%s), so the volume follows the scan where they lie away from the labels' "
                    "surface (the segmentation's clean-up, thresholds other than the segmentation's, or "
                    "smooth.image_sigma %g blurring thin parts): check the thresholds and smooth.image_sigma, or "
                    "set smooth.surface_from_image: false to smooth from the labels alone",
                    said, ", ".join(f"{float(t):g}" for t in thresholds), where, settings["image_sigma"])
    elif said:  # a part a few voxels across loses its corners: a large share of it
        log.warning("%s; parts a few voxels across (after merging: a few merged elements) shrink most: lower "
                    "smooth.coefficient, or merge less (merge.passes, merge.min_thickness)", said)
    backed, nodes = report["backed_off_nodes"], report["boundary_nodes"]
    if backed > SMOOTH_BACKOFF_WARNING * nodes:  # the guard undid much of the smoothing: a near-staircase model
        log.warning("smooth: the quality guard backed off %d of the %d boundary nodes (%.0f %%; mean boundary move "
                    "%.3g mm) to keep smooth.min_scaled_jacobian=%g: the surface there stays near the voxel staircase; "
                    "lower smooth.min_scaled_jacobian (default 0.3)", backed, nodes, 100.0 * backed / nodes,
                    report["mean_boundary_displacement_mm"], settings["min_scaled_jacobian"])
    if report.get("frozen_rounds"):
        log.warning("smooth: %d back-off rounds did not keep smooth.min_scaled_jacobian=%g; %d more kept %d boundary "
                    "nodes around the failing elements where they were (the voxel staircase there): lower "
                    "smooth.min_scaled_jacobian or raise smooth.max_backoff_rounds to smooth them",
                    report["backoff_rounds"], settings["min_scaled_jacobian"], report["frozen_rounds"],
                    report["frozen_nodes"])
    _warn_of_short_pull(report, settings)
    under = report["min_scaled_jacobian"] < settings["min_scaled_jacobian"] - 1e-6 and not report["inverted_elements"]
    if under and is_graded(smoothed):  # merge.min_scaled_jacobian is plane merging's: the templates keep their shapes
        log.warning("smooth: the smallest scaled Jacobian is %.3f, under smooth.min_scaled_jacobian=%g: the "
                    "transition templates of graded coarsening (merge.method: templates) in %s keep the shapes they "
                    "have on the lattice (0.23 at worst, less on elongated voxels), and their nodes are held; plane "
                    "merging (merge.method: planes) keeps the floor", report["min_scaled_jacobian"],
                    settings["min_scaled_jacobian"], Path(mesh_path).name)
    elif under:  # the guard keeps elements that came in below its floor no worse; it does not raise them
        log.warning("smooth: the smallest scaled Jacobian is %.3f, under smooth.min_scaled_jacobian=%g: elements "
                    "already under it in %s (merging's floor is merge.min_scaled_jacobian) are kept no worse, "
                    "not raised; set merge.min_scaled_jacobian=%g too to keep every element at the floor",
                    report["min_scaled_jacobian"], settings["min_scaled_jacobian"], Path(mesh_path).name,
                    settings["min_scaled_jacobian"])
    layer = report.get("pillow")
    # the faces at fixed bounding planes go without the layer by design: not counted against it
    faces = layer["elements_added"] + layer["faces_without_layer"] - layer.get("faces_at_fixed_planes", 0) \
        if layer else 0
    if faces and layer["elements_added"] < 0.5 * faces:  # asked for, and mostly not made
        sizes = [float(v) for v in smoothed.spacing[:smoothed.dim]]
        if max(sizes) >= LONG_VOXELS * min(sizes):  # 0.1-0.75 voxel cover 16-31 % on 5:1 voxels (measured)
            fix = ("); the voxels are %s mm, on which a layer of any thickness keeps the floor on few faces (now "
                   "smooth.pillow_thickness=%%g): a downsample.factor per axis makes them nearer cubic"
                   % " x ".join(f"{v:g}" for v in sizes))
        elif layer["thickness_voxels"] < 0.25:  # under the default: thinner layers stretch under merged faces
            fix = (", or would be over 20 times longer than thick under long merged faces); raise smooth.pillow_thickness "
                   "(now %g) or lower smooth.min_scaled_jacobian")
        else:
            fix = "); lower smooth.pillow_thickness (now %g) or smooth.min_scaled_jacobian"
        log.warning("smooth: the pillow layer covers %d of the %d exterior faces it could cover (the others could not "
                    "keep smooth.min_scaled_jacobian with it" + fix, layer["elements_added"], faces,
                    layer["thickness_voxels"])
    return smoothed


def do_mesh(labels_path: str, out: Path, config: dict, write=_now):
    from dicer.config import stage_kwargs
    from dicer.io.images import read_labels
    from dicer.io.meshes import write_mesh
    from dicer.mesh.voxel import mesh_labels

    with _Stage("mesh"):
        labels = read_labels(labels_path, _npy_spacing(labels_path, config))
        _check_labels(labels, labels_path, config)
        if labels.array.ndim == 2 and labels.direction is not None and config["mesh"]["coordinates"] == "scanner":
            log.warning("mesh: the 2D image's direction cosines (%s) are not applied: a 2D model lies in the "
                        "image's index frame, flipped or turned against the scanner's axes as they are "
                        "(docs/coordinates.md)", " ".join(f"{v:g}" for v in labels.direction))
        _warn_of_long_voxels(labels.spacing, labels.array.shape)
        try:
            mesh = mesh_labels(labels, **stage_kwargs(config, "mesh"))
        except DicerError as exc:
            raise DicerError(f"{labels_path}: {exc}") from None
        write(lambda: write_mesh(mesh, out))
        log.info("mesh: wrote %s (%d nodes, %d elements)", out, mesh.n_points, mesh.n_cells)
    return mesh


LONG_VOXELS = 3.0
"""A voxel this many times longer along one axis than along another makes elements a solver
reads poorly (thick clinical slices); the mesh stage says so before it makes them."""


def _warn_of_long_voxels(spacing, shape) -> None:
    """Warn of voxels LONG_VOXELS or more times longer along one axis, with a factor per axis that evens them
    (at most half the axis's voxels: a coarser grid keeps two)."""
    sizes = [float(v) for v in spacing]
    if max(sizes) < LONG_VOXELS * min(sizes):
        return
    even = [max(1, min(int(round(max(sizes) / v)), n // 2)) if v < max(sizes) / 1.5 else 1
            for v, n in zip(sizes, shape)]
    long_axes = [1 if v >= max(sizes) / 1.5 else 0 for v in sizes]
    log.warning("mesh: the voxels are %s mm, %.0f times longer along one axis: every element is as long; a "
                "downsample.factor per axis up to %s makes them nearer cubic (the larger, the more thin parts the "
                "coarser grid loses), and merge.passes %s keeps merging off the long axis",
                " x ".join(f"{v:g}" for v in sizes), max(sizes) / min(sizes), even, [0 if a else 1 for a in long_axes])


def do_export(mesh_path: str, out: Path, config: dict, mesh=None, neighbours=None, materials_path: str | None = None,
              quadratic=None):
    from dicer.config import stage_kwargs
    from dicer.export import export_mesh
    from dicer.io.meshes import read_mesh, refuse_inverted

    with _Stage("export"):
        # the export only reads the mesh: its arrays stay in the page cache, mapped, not copied
        if mesh is None:  # (a mesh handed on by dicer run was checked by the stage that made it)
            mesh = read_mesh(mesh_path, mapped=True)
            refuse_inverted(mesh, mesh_path)
        _check_materials_file("export", materials_path, mesh, mesh_path, config)
        named = [m["name"] for m in config["materials"]]
        if any(a != b for a, b in zip(mesh.names, named)):  # properties go by material number: the mesh's own names say which were meant
            given = materials_path or "the config"
            fix = (f"unless {materials_path} was written with this mesh's labels (by the dicer run or dicer labels "
                   "that made them) and the mesh without it, the deck's materials are another model's: give that "
                   "materials.json" if materials_path else
                   "give --materials materials.json (written by dicer labels / dicer run --labels) or a config with "
                   "these materials")
            log.warning("export: the mesh names its materials %s, %s %s; the deck takes %s's names and properties "
                        "by material number; %s", brief_names(mesh.names), given,
                        brief_names(named[:len(mesh.names)]), given, fix)
        info = export_mesh(mesh, out, **stage_kwargs(config, "export"), source=mesh_path, neighbours=neighbours,
                           quadratic=quadratic)
        # the summary's keys sorted, its materials in label order
        log.info("export: wrote %s (%s)", out, brief_json(dict(sorted(info.items())), whole_top=True))


def _check_materials_file(stage: str, path: str | None, mesh, mesh_path: str, config: dict) -> None:
    """Refuse a --materials file that lists fewer materials than the mesh's labels run to;
    warn where a mesh that carries its own names is read with another file's (quality and
    surface take the mesh's names, export the file's properties by material number), and
    where quality reads it with the config's other names (its time step takes their properties)."""
    if not mesh.n_cells or not (path or stage == "quality"):
        return
    listed = [m["name"] for m in config["materials"]]
    top = int(mesh.material.max(initial=0))
    if path and len(listed) < top:
        raise DicerError(f"{path}: lists {len(listed)} material(s) but {mesh_path} has material labels 1..{top}; "
                         "give the materials.json written with this mesh's labels (dicer labels --materials, "
                         "or the run's own)")
    if stage != "export" and mesh.names and any(a != b for a, b in zip(mesh.names, listed)):
        # the report's explicit time step takes the properties by material number, as the decks do
        what = ("report takes the mesh's names, and its explicit time step the properties of "
                f"{brief_names(listed[:len(mesh.names)])} by material number, as the decks do"
                if stage == "quality" else "surfaces take the mesh's names")
        log.warning("%s: the mesh names its materials %s, %s %s; the %s (give the materials.json written with "
                    "this mesh's labels%s)", stage, brief_names(mesh.names), path or "the config",
                    brief_names(listed[:len(mesh.names)]), what, ", or a config with these materials" if not path else "")


def _mesh_names(mesh, config: dict) -> list[str]:
    """The material names a mesh file carries (what its materials were called when it was
    made: the config's then, or a label volume's materials.json), else the config's."""
    names = list(mesh.names or ())
    top = int(mesh.material.max(initial=0)) if mesh.n_cells else 0
    return names if names and len(names) >= top else [m["name"] for m in config["materials"]]


def do_surface(mesh_path: str, outdir: Path, config: dict, only: list[str] | None = None,
               materials_path: str | None = None) -> dict:
    from dicer.export.stl import write_surfaces
    from dicer.io.meshes import read_mesh, refuse_inverted

    with _Stage("surface"):
        mesh = read_mesh(mesh_path)
        refuse_inverted(mesh, mesh_path)
        _check_materials_file("surface", materials_path, mesh, mesh_path, config)
        info = write_surfaces(mesh, outdir, _mesh_names(mesh, config), only)
        written = {v["file"] for v in info.values()}
        others = sorted(p.name for p in outdir.glob("*.stl") if p.name not in written and not p.name.startswith("."))
        if others:  # another mesh's surfaces beside these would be read as this model's
            log.warning("surface: %s also holds %d .stl file(s) this mesh did not write (%s): another mesh's or "
                        "material's; remove them, or write into an empty folder", outdir, len(others),
                        brief_names(others))
        log.info("surface: wrote %s", ", ".join(f"{outdir / v['file']} ({v['triangles']} triangles, "
                                                 f"{v['volume_mm3']:.6g} mm^3)" for v in info.values()))
    return info


def _check_original(original, path: str, mesh) -> None:
    """Refuse an original segmentation that is not the one the mesh's labels came from: its
    extent or place differs by more than a voxel of the mesh, or it holds label values past the
    mesh's materials (a raw atlas before labels.map): its volumes would be compared with
    another volume."""
    import numpy as np

    dim = original.array.ndim
    if dim != mesh.dim:
        raise DicerError(f"{path}: a {dim}D segmentation for a {mesh.dim}D mesh; give the segmentation the mesh was "
                         "made from with --original (labels.nii.gz of the run)")
    spacing, origin = np.asarray(mesh.spacing, float)[:dim], np.asarray(mesh.origin, float)[:dim]
    extent = np.asarray(mesh.grid_shape, float)[:dim] * spacing
    theirs = np.asarray(original.array.shape, float) * np.asarray(original.spacing, float)
    moved = np.abs(np.asarray(original.origin, float) - origin)
    if np.any(np.abs(theirs - extent) > spacing) or np.any(moved > spacing):
        raise DicerError(f"{path}: the original segmentation spans {' x '.join(f'{v:g}' for v in theirs)} mm from "
                         f"{', '.join(f'{v:g}' for v in original.origin)}, the mesh's labels "
                         f"{' x '.join(f'{v:g}' for v in extent)} mm from {', '.join(f'{v:g}' for v in origin)}; give "
                         "the segmentation the mesh was made from with --original (labels.nii.gz of the run)")
    top = int(original.array.max(initial=0))
    materials = max(len(mesh.names or ()), int(mesh.material.max(initial=0)) if mesh.n_cells else 0)
    if top > materials:
        raise DicerError(f"{path}: the original segmentation holds label {top}, past the mesh's {materials} "
                         "materials (labels before labels.map?); give the mapped labels.nii.gz of dicer labels "
                         "with --original")


def do_quality(mesh_path: str, out: Path, config: dict, labels_path: str | None = None, html: str | None = None,
               pictures: list[str] = (), stage_reports: list[str] = (), csv: Path | None = None,
               original_path: str | None = None, histogram: Path | None = None, model_picture: Path | None = None,
               node_classes: Path | None = None, mesh=None, neighbours=None, materials_path: str | None = None):
    from dicer.io.atomic import in_this_block, write_bytes_atomic
    from dicer.io.meshes import read_mesh

    with _Stage("quality"):
        # the report only reads the mesh: its arrays stay in the page cache, mapped, not copied
        mesh = read_mesh(mesh_path, mapped=True) if mesh is None else mesh
        _check_materials_file("quality", materials_path, mesh, mesh_path, config)
        labels = original = None
        if labels_path or original_path:
            import numpy as np

            from dicer.io.images import read_labels

            labels = read_labels(labels_path, _npy_spacing(labels_path, config)) if labels_path else None
            original = read_labels(original_path, _npy_spacing(original_path, config)) if original_path else None
            if original is not None:
                _check_original(original, original_path, mesh)
            if labels is not None:
                # voxel counts of another grid would compare the mesh with another volume
                shape = tuple(labels.array.shape) + (1,) * (3 - labels.array.ndim)
                grid = tuple(int(n) for n in mesh.grid_shape)
                if shape != grid:
                    raise DicerError(f"{labels_path}: the labels have {'x'.join(map(str, shape))} voxels but the mesh "
                                     f"was made from {'x'.join(map(str, grid))}; give the label volume the mesh was "
                                     "made from with --labels (the original segmentation goes to --original)")
                size = np.asarray(labels.spacing, float)
                if not np.allclose(size, np.asarray(mesh.spacing, float)[:size.size], rtol=1e-5, atol=0):
                    raise DicerError(f"{labels_path}: the labels' voxels are {' x '.join(f'{v:g}' for v in size)} mm "
                                     "but the mesh's "
                                     f"{' x '.join(f'{v:g}' for v in np.asarray(mesh.spacing)[:size.size])} mm; give "
                                     "the label volume the mesh was made from with --labels")
                from dicer.mesh.labelsurface import check_labels_for_mesh

                # a raw atlas, or labels mapped otherwise, on the same grid: wrong volumes, false topology flags
                check_labels_for_mesh(labels, mesh, labels_path)
        # every element metric once: the report's, the figures' and the CSV's with skew
        from dicer.mesh.metrics import element_metrics
        from dicer.parallel import meanwhile
        from dicer.quality import REPORT_METRICS, element_neighbours, floating_parts

        def connectivity() -> tuple:  # the face neighbours (model picture) and the parts: no metric needed
            from dicer.mesh.faces import voxel_elements

            voxel = voxel_elements(mesh) if mesh.n_cells and mesh.material.min() > 0 else None
            # another mesh's parts (and surfaces, against the labels) need the neighbours anyway
            wanted = model_picture or (voxel is None and mesh.n_cells)
            nb = neighbours() if neighbours is not None else element_neighbours(mesh) if wanted else None
            return nb, floating_parts(mesh, nb, voxel), voxel

        # on a thread beside the metrics: labelling the parts runs much of its time on one core
        parts_later = meanwhile(connectivity)
        names = REPORT_METRICS + (("skew",) if csv else ())
        metrics = element_metrics(mesh.points, mesh.cells, names)
        sj = metrics["scaled_jacobian"]
        across, parts, voxel = parts_later()
        with ThreadPoolExecutor(1) as pool:
            table = None
            if csv:  # the table is written and read back beside the report (part of its all-or-nothing)
                from dicer.io.metrics_csv import write_metrics_csv

                table = pool.submit(in_this_block(write_metrics_csv), mesh, csv, metrics)
            # on an error the pool waits for the table, whose file the block then deletes
            report = _report_of(mesh, config, labels, original, metrics, sj, stage_reports, html, pictures,
                                histogram, model_picture, node_classes, across, parts, voxel)
            if table is not None:
                table.result()
        write_bytes_atomic(out, json.dumps(report, indent=2, sort_keys=True) + "\n")
        step = report.get("explicit_time_step")
        log.info("quality: wrote %s (min scaled Jacobian %.3f, %d inverted, %d part(s)%s)", out,
                 report["scaled_jacobian"]["min"], report["inverted_elements"], report["parts"]["model"]["parts"],
                 f", explicit time step {step['smallest_s']:.3g} s in {step['material']}" if step else "")
        if report["inverted_elements"]:  # the stages never make one: a mesh another tool made or edited
            log.warning("quality: %d of the %d elements are inverted or degenerate (scaled Jacobian 0 or less: "
                        "corners in another order or folded); no solver takes them, and the volumes here count "
                        "them negative; export and surface refuse them: remesh from the labels with dicer mesh",
                        report["inverted_elements"], report["elements"])
        whole = report["parts"]["model"]
        if whole["parts"] > 1:  # each part needs supports of its own, else a static solve is singular
            log.warning("quality: the model is %d parts joined by no face: %d element(s) float free of the largest "
                        "part (the smallest part %d); hold each part in the solver, or drop the parts below a "
                        "size with fix.min_component_voxels", whole["parts"], whole["floating_elements"],
                        whole["smallest"])
        changed = report.get("topology_changed")
        if changed:
            first = report["materials"][changed[0]]
            log.warning("quality: the surface of %s has another topology than its voxels (Euler characteristic %d "
                        "against %d): merging closed a hole or channel a voxel or two wide, filled a cavity, or "
                        "pinched the surface at a node; to keep the voxels' shape set merge.passes=[0, 0, 0] or "
                        "merge.method: templates", brief_names(changed), first["surface_euler"],
                        first["voxel_surface_euler"])
        if report["materials_without_elements"]:  # said by the stage that lost them, which a workflow logs only
            log.warning("quality: %d material(s) have no elements in the model: %s; the deck has no element set for "
                        "them (the segmentation, downsampling or fixes left no voxel of them: see those stages' "
                        "warnings)", len(report["materials_without_elements"]),
                        brief_names(report["materials_without_elements"]))
        if report["stretched_elements"]:  # a solver's stresses suffer in them long before it refuses them
            log.warning("quality: %d element(s) have an edge ratio above %g (largest %.3g); %s make them; "
                        "quality.stretched_edge_ratio sets the limit", report["stretched_elements"],
                        report["stretched_threshold"], report["edge_ratio"]["max"], _stretch_causes(mesh, report))
    return report


def _stretch_causes(mesh, report: dict) -> str:
    """What makes elements long and thin in this model: elongated voxels (only when they are),
    merging, a pillow layer (only when the smoothing report says there is one), smoothing."""
    import numpy as np

    spacing = np.asarray(mesh.spacing, float)[:mesh.dim]
    causes = []
    if spacing.max() > 1.5 * spacing.min():
        causes.append("elongated voxels (downsample with a factor per axis)")
    causes.append("merging across the long axis (merge.passes)")
    if "pillow" in report.get("stages", {}).get("smooth", {}):
        causes.append("a thin pillow layer (smooth.pillow_thickness)")
    causes.append("smoothing that shortens an edge of a small part or a sharp fold")
    return ", ".join(causes[:-1]) + " or " + causes[-1]


def _report_of(mesh, config: dict, labels, original, metrics: dict, sj, stage_reports, html, pictures, histogram,
               model_picture, node_classes, neighbours, parts: dict, voxel=None) -> dict:
    """The quality report of ``mesh`` with the stage reports; its pictures and HTML page written.
    ``neighbours``: the model picture's faces (None without it: the parts of a voxel mesh come
    from its voxel grid); ``parts``: the mesh's floating parts."""
    from dicer.config import stage_kwargs
    from dicer.io.atomic import pending, write_bytes_atomic
    from dicer.quality import quality_report, render_html

    settings = {**stage_kwargs(config, "quality"), "names": _mesh_names(mesh, config)}
    # the properties the decks give each material number, and a 2D deck's plane stress or
    # strain: the explicit time step's wave speeds
    export = stage_kwargs(config, "export")
    report = quality_report(mesh, **settings, labels=labels, original=original, metrics=metrics,
                            neighbours=neighbours, parts=parts, voxel=voxel, properties=export["materials"],
                            plane_stress=not str(export["element_type"] or "CPS").startswith("CPE"))
    stages, given = {}, {}
    for path in stage_reports:
        try:
            content = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DicerError(f"{path}: cannot read the stage report ({exc}); rerun that stage") from None
        if not isinstance(content, dict):
            raise DicerError(f"{path}: not a stage report (a JSON object, as dicer fix, merge and smooth write with "
                             "--report); give those files")
        # named by what it holds, not by its file name (which may carry a patient's code)
        stage = next((s for s, keys in _STAGE_REPORT_KEYS.items() if keys <= content.keys()), None)
        if stage is None:
            raise DicerError(f"{path}: not a report of dicer fix, merge or smooth (it lacks their keys); give the "
                             "--report files of those stages (fix.json, merge.json, smooth.json of dicer run)")
        if stage in given:
            raise DicerError(f"{path}: a second {stage} report ({given[stage]} is one); give one report per stage")
        stages[stage], given[stage] = content, path
    if stages:
        report["stages"] = stages
    figures = _quality_figures(mesh, report, sj, dict(enumerate(settings["names"], start=1)), histogram,
                               model_picture, node_classes, neighbours)
    if html:
        shown = []
        for path in list(pictures) + figures:
            try:
                shown.append((_PICTURE_CAPTIONS.get(Path(path).name, "Picture"), pending(path).read_bytes()))
            except OSError as exc:
                raise DicerError(f"{path}: cannot read the picture ({exc.strerror}); give an existing PNG "
                                 "with --picture") from None
            if not shown[-1][1].startswith(b"\x89PNG\r\n\x1a\n"):  # the page embeds it as a PNG
                raise DicerError(f"{path}: not a PNG picture (the report would show a broken image); give a PNG "
                                 "with --picture, such as segmentation.png")
        write_bytes_atomic(html, render_html(report, shown))
    return report


_STAGE_REPORT_KEYS = {"fix": {"type_a"}, "merge": {"element_ratio", "elements_before"},
                      "smooth": {"node_classes", "boundary_iterations"}}
"""The keys each stage's report holds and the others' (and quality.json) do not."""

_PICTURE_CAPTIONS = {
    "segmentation.png": "Segmentation: the labels over the scan, three orthogonal slices",
    "thresholds.png": "Threshold criterion per material",
    "jacobian.png": "Scaled Jacobian per material",
    "model.png": "The model: exterior coloured by material, and cut open",
    "node_classes.png": "Boundary node classes",
}


def _quality_figures(mesh, report: dict, sj, names: dict, histogram: Path | None, model_picture: Path | None,
                     node_classes: Path | None, neighbours=None) -> list[Path]:
    """Write the quality pictures asked for; returns their paths (in the report's order).
    neighbours : (M, F) element across each face, for the model picture (computed when None)."""
    written = []
    if not (histogram or model_picture or node_classes):
        return written  # matplotlib is not even imported
    from dicer.io.pictures import save_jacobian_histogram, save_model_picture, save_node_class_chart

    if histogram:
        written.append(save_jacobian_histogram(sj, mesh.material, names, histogram, report["poor_threshold"]))
    if model_picture:
        written.append(save_model_picture(mesh, names, model_picture, neighbours=neighbours))
    if node_classes:
        if "node_classes" not in report:
            raise DicerError(f"{node_classes}: the mesh has no node classes (point data node_class); give the "
                             "smoothed mesh (dicer smooth writes them) or leave out --node-classes")
        written.append(save_node_class_chart(report["node_classes"], node_classes))
    return written


def _read_benchmark(path: Path) -> dict:
    """A Snakemake benchmark file's first line as a dict (s, max_rss, ...)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DicerError(f"{path}: cannot read the benchmark file ({exc}); rerun that stage") from None
    if len(lines) < 2 or "s" not in lines[0].split("\t"):
        raise DicerError(f"{path}: not a Snakemake benchmark file (a header with s and max_rss, then a line); "
                         "rerun that stage or delete the file")
    return dict(zip(lines[0].split("\t"), lines[1].split("\t")))


def _benchmark_files(paths, patients) -> dict[str, dict[str, Path]]:
    """Patient -> stage -> benchmark file, from files named <patient>/<stage>.tsv or folders
    holding such <patient> folders (every stage file there)."""
    found: dict[str, dict[str, Path]] = {}
    for path in map(Path, paths or ()):
        if path.is_dir():
            for patient in patients:
                for f in sorted((path / patient).glob("*.tsv")):
                    found.setdefault(patient, {})[f.name[:-4]] = f
        elif path.is_file() and path.suffix == ".tsv":
            found.setdefault(path.resolve().parent.name, {})[path.name[:-4]] = path
        else:
            raise DicerError(f"{path}: no such benchmark file or folder; give Snakemake's benchmark files "
                             "(<patient>/<stage>.tsv) or the folder holding their patient folders")
    return found


def _warn_of_mixed_versions(quality: dict[str, dict]) -> None:
    """Warn where the patients' models were made by different versions of dicer or of its
    libraries (``library_versions``; reports made before it was recorded are left out): their
    last bits may differ for that alone."""
    from collections import Counter

    made: dict[str, Counter] = {}
    for report in quality.values():
        if "dicer_version" in report:
            made.setdefault("dicer", Counter())[report["dicer_version"]] += 1
        for name, version in report.get("library_versions", {}).items():
            made.setdefault(name, Counter())[version] += 1
    mixed = [f"{name} " + ", ".join(f"{v} ({counts[v]} patient(s))" for v in sorted(counts))
             for name, counts in made.items() if len(counts) > 1]
    if mixed:
        log.warning("cohort: the patients' models were made by different versions: %s; a model can differ in its "
                    "last bits for that alone, so to compare like with like run them again in one environment "
                    "(make setup installs the versions of constraints.txt)", "; ".join(mixed))


def do_cohort(reports: list[str], out: Path, tsv: Path | None = None, benchmarks=None):
    from dicer.cohort import cohort_rows, cohort_tsv, report_problem, render_cohort_html
    from dicer.io.atomic import write_bytes_atomic

    with _Stage("cohort"):
        quality, bench = {}, {}
        for path in reports:
            patient = Path(path).resolve().parent.name
            if patient in quality:
                raise DicerError(f"{path}: a second report of patient {patient!r} (patients are named by the "
                                 "report's folder); give one quality.json per patient folder")
            try:
                quality[patient] = json.loads(Path(path).read_text(encoding="utf-8"))
            except FileNotFoundError:
                raise DicerError(f"{path}: quality report not found; run dicer quality first") from None
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise DicerError(f"{path}: cannot read the quality report ({exc}); run dicer quality again") from None
            problem = report_problem(quality[patient])
            if problem:
                raise DicerError(f"{path}: not a dicer quality report ({problem}); give quality.json files written by "
                                 "dicer quality")
        for patient, stages in _benchmark_files(benchmarks, quality).items():
            if patient in quality:
                bench[patient] = {stage: _read_benchmark(f) for stage, f in stages.items()}
        columns, rows = cohort_rows(quality, bench)
        poor = next((r.get("poor_threshold") for r in quality.values()), None)
        if len({r.get("poor_threshold") for r in quality.values()} - {None}) > 1:  # patients' configs differ
            log.info("cohort: the patients' poor thresholds differ (%s); a row counted below another threshold "
                     "than the heading's shows its own", ", ".join(sorted({f"{r['poor_threshold']:g}" for r in
                                                                       quality.values() if "poor_threshold" in r})))
        _warn_of_mixed_versions(quality)
        write_bytes_atomic(out, render_cohort_html(columns, rows, poor))
        if tsv:
            write_bytes_atomic(tsv, cohort_tsv(columns, rows))
        log.info("cohort: wrote %s (%d patient(s))", out, len(rows))
    return columns, rows


# --- commands -------------------------------------------------------------------------


def cmd_segment(args):
    out = _check_output(args.output, (".nii", ".nii.gz"), "the label volume")
    overlay = _check_output(args.overlay, (".png",), "the overlay picture") if args.overlay else None
    plot = _check_output(args.plot, (".png",), "the threshold plot") if args.plot else None
    info = _check_output(args.info, (".json",), "the segmentation info") if args.info else None
    do_segment(args.image, out, _config(args), overlay=overlay, info_path=info, plot=plot)


def cmd_labels(args):
    out = _check_output(args.output, (".nii", ".nii.gz"), "the label volume")
    materials = _check_output(args.materials_out, (".json",), "the materials file") if args.materials_out else None
    do_labels(args.labels, out, _config(args), materials, names_only=_names_only(args))


def _names_only(args) -> bool:
    """Whether --settings gives the materials by name alone (the workflow's labels rule: the
    properties go to the export from its own settings, and the file holds no stale ones)."""
    if not getattr(args, "settings", None):
        return False
    listed = json.loads(args.settings).get("materials")
    return bool(listed) and all(isinstance(m, dict) and set(m) == {"name"} for m in listed)


def _warn_of_config_numbering(args, config: dict, stage: str) -> None:
    """Warn when a stage numbers a mapped label volume's materials by the config's materials
    list although its labels.map numbers them otherwise: dicer labels numbers materials by
    their smallest label value, and without --materials label i takes the i-th entry."""
    mapping = config["labels"]["map"]
    if getattr(args, "materials", None) or not mapping:
        return
    by_value = list(dict.fromkeys(name for _, name in sorted((int(k), v) for k, v in mapping.items())))
    listed = [m["name"] for m in config["materials"]]
    if by_value == listed[:len(by_value)]:
        return
    log.warning("%s: the config's labels.map numbers its materials %s (by smallest label value, as dicer labels "
                "does), its materials list %s: without --materials a mapped label volume's material i takes the "
                "i-th materials entry, so names and properties may go to the wrong labels; give --materials "
                "materials.json (written by dicer labels --materials)", stage, brief_names(by_value),
                brief_names(listed))


def cmd_downsample(args):
    config = _config(args)
    if args.materials:  # a label volume dicer labels mapped: downsampled as dicer run --labels does
        from dicer.config import for_label_volume

        config = for_label_volume(config)
    _warn_of_config_numbering(args, config, "downsample")
    do_downsample(args.labels, _check_output(args.output, (".nii", ".nii.gz"), "the label volume"), config)


def cmd_fix(args):
    report = _check_output(args.report, (".json",), "the fix report") if args.report else None
    config = _config(args)
    _warn_of_config_numbering(args, config, "fix")
    do_fix(args.labels, _check_output(args.output, (".nii", ".nii.gz"), "the label volume"), config, report)


def cmd_merge(args):
    report = _check_output(args.report, (".json",), "the merge report") if args.report else None
    do_merge(args.mesh, _check_output(args.output, (".vtu",), "the mesh"), _config(args), report)


def cmd_smooth(args):
    from dicer.config import places_faces_by_scan, smoothing_reads_scan, stage_kwargs

    report = _check_output(args.report, (".json",), "the smoothing report") if args.report else None
    config = _config(args)
    smooth = stage_kwargs(config, "smooth")
    scan_surface = args.image is not None and smooth["surface_from_image"]
    if args.labels is not None and (scan_surface or not smooth["surface_from_labels"]):
        log.warning("smooth: --labels is read by smooth.surface_from_labels only, which is %s: %s is not read",
                    "not used beside the scan's surface (smooth.surface_from_image)" if scan_surface else "off",
                    args.labels)
    if smooth["label_samples"] in ("relaxed", "auto") and smooth["surface_from_labels"] and not scan_surface and \
            args.labels is None:
        # asked for by name, a warning; the default's (auto) a note: a bare 'dicer smooth' is no mistake
        (log.warning if smooth["label_samples"] == "relaxed" else log.info)(
            "smooth: smooth.label_samples: %s relaxes the staircase of the label volume: give it with --labels "
            "(labels_fixed.nii.gz of dicer run); without it the fit takes the mesh's faces", smooth["label_samples"])
    if args.image is not None and args.labels is None and not scan_surface and places_faces_by_scan(smooth):
        log.warning("smooth: smooth.fit_to_scan places the labels' faces by the scan: it needs --labels beside "
                    "--image (labels_fixed.nii.gz of dicer run); without it the fit takes the mesh's faces, and the "
                    "scan is not read")
    elif args.image is not None and not smoothing_reads_scan(smooth):
        log.warning("smooth: --image is read by smooth.surface_from_image, or by smooth.fit_to_scan with --labels "
                    "(the fit's faces placed by the scan), and these settings use neither: %s is not read", args.image)
    do_smooth(args.mesh, _check_output(args.output, (".vtu",), "the mesh"), config, report,
              image_path=args.image, thresholds_path=args.thresholds, labels_path=args.labels)


def cmd_mesh(args):
    config = _config(args)
    _warn_of_config_numbering(args, config, "mesh")
    do_mesh(args.labels, _check_output(args.output, (".vtu",), "the mesh"), config)


def cmd_export(args):
    from dicer.export import EXPORT_SUFFIXES

    config = _config(args)  # with --order
    do_export(args.mesh, _check_output(args.output, EXPORT_SUFFIXES, "the model file"), config,
              materials_path=args.materials)


def cmd_quality(args):
    csv = _check_output(args.csv, (".csv",), "the metrics table") if args.csv else None
    pngs = {k: _check_output(getattr(args, k), (".png",), f"the {what}") if getattr(args, k) else None
            for k, what in (("histogram", "scaled-Jacobian histogram"), ("model_picture", "model picture"),
                            ("node_classes", "node-class chart"))}
    html = _check_output(args.html, (".html", ".htm"), "the HTML report") if args.html else None
    do_quality(args.mesh, _check_output(args.output, (".json",), "the quality report"), _config(args),
               labels_path=args.labels, html=html, pictures=args.picture or [],
               stage_reports=args.stage_report or [], csv=csv, original_path=args.original, **pngs,
               materials_path=args.materials)


def cmd_cohort(args):
    tsv = _check_output(args.tsv, (".tsv",), "the cohort table") if args.tsv else None
    do_cohort(args.reports, _check_output(args.output, (".html", ".htm"), "the cohort overview"), tsv,
              args.benchmarks)


def cmd_surface(args):
    do_surface(args.mesh, Path(args.output), _config(args), args.material, materials_path=args.materials)


def cmd_phantom(args):
    from dicer.io.images import write_image
    from dicer.phantoms import PHANTOMS, make_phantom

    if args.name not in PHANTOMS:
        raise DicerError(f"phantom {args.name!r} is unknown; choose one of {', '.join(sorted(PHANTOMS))}")
    if args.seed < 0:
        raise DicerError(f"phantom: --seed {args.seed} is negative; give a whole number from 0")
    out = _check_output(args.output, (".nii", ".nii.gz", ".nrrd", ".mha"), "the phantom image")
    with _Stage("phantom"):
        image = make_phantom(args.name, size=args.size, noise=args.noise, seed=args.seed)
        write_image(image, out)
        log.info("phantom: wrote %s (%s voxels of %s mm)", out, "x".join(map(str, image.array.shape)),
                 "x".join(f"{s:g}" for s in image.spacing))


RUN_OUTPUTS = ("labels.nii.gz", "materials.json", "segmentation.png", "segmentation.json", "thresholds.png", "labels_ds.nii.gz",
               "labels_fixed.nii.gz", "fix.json", "mesh.vtu", "merged.vtu", "merge.json", "smoothed.vtu",
               "smooth.json", "model.inp", "model.vtu", "model.out", "model.neu", "model.k", "model.msh", "model.exo",
               "model.e", "model.feb", "quality.json", "report.html", "jacobian.png", "model.png", "node_classes.png")
"""Every file dicer run may write into its folder (the models: those workflow.exports names)."""


def _check_priority(config: dict, source: str) -> None:
    """``fix.priority``'s names against the materials, before the stages that come before the fix."""
    from dicer.connectivity import check_priority

    try:
        check_priority([m["name"] for m in config["materials"]], config["fix"]["priority"] or [])
    except DicerError as exc:
        raise DicerError(f"{source}: {exc}") from None


def _check_export_dims(config: dict, dim: int, source: str) -> None:
    """Refuse a model of ``dim`` dimensions that a format of ``workflow.exports`` cannot hold."""
    from dicer.export.registry import BY_SUFFIX

    cannot = [(ext, BY_SUFFIX[f".{ext}"]) for ext in dict.fromkeys(config["workflow"]["exports"])
              if dim not in BY_SUFFIX[f".{ext}"].dims]
    if cannot:
        named = ", ".join(f"{ext} ({fmt.name})" for ext, fmt in cannot)
        them = " and ".join(ext for ext, _ in cannot)
        dims = " and ".join(f"{d}D" for d in cannot[0][1].dims)
        raise DicerError(f"{source}: a {dim}D image, and workflow.exports names {named}, which hold"
                         f"{'s' if len(cannot) == 1 else ''} {dims} models only; drop {them} from workflow.exports")
    from dicer.export.model import ELEMENT_TYPES, element_types

    etype = config["export"]["element_type"]
    if etype is not None and ELEMENT_TYPES[etype][0] != dim:  # found at the export, after every stage
        raise DicerError(f"{source}: a {dim}D image, and export.element_type {etype} is for {3 if dim == 2 else 2}D "
                         f"models; use one of {', '.join(element_types(dim, config['export']['order']))}, or "
                         "leave export.element_type out (null: the default of the order)")


def _check_exodus_size(config: dict, labels, source: str) -> None:
    """Refuse, before the meshing, an Exodus export that the fixed labels' materials and their
    interfaces already make too large (it was refused after every stage and the other exports)."""
    if not {"exo", "e"} & set(config["workflow"]["exports"]):
        return
    from dicer.export.exodus import _MAX_ARRAYS, least_arrays

    variables, materials, pairs = least_arrays(labels, config["export"]["sets"])
    if variables > _MAX_ARRAYS:  # the export's own limit
        raise DicerError(f"{source}: the Exodus file of workflow.exports would hold at least {variables} netCDF "
                         f"variables ({materials} materials' blocks and boundary sets, {pairs} interfaces' node and "
                         f"side sets), above the {_MAX_ARRAYS} whose definition takes the netCDF library a minute and "
                         "more; export fewer sets (--set 'export.sets=[exterior]') or leave exo out of "
                         "workflow.exports (an Abaqus deck, .inp, holds them)")


def _input_dims(source: str) -> int | None:
    """2 or 3: the model's dimension from the input's header (an image of one voxel along an
    axis is read as 2D); None where the header does not tell (a folder of slices) or cannot be read."""
    from dicer.resources import scan_shape

    try:
        shape, _ = scan_shape(source)
    except OSError:  # the first stage names the problem
        return None
    if shape is None:
        return None
    kept = [n for n in shape if n != 1]
    if len(shape) == 2 or (len(shape) == 3 and len(kept) == 2):
        return 2
    return 3 if len(shape) == 3 else None


def run_models(config: dict) -> list[str]:
    """The model files ``dicer run`` exports: ``model.<ext>`` for each of ``workflow.exports``
    (default inp and vtu), as the workflow does per patient."""
    return [f"model.{ext}" for ext in dict.fromkeys(config["workflow"]["exports"])]


def _cropped_voxels(voxels: int, spacing, crop: dict | None) -> int:
    """The voxels image.crop keeps of a scan of ``voxels`` (an estimate for unit mm: the
    box's extent over the voxel size, as for an axis-aligned scan)."""
    import numpy as np

    if crop is None or len(crop["min"]) != len(crop["max"]):  # a bad crop: the first stage names it
        return voxels
    extent = np.abs(np.subtract(crop["max"], crop["min"]))
    if crop["unit"] == "mm":
        if spacing is None or len(spacing) != extent.size:
            return voxels
        extent = np.floor(extent / np.asarray(spacing, float)) + 1
    return int(min(voxels, np.prod(extent)))


class _MemoryError(DicerError):
    """The run would need more memory than the machine has: refused before the stage that
    would, with nothing written."""


def _check_memory(source: str, config: dict, elements: int | None = None, faces: int | None = None,
                  label_volume: bool = False) -> None:
    """DicerError when the run's fitted peak memory (dicer/resources.py) exceeds what this
    machine or job may use: before any stage, for the stages that read the scan; with the
    mesh's ``elements`` and surface ``faces`` (after fix), for the stages from the mesh on.
    The kernel would otherwise kill the run without a message."""
    import numpy as np

    from dicer.config import downsample_applies, places_faces_by_scan, relaxes_staircase, stage_kwargs
    from dicer.downsample import reduction_factor
    from dicer.resources import machine_memory_mb, run_peak_mb, scan_header, voxel_reduction

    try:
        voxels, spacing = scan_header(source)
    except OSError:  # missing or unreadable: the first stage names the problem
        return
    ds = stage_kwargs(config, "downsample")
    factor = (reduction_factor(spacing or (1.0, 1.0, 1.0), factor=ds["factor"], voxel_size=ds["voxel_size"],
                               source=source) if downsample_applies(config) else 1)
    whole, voxels = voxels, _cropped_voxels(voxels, spacing, config["image"]["crop"])
    order = stage_kwargs(config, "export")["order"]
    smooth = stage_kwargs(config, "smooth")
    relaxed = (smooth["surface_from_labels"] and not smooth["surface_from_image"] and
               relaxes_staircase(smooth, not label_volume and places_faces_by_scan(smooth)))
    need, have = run_peak_mb(voxels, factor, elements, order, faces, relaxed), machine_memory_mb()
    if voxels < whole:  # the whole scan is read (as float32) before it is cut
        need += whole * 4 / 2**20
    if have is None or need <= have:
        return

    def peak(f):  # the elements shrink with the voxels a coarser grid leaves, the faces as their area
        coarser = np.maximum(factor, f)
        shrink = voxel_reduction(factor) / voxel_reduction(coarser)
        fewer = None if elements is None else int(elements * shrink)
        less = None if elements is None or faces is None else int(faces * shrink ** (2 / 3))
        return run_peak_mb(voxels, coarser, fewer, order, less, relaxed)

    fits = [(f, p) for f, p in ((f, peak(f)) for f in range(2, 9)) if p <= 0.8 * have]
    hint = (f"set downsample.factor: {fits[0][0]} (about {fits[0][1] / 1024:.1f} GB)" if fits
            else "crop or downsample the scan")
    shown = "x".join(str(int(f)) for f in np.atleast_1d(factor))
    size = f"{voxels:,} voxels" + ("" if elements is None else f" ({elements:,} elements)")
    raise _MemoryError(f"{source}: {size} at downsample factor {shown} need about {need / 1024:.1f} GB "
                     f"of memory, this machine (or job) has {have / 1024:.1f} GB; {hint}, or use a larger machine "
                     "(--skip-memory-check runs anyway)")


SIDE_BY_SIDE_MEMORY = 1.2
"""The run's fitted peak (dicer/resources.py) times this must fit the machine for the second
thread, which raised the measured peak by 4.7 % on the 256³ CT (2.68 -> 2.80 GB) and by
14 % on the 512³ CT (17.1 -> 19.5 GB; fitted peak then 19.0 GB, times 1.2: 22.8 GB; since
the surface faces count, 19.5 GB, times 1.2: 23.4 GB of the 23.5 GB)."""


def _side_by_side(source: str, elements: int, order: int = 1, faces: int | None = None) -> bool:
    """Whether ``dicer run`` may write stage files and make its quality report in a second
    thread: a second core for it, and memory for :data:`SIDE_BY_SIDE_MEMORY` times the run's
    fitted peak (dicer/resources.py) at its ``export.order``, for its ``elements`` and
    surface ``faces``."""
    from dicer.parallel import cores
    from dicer.resources import machine_memory_mb, run_peak_mb, scan_header

    if cores() < 2:
        return False
    have = machine_memory_mb()
    try:
        voxels = scan_header(source)[0]
    except OSError:
        return False
    return have is None or SIDE_BY_SIDE_MEMORY * run_peak_mb(voxels, 1, elements, order, faces) <= have


@contextlib.contextmanager
def _each_warning_once():
    """Drop a warning that repeats one said before word for word (dicer run's two exports of
    one mesh met the same things)."""
    said = set()

    def first_time(record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        text = record.getMessage()
        if text in said:
            return False
        said.add(text)
        return True

    loggers = [logging.getLogger(name) for name in ("dicer", "dicer.io.images")]
    for logger in loggers:
        logger.addFilter(first_time)
    try:
        yield
    finally:
        for logger in loggers:
            logger.removeFilter(first_time)


def cmd_run(args):
    with _each_warning_once():
        return _run_chain(args)


def _run_chain(args):
    """segment -> downsample -> fix -> mesh -> merge -> smooth -> export (workflow.exports) -> quality, into OUTDIR.

    With --labels: labels (map the given label volume to materials) -> downsample (only when
    downsample.factor or voxel_size is set) -> fix -> ... as above.
    The stages write into a staging folder beside OUTDIR; a finished run moves its files
    into OUTDIR, a failed one leaves OUTDIR as it was and its finished stage files in
    OUTDIR.failed (named in the error).
    """
    if (args.image is None) == (args.labels is None):
        raise DicerError("dicer run: give either an IMAGE to segment or --labels LABELS (a label volume), "
                         "not both and not neither")
    config = _config(args)
    if not str(args.output).strip():  # an unset shell variable: Path("") is the current folder
        raise DicerError("dicer run: -o names no folder (an empty or blank string); give an output folder with -o")
    outdir = Path(args.output)
    if (outdir.exists() or outdir.is_symlink()) and not outdir.is_dir():
        raise DicerError(f"{outdir}: exists and is not a folder; give an output folder with -o")
    source = args.labels if args.image is None else args.image
    dim = _input_dims(source)
    if dim is not None:  # before any stage (fix checks the labels it made again)
        _check_export_dims(config, dim, source)
    if args.labels is None:  # the segmentation's materials are the config's: a misspelt name stops here
        _check_priority(config, source)
    if args.set:
        from dicer.config import for_label_volume
        from dicer.sheet import unread_settings

        label_volume = args.labels is not None
        for key, why in unread_settings(args.set, for_label_volume(config) if label_volume else config, label_volume):
            log.warning("run: --set %s %s, so it changes nothing", key, why)
    if not args.skip_memory_check:
        _check_memory(source, config)
    with _output_lock(outdir), _logged_as_published(outdir.parent / f".{outdir.name}.partial", outdir):
        _run_staged(args, config, outdir, source)


@contextlib.contextmanager
def _logged_as_published(staging: Path, outdir: Path):
    """Log lines name a staged file where the finished run puts it (OUTDIR/quality.json, not
    .OUTDIR.partial/quality.json, which is gone when the run ends)."""
    here, there = str(staging), str(outdir)

    def rename(record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if here in text:
            record.msg, record.args = text.replace(here, there), None
        return True

    handlers = list(logging.getLogger().handlers)
    for handler in handlers:
        handler.addFilter(rename)
    try:
        yield
    finally:
        for handler in handlers:
            handler.removeFilter(rename)


@contextlib.contextmanager
def _output_lock(outdir: Path):
    """Hold ``.OUTDIR.lock`` beside OUTDIR while a run writes it: a second run into the same
    folder shared the staging folder with the first, deleted it under it and mixed the two
    runs' files in OUTDIR. The lock file goes when the run ends (checked to be the one
    locked, so that a run starting as another ends cannot lock a file already removed)."""
    import fcntl

    lock = outdir.parent / f".{outdir.name}.lock"
    try:
        outdir.parent.mkdir(parents=True, exist_ok=True)  # as the staging folder would be
        while True:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise DicerError(f"{outdir}: another dicer run is writing this folder (it holds {lock.name}); "
                                 "wait for it to finish, or give another output folder with -o") from None
            try:
                same = os.stat(lock).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
    except OSError as exc:
        raise DicerError(f"{outdir}: cannot write to folder {outdir.parent} ({exc.strerror}); choose a writable "
                         "output folder") from None
    folder = None
    try:
        # the folder itself too: a run given a symlink to it holds another lock file (beside
        # the link, where its staging folder goes) but publishes here
        with contextlib.suppress(OSError):
            folder = os.open(outdir, os.O_RDONLY | os.O_DIRECTORY) if outdir.is_dir() else None
        if folder is not None:
            try:
                fcntl.flock(folder, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise DicerError(f"{outdir}: another dicer run is writing this folder ({os.path.realpath(outdir)}, "
                                 "given by another path); wait for it to finish, or give another output folder "
                                 "with -o") from None
            except OSError:  # a file system that locks only files open for writing (NFS): the lock file holds
                os.close(folder)
                folder = None
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)
        if folder is not None:
            os.close(folder)


def _run_staged(args, config: dict, outdir: Path, source: str) -> None:
    """The stages of ``dicer run`` into a staging folder, published into ``outdir`` at the end."""
    from dicer.config import downsample_applies, stage_kwargs
    from dicer.resources import surface_faces

    # every stage writes into a staging folder beside OUTDIR; only a finished run moves its
    # files into OUTDIR (an existing OUTDIR keeps its old files until then), and a failed
    # one leaves its finished, checked stage files in OUTDIR.failed for a look or a report
    staging = outdir.parent / f".{outdir.name}.partial"  # (as _logged_as_published names it)
    failed = outdir.parent / f"{outdir.name}.failed"
    try:
        if staging.exists():
            shutil.rmtree(staging)
        staging.mkdir(parents=True)
    except OSError as exc:
        raise DicerError(f"{outdir}: cannot write to folder {outdir.parent} ({exc.strerror}); choose a writable "
                         "output folder") from None
    t0 = time.perf_counter()
    stage = "start"

    def path(name: str) -> Path:
        return staging / name

    def step(name: str) -> None:
        nonlocal stage
        check_stop()
        stage = name

    try:
        if args.labels is not None:
            step("labels")
            from dicer.config import for_label_volume

            config = for_label_volume(config)
            config["materials"] = do_labels(args.labels, path("labels.nii.gz"), config, path("materials.json"))
            _check_priority(config, source)  # the label volume's materials: known once it is mapped
        else:
            step("segment")
            do_segment(args.image, path("labels.nii.gz"), config, overlay=path("segmentation.png"),
                       info_path=path("segmentation.json"), plot=path("thresholds.png"), plot_if_any=True)
        fix_input = path("labels.nii.gz")
        if args.labels is None or downsample_applies(config):
            step("downsample")
            do_downsample(str(path("labels.nii.gz")), path("labels_ds.nii.gz"), config)
            fix_input = path("labels_ds.nii.gz")
        step("fix")
        fixed = do_fix(str(fix_input), path("labels_fixed.nii.gz"), config, path("fix.json"))
        _check_export_dims(config, fixed.ndim, source)  # before the meshing, not after it
        _check_exodus_size(config, fixed, source)
        step("mesh")
        elements = int(fixed.size - (fixed == 0).sum())  # one element per labelled voxel
        faces = surface_faces(fixed)
        del fixed
        if not args.skip_memory_check:  # the mesh's size is known now
            _check_memory(source, config, elements, faces, args.labels is not None)
        # each stage hands its mesh to the next in memory, so the next stage need not read
        # the file again; with a second core (and memory), the file is written and checked
        # in a second thread meanwhile (the stages only read their input mesh)
        beside = _side_by_side(source, elements, order=stage_kwargs(config, "export")["order"], faces=faces)
        with ThreadPoolExecutor(1) as files:
            written = []

            def write(job):
                if beside:
                    written.append((stage, files.submit(job)))
                else:
                    job()

            try:
                mesh = do_mesh(str(path("labels_fixed.nii.gz")), path("mesh.vtu"), config, write=write)
                step("merge")
                # the merge's many fresh tables come quicker in ordinary pages (dicer.pages): 1-2 s
                # at 256³; a large mesh's in huge pages (16 s of 57 at 512³)
                with ordinary_pages(unless_set=True) if mesh.n_cells < LARGE_JOB else contextlib.nullcontext():
                    mesh = do_merge(str(path("mesh.vtu")), path("merged.vtu"), config, path("merge.json"),
                                    mesh=mesh, write=write)
                step("smooth")
                # a segmented scan lends its grey values: the surface goes onto its iso-surfaces
                scan = (args.image, str(path("segmentation.json"))) if args.labels is None else (None, None)
                mesh = do_smooth(str(path("merged.vtu")), path("smoothed.vtu"), config, path("smooth.json"),
                                 image_path=scan[0], thresholds_path=scan[1], mesh=mesh, write=write,
                                 labels_path=str(path("labels_fixed.nii.gz")))
            except BaseException:
                # an earlier stage's file, checked beside this stage, failed first: its error is the
                # cause (a merge that made inverted corners, then the smoothing that could not mend them)
                for earlier, job in written:
                    if job.exception() is not None:
                        stage = earlier  # as the error handler names it
                        job.result()
                raise
            # every file checked before the exports (they hash smoothed.vtu); a failed write
            # names the stage that made its file (``stage``, as the error handler reads it)
            for stage, job in written:
                job.result()
        # the pictures the workflow's report shows too (its segment rule draws no criterion:
        # thresholds.png exists for one method only), so that report.html is the same bytes
        pictures = [str(path(n)) for n in ("segmentation.png",) if path(n).exists()]
        # the face neighbours once, for the deck's sets and the report's parts and picture
        from dicer.parallel import meanwhile
        from dicer.quality import element_neighbours

        neighbours = meanwhile(element_neighbours, mesh)
        # the decks of order 2 take one quadratic mesh: its mid-edge nodes placed and checked once
        from functools import cache

        from dicer.export.model import quadratic_nodes

        quadratic = cache(lambda midside_nodes: quadratic_nodes(mesh, midside_nodes, neighbours))

        def quality():
            do_quality(str(path("smoothed.vtu")), path("quality.json"), config,
                       labels_path=str(path("labels_fixed.nii.gz")), html=str(path("report.html")), pictures=pictures,
                       stage_reports=[str(path(n)) for n in ("fix.json", "merge.json", "smooth.json")],
                       original_path=str(path("labels.nii.gz")), histogram=path("jacobian.png"),
                       model_picture=path("model.png"), node_classes=path("node_classes.png"), mesh=mesh,
                       neighbours=neighbours)

        # the exports and the quality report only read the smoothed mesh: with a second core
        # and memory for both, the report is made beside the exports
        with ThreadPoolExecutor(1) as pool:
            report = None
            if beside:
                log.info("run: the quality report is made beside the exports (a second core)")
                report = pool.submit(quality)
            step("export")
            for name in run_models(config):
                do_export(str(path("smoothed.vtu")), path(name), config, mesh=mesh, neighbours=neighbours,
                          quadratic=quadratic)
            quadratic.cache_clear()  # its arrays go before the report's last part
            step("quality")
            report.result() if report is not None else quality()
    except _MemoryError:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    except BaseException as exc:
        kept = _keep_failed(staging, failed)
        if kept and not isinstance(exc, DicerError):  # interrupted or terminated: said by main
            exc.add_note(f"{outdir} is unchanged; the finished stage files are in {failed}")
        if isinstance(exc, DicerError):
            where = f"; its finished stage files are in {failed}" if kept else ""
            message = str(exc)
            # a fault of the labels (what segment or labels made of the input, downsampled and
            # fixed) is the input's: name the file the user gave (not for a write that failed)
            for name in ("labels.nii.gz", "labels_ds.nii.gz", "labels_fixed.nii.gz"):
                if message.startswith(f"{staging / name}: ") and not message.startswith(
                        f"{staging / name}: cannot write"):
                    message = f"{source}: {message[len(str(staging / name)) + 2:]}"
            # the stage named its file in the staging folder: name it where it now is
            message = message.replace(str(staging), str(failed)) if kept else message
            raise DicerError(f"{message} (dicer run stopped at the {stage} stage{where})") from None
        raise
    try:
        try:
            check_stop()
        except BaseException as exc:
            if _keep_failed(staging, failed):
                exc.add_note(f"{outdir} is unchanged; the finished stage files are in {failed}")
            raise
        _publish(staging, outdir)
    except OSError as exc:
        kept = _keep_failed(staging, failed)
        raise DicerError(f"{outdir}: cannot move the results into the folder ({exc.strerror}); "
                         + (f"they are in {failed}" if kept else "check the output folder")) from None
    log.info("run: finished in %.1f s; model in %s", time.perf_counter() - t0,
             ", ".join(str(outdir / name) for name in run_models(config)))


def _keep_failed(staging: Path, failed: Path) -> bool:
    """Move a failed run's staging folder to ``failed`` (replacing an older one); False if
    it held no file."""
    with contextlib.suppress(OSError):
        for tmp in staging.glob(".*.*.*.tmp*"):  # a write the failure cut short
            tmp.unlink()
        if not any(staging.iterdir()):
            staging.rmdir()
            return False
        if failed.exists():
            shutil.rmtree(failed)
        staging.rename(failed)
        return True
    return False


def _publish(staging: Path, outdir: Path) -> None:
    """Move a finished run's files into ``outdir``, all or none: an earlier run's results go
    aside first (beside the folder, on its disk), then each new file by an atomic rename;
    where a rename fails the new files go back to ``staging`` and the earlier ones back into
    ``outdir`` (a file that could not be replaced left the folder mixing two runs), so the
    folder never mixes two runs' results."""
    outdir.mkdir(parents=True, exist_ok=True)
    written = sorted(p.name for p in staging.iterdir())
    aside = outdir.parent / f".{outdir.name}.previous"
    if aside.exists():
        shutil.rmtree(aside)
    aside.mkdir()
    moved_aside: list[str] = []
    placed: list[str] = []
    try:
        for name in sorted(set(written) | set(RUN_OUTPUTS)):
            if (outdir / name).exists():
                os.replace(outdir / name, aside / name)
                moved_aside.append(name)
        for name in written:
            os.replace(staging / name, outdir / name)
            placed.append(name)
    except BaseException:  # a failed rename, or an interrupt between two
        with contextlib.suppress(OSError):
            for name in reversed(placed):
                os.replace(outdir / name, staging / name)
            for name in reversed(moved_aside):
                os.replace(aside / name, outdir / name)
            aside.rmdir()
        raise
    shutil.rmtree(aside, ignore_errors=True)
    staging.rmdir()


# --- parser ---------------------------------------------------------------------------


def _add_materials_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--materials", metavar="JSON",
                   help="materials file from 'dicer labels --materials' (replaces the config's materials)")


def _add_config_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="YAML configuration (defaults: see config/config.yaml)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one config key, e.g. --set segment.method=multiotsu, or take a preset's "
                        "settings, --set preset=static-stress (repeatable)")
    p.add_argument("--settings", metavar="JSON", help=argparse.SUPPRESS)  # stage settings from the workflow
    p.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only")


class _StoreOnce(argparse._StoreAction):
    """An option given twice is refused: argparse kept the last (``--config a.yaml --config
    b.yaml`` read b.yaml alone, without a word)."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = namespace.__dict__.setdefault("_given", set())
        if self.option_strings and self.dest in given:
            parser.error(f"{'/'.join(self.option_strings)} is given twice; give it once (--set repeats: "
                         "--config FILE --set key=value overrides one file's settings)")
        given.add(self.dest)
        super().__call__(parser, namespace, values, option_string)


class _Parser(argparse.ArgumentParser):
    """Usage errors in the command's one error line too (exit status 2, as argparse's); an
    option given twice is an error, and options are not taken by their beginnings
    (``--sett`` read as the workflow's hidden ``--settings``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        self.register("action", "store", _StoreOnce)
        self.register("action", None, _StoreOnce)

    def error(self, message):
        message = message.replace("\r", "\\r").replace("\n", "\\n")
        self.exit(2, f"error: {self.prog}: {message}; see '{self.prog} --help'\n")


class _Version(argparse.Action):
    """``--version``: dicer's version and the libraries' it runs on (looked up only when asked)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, help="show dicer's version and its libraries' and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        libraries = ", ".join(f"{name} {version}" for name, version in library_versions().items())
        sys.stdout.write(f"dicer {__version__} ({libraries})\n")  # stdout, as argparse's version action
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dicer",
        description="All-hexahedral finite-element models from CT/MR scans (DICER method).",
        epilog="Each stage reads one file and writes one; 'dicer run' chains them. See README.md.",
    )
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name, func, help_text, description=None, **options):
        p = sub.add_parser(name, help=help_text, description=description or help_text, **options)
        p.set_defaults(func=func)
        return p

    _add_image_commands(command)
    _add_mesh_commands(command)
    _add_report_commands(command)
    return parser


def _add_image_commands(command) -> None:
    """run, segment, labels, downsample, fix: the commands that read images and label volumes."""
    p = command("run", cmd_run, "the whole chain: image -> labels -> mesh -> model.inp, model.vtu (the formats "
                "workflow.exports names), quality.json")
    p.add_argument("image", metavar="IMAGE", nargs="?", help="image file or DICOM/TIFF/PNG folder")
    p.add_argument("--labels", metavar="LABELS",
                   help="mesh this label volume (" + ", ".join(LABEL_SUFFIXES) + ") instead of segmenting an "
                        "image; its values become materials by the config's labels section")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="output folder")
    p.add_argument("--skip-memory-check", action="store_true",
                   help="run even when the estimated peak memory exceeds what this machine or job has")
    _add_config_options(p)

    p = command("segment", cmd_segment, "classify voxels into the configured materials (labels 1..K)")
    p.add_argument("image", metavar="IMAGE",
                   help="NIfTI, NRRD, MetaImage, TIFF, .npy, or a folder of DICOM, TIFF or PNG slices")
    p.add_argument("-o", "--output", required=True, metavar="LABELS", help="label volume (.nii.gz)")
    p.add_argument("--overlay", metavar="PNG", help="also write three orthogonal slices with the labels over the image")
    p.add_argument("--plot", metavar="PNG", help="also plot the threshold criterion (segment.method=shape_connectivity)")
    p.add_argument("--info", metavar="JSON", help="also write thresholds, criterion curves and class fractions")
    _add_config_options(p)

    p = command("labels", cmd_labels, "map a label volume made elsewhere to materials 1..K (config labels:)")
    p.add_argument("labels", metavar="LABELS", help="label volume: " + ", ".join(LABEL_SUFFIXES))
    p.add_argument("-o", "--output", required=True, metavar="LABELS", help="mapped label volume (.nii.gz)")
    p.add_argument("--materials", dest="materials_out", metavar="JSON",
                   help="also write the materials of the mapped labels (give it to the later stages' --materials)")
    _add_config_options(p)

    p = command("downsample", cmd_downsample, "reduce the label volume's resolution, keeping thin classes")
    p.add_argument("labels", metavar="LABELS", help="label volume")
    p.add_argument("-o", "--output", required=True, metavar="LABELS", help="reduced label volume (.nii.gz)")
    _add_materials_option(p)
    _add_config_options(p)

    p = command("fix", cmd_fix, "repair poorly connected voxels (connectivity fixes A, B, C) to a fixed point")
    p.add_argument("labels", metavar="LABELS", help="label volume")
    p.add_argument("-o", "--output", required=True, metavar="LABELS", help="fixed label volume (.nii.gz)")
    p.add_argument("--report", metavar="JSON", help="also write the voxels changed per type and class")
    _add_materials_option(p)
    _add_config_options(p)


def _add_mesh_commands(command) -> None:
    """mesh, merge, smooth, export, surface: the commands that make and write meshes."""
    p = command("mesh", cmd_mesh, "one hexahedron (2D: quad) per non-background voxel")
    p.add_argument("labels", metavar="LABELS", help="label volume: " + ", ".join(LABEL_SUFFIXES) + " (.npy: spacing 1)")
    p.add_argument("-o", "--output", required=True, metavar="MESH", help="mesh (.vtu)")
    _add_materials_option(p)
    _add_config_options(p)

    p = command("merge", cmd_merge, "merge pairs of element layers where safe (fewer elements, same surface)")
    p.add_argument("mesh", metavar="MESH", help="mesh (.vtu) from 'dicer mesh'")
    p.add_argument("-o", "--output", required=True, metavar="MESH", help="merged mesh (.vtu)")
    p.add_argument("--report", metavar="JSON", help="also write counts per axis and pass and volume changes")
    _add_config_options(p)

    p = command("smooth", cmd_smooth, "smooth the boundary per node class, relax the interior, never invert")
    p.add_argument("mesh", metavar="MESH", help="mesh (.vtu) from 'dicer mesh' or 'dicer merge'")
    p.add_argument("-o", "--output", required=True, metavar="MESH", help="smoothed mesh (.vtu)")
    p.add_argument("--report", metavar="JSON", help="also write node class counts, back-offs and quality")
    p.add_argument("--image", metavar="IMAGE",
                   help="the scan the labels were segmented from: boundary nodes move onto its threshold "
                        "iso-surfaces when smooth.surface_from_image is true (off by default)")
    p.add_argument("--thresholds", metavar="JSON",
                   help="with --image: segmentation.json of 'dicer segment --info' (its thresholds); "
                        "default: the config's manual segment.thresholds")
    p.add_argument("--labels", metavar="LABELS",
                   help="the label volume the mesh was made from (dicer fix's output): smooth.surface_from_labels "
                        "fits its staircase, not a merged mesh's steps; default: the mesh's own faces")
    _add_config_options(p)

    p = command("export", cmd_export, "write the mesh for a solver or viewer (format from the file extension)")
    p.add_argument("mesh", metavar="MESH", help="mesh (.vtu)")
    p.add_argument("-o", "--output", required=True, metavar="MODEL", help="model.inp (Abaqus/CalculiX) or model.vtu (ParaView)")
    p.add_argument("--order", type=int, choices=(1, 2), help="element order (overrides export.order)")
    _add_materials_option(p)
    _add_config_options(p)

    p = command("surface", cmd_surface, "a closed STL surface per material (for CAD and viewing)")
    p.add_argument("mesh", metavar="MESH", help="mesh (.vtu), e.g. smoothed.vtu or model.vtu")
    p.add_argument("-o", "--output", required=True, metavar="FOLDER",
                   help="folder to write <material>.stl into (binary STL, mm, scanner coordinates)")
    p.add_argument("--material", action="append", metavar="NAME",
                   help="only this material (repeatable; default: every material in the mesh)")
    _add_materials_option(p)
    _add_config_options(p)


def _add_report_commands(command) -> None:
    """quality, cohort, phantom: reports and test images."""
    p = command("quality", cmd_quality, "element quality report (JSON, optional HTML)")
    p.add_argument("mesh", metavar="MESH", help="mesh (.vtu)")
    p.add_argument("-o", "--output", required=True, metavar="JSON", help="quality report (.json)")
    p.add_argument("--labels", metavar="LABELS", help="label volume the mesh came from (for voxel counts)")
    p.add_argument("--html", metavar="HTML", help="also write a readable HTML report")
    p.add_argument("--csv", metavar="CSV",
                   help="also write every element's metrics, one line per element in automesh's metrics "
                        "columns (edge ratio, scaled Jacobian, skew, volume)")
    p.add_argument("--original", metavar="LABELS",
                   help="the segmentation before downsampling (full resolution): adds each material's volume change "
                        "against it")
    p.add_argument("--histogram", metavar="PNG", help="also draw the scaled-Jacobian histogram per material")
    p.add_argument("--model-picture", metavar="PNG",
                   help="also draw the model: exterior coloured by material, and cut open")
    p.add_argument("--node-classes", metavar="PNG", help="also draw the boundary node-class counts (smoothed mesh)")
    p.add_argument("--picture", action="append", metavar="PNG",
                   help="a further picture to embed in the HTML report, e.g. segmentation.png (repeatable)")
    p.add_argument("--stage-report", action="append", metavar="JSON",
                   help="a stage report (fix.json, merge.json, smooth.json) to include (repeatable); named by "
                        "what it holds, not by its file name")
    _add_materials_option(p)
    _add_config_options(p)

    # @FILE: arguments read from a file, one a line (a cohort's hundreds of paths pass the
    # length a shell command line may have)
    p = command("cohort", cmd_cohort, "cohort overview: one table row per patient from its quality.json and benchmarks",
                epilog="@FILE in place of arguments reads them from FILE, one a line.", fromfile_prefix_chars="@")
    p.add_argument("reports", metavar="QUALITY_JSON", nargs="+",
                   help="quality reports, one per patient; the patient is the report's folder name")
    p.add_argument("-o", "--output", required=True, metavar="HTML", help="cohort overview (.html)")
    p.add_argument("--tsv", metavar="TSV", help="also write the table as tab-separated values")
    p.add_argument("--benchmarks", metavar="PATH", nargs="+",
                   help="Snakemake benchmark files <patient>/<stage>.tsv (seconds and peak memory), or the folder "
                        "holding their patient folders (every stage file there)")
    p.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only")

    p = command("phantom", cmd_phantom, "write a synthetic CT phantom (HU, with noise) for demos and tests")
    p.add_argument("name", metavar="NAME", help="phantom name: head, long_bone, shell, sphere, block")
    p.add_argument("-o", "--output", required=True, metavar="IMAGE", help="image file (.nii.gz, .nrrd, .mha)")
    p.add_argument("--size", type=int, default=None, help="voxels along the longest axis (phantom default if omitted)")
    p.add_argument("--noise", type=float, default=None, help="Gaussian noise sigma in HU (phantom default if omitted)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the noise (default 0)")
    p.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only")


_REUSES_MEMORY = {"run", "merge", "smooth", "export", "quality"}
"""Commands that keep freed memory for their next arrays (dicer.pages.reuse_freed_memory):
at 256³, alternating, 'run' 37-38 -> 31-34 s, 'merge' 10-11 -> 7-9 s, 'export' to .inp
5.8-7.3 -> 5.0-6.5 s, 'quality' 4.1-4.2 -> 3.8-4.0 s, 'smooth' 7.8-11.3 -> 7.5-10.2 s
(kernel time 2.1-2.6 -> 1.4-1.8 s, peak 1.58 -> 2.00 GB); 'mesh' measured no quicker."""


class _LineFormatter(logging.Formatter):
    """Lines of the library's modules (``dicer.io.images``: an input's header) read as the
    stage's own: ``dicer fix: head.npy: ...``, not the module's name."""

    def format(self, record: logging.LogRecord) -> str:
        if record.name.startswith("dicer."):
            stage = f"{_Stage.current}: " if _Stage.current else ""
            return f"dicer {stage}{record.getMessage()}"
        return super().format(record)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command in _REUSES_MEMORY:
        reuse_freed_memory()  # before any thread allocates
    logging.basicConfig(
        level=logging.WARNING if getattr(args, "quiet", False) else logging.INFO,
        format="%(name)s %(message)s", stream=sys.stderr,
    )
    for handler in logging.getLogger().handlers:
        handler.setFormatter(_LineFormatter("%(name)s %(message)s"))
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    previous_int = signal.signal(signal.SIGINT, _interrupt) if main_thread else None
    try:
        try:
            _check_paths(args)
        except OSError as exc:  # a path the system refuses to look at (too long, a loop of links)
            raise DicerError(f"{exc.filename}: cannot use this path ({exc.strerror}); give a shorter or "
                             "another path") from None
        # a command's several outputs replace the old files together, or none does
        # ('run' publishes its folder itself: its stages read each other's files)
        # a stage's process takes nearly all its memory fresh: ordinary pages unless the job
        # is large (dicer.pages); 'run' reuses what its stages free, where numpy's huge pages
        # measured faster
        _warn_of_unused_settings(args)
        run = args.command == "run"
        ordinary = not run and not large_job(_input_paths(args))
        with contextlib.nullcontext() if run else all_or_nothing(), \
                ordinary_pages(unless_set=True) if ordinary else contextlib.nullcontext(), one_blas_thread():
            args.func(args)
        check_stop()
    except Terminated as exc:
        kept = "; ".join(getattr(exc, "__notes__", ())) or "no output of the unfinished step was kept"
        print(f"error: terminated (SIGTERM, e.g. a cluster time limit); {kept}", file=sys.stderr)
        return 143
    except DicerError as exc:
        # one line, also where a path holds a line break
        print("error: " + str(exc).replace("\r", "\\r").replace("\n", "\\n"), file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        kept = "; ".join(getattr(exc, "__notes__", ())) or "no output was kept"
        print(f"error: interrupted; {kept}", file=sys.stderr)
        # CPython marks the process interrupted when a KeyboardInterrupt leaves an exec()
        # or eval() of a string (a namedtuple or dataclass made while a module is
        # imported), caught or not, and under "python -m" then ends it by SIGINT instead
        # of exiting 130; the next exec of a string clears the mark
        exec("None")
        return 130
    except MemoryError:
        print("error: out of memory; downsample the labels (downsample.factor) or use a larger machine", file=sys.stderr)
        return 2
    finally:
        stop_requested.clear()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if previous_int is not None:
            signal.signal(signal.SIGINT, previous_int)
    return 0


class Terminated(BaseException):
    """SIGTERM arrived: unwinds like KeyboardInterrupt, so every temporary file is removed."""


def _interrupt(signum, frame):
    from dicer.io import atomic

    atomic.stop_requested.append(KeyboardInterrupt)  # as for SIGTERM: raised again if this one is lost
    raise KeyboardInterrupt()


def _terminate(signum, frame):
    from dicer.io import atomic

    atomic.stop_requested.append(Terminated)  # raised again before any rename if this one is lost
    raise Terminated()


if __name__ == "__main__":
    raise SystemExit(main())
