"""A label atlas of 100+ materials end to end through the ``dicer`` command (in-process).

Voronoi regions inside a ball (as the parcels of a brain atlas) -> fix -> mesh -> merge
(plane merging: 130 labels; graded coarsening: 104 larger parcels) -> smooth -> export
(.inp) -> quality, with one named material per label in the config; and the same labels
with a config that does not name them, stopped before the fix.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import yaml

from dicer.cli import main
from dicer.image import Volume
from dicer.io.images import write_labels

N, KINDS = 40, 130


def atlas_labels(n: int = N, kinds: int = KINDS, seed: int = 0) -> np.ndarray:
    """(n, n, n) uint16: the Voronoi regions of ``kinds`` random seeds inside a ball of
    radius 0.47 n, labelled 1..kinds; background outside the ball."""
    rng = np.random.default_rng(seed)
    centres = np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.linalg.norm(centres - n / 2, axis=1) < 0.47 * n
    direction = rng.normal(size=(kinds, 3))
    radius = 0.45 * n * rng.uniform(0, 1, kinds) ** (1 / 3)  # uniform in the ball
    seeds = n / 2 + direction / np.linalg.norm(direction, axis=1)[:, None] * radius[:, None]
    lab = np.zeros(n**3, np.uint16)
    lab[inside] = 1 + ((centres[inside, None, :] - seeds) ** 2).sum(axis=2).argmin(axis=1)
    return lab.reshape(n, n, n)


def touching_pairs(lab: np.ndarray) -> set[tuple[int, int]]:
    """Pairs (a, b), 0 < a < b, of labels with voxels sharing a face."""
    pairs = set()
    for axis in range(lab.ndim):
        lo = lab.take(range(lab.shape[axis] - 1), axis).ravel()
        hi = lab.take(range(1, lab.shape[axis]), axis).ravel()
        keep = (lo != hi) & (lo > 0) & (hi > 0)
        pairs |= set(zip(np.minimum(lo, hi)[keep].tolist(), np.maximum(lo, hi)[keep].tolist()))
    return pairs


def _names(kinds: int) -> list[str]:
    # atlas-like names: shared prefixes and underscores, distinct set names
    return [f"{('Left', 'Right')[i % 2]}_Gyrus_{i // 2 + 1}" for i in range(kinds)]


CHAINS = {"planes": (N, KINDS), "templates": (64, 104)}
"""merge.method -> (image side, labels) of the atlas it is tried on."""


@pytest.fixture(scope="module", params=sorted(CHAINS))
def chain(request, tmp_path_factory):
    """The files and reports of the whole chain on the atlas, per merge method."""
    method = request.param
    n, kinds = CHAINS[method]
    folder = tmp_path_factory.mktemp(f"atlas-{method}")
    write_labels(Volume(atlas_labels(n, kinds), (1.0, 1.0, 1.0)), folder / "atlas.nii.gz")
    materials = [{"name": n, "youngs_modulus": 1.0 + i, "poissons_ratio": 0.45} for i, n in enumerate(_names(kinds))]
    # no pillow layer: the deck's sets and the quality report's elements those of the labels' voxels
    (folder / "atlas.yaml").write_text(yaml.safe_dump({"preset": "explicit-dynamics", "materials": materials,
                                                       "merge": {"method": method}}))
    steps = [
        ["fix", "atlas.nii.gz", "-o", "fixed.nii.gz"],
        ["mesh", "fixed.nii.gz", "-o", "mesh.vtu"],
        ["merge", "mesh.vtu", "-o", "merged.vtu", "--report", "merge.json"],
        ["smooth", "merged.vtu", "-o", "smoothed.vtu", "--report", "smooth.json", "--labels", "fixed.nii.gz"],
        ["export", "smoothed.vtu", "-o", "model.inp"],
        ["quality", "smoothed.vtu", "-o", "quality.json", "--labels", "fixed.nii.gz"],
    ]
    for command, *rest in steps:
        argv = [command] + [str(folder / a) if "." in a else a for a in rest]
        assert main([*argv, "--config", str(folder / "atlas.yaml"), "-q"]) == 0, command
    return folder, method, kinds


def test_every_stage_takes_a_hundred_and_more_materials(chain):
    from dicer.io.images import read_labels
    from dicer.io.meshes import read_mesh

    chain, method, kinds = chain
    fixed = read_labels(chain / "fixed.nii.gz").array
    present = np.unique(fixed[fixed > 0])
    assert present.size == kinds
    merged, mesh = read_mesh(chain / "merged.vtu"), read_mesh(chain / "mesh.vtu")
    assert mesh.n_cells == np.count_nonzero(fixed) and merged.n_cells <= mesh.n_cells
    assert np.array_equal(np.unique(merged.material), present)
    report = json.loads((chain / "merge.json").read_text())
    if method == "planes":
        # (a merge region crossing a material interface keeps its plane; here every plane
        # of the ball crosses one, so merging refuses them for that reason)
        steps = report["steps"]
        assert [s["axis"] for s in steps] == ["x", "y", "z"] and all(s["blocked_material"] > 0 for s in steps)
    else:
        # parcels some 12 voxels across: coarse cells and templates inside the larger ones
        assert report["method"] == "templates" and sum(report["elements_by_level"]["1"].values()) > 500
        assert merged.n_cells < mesh.n_cells

    # smoothing: no inverted element, the quality floor kept, every node classified
    smooth = json.loads((chain / "smooth.json").read_text())
    assert smooth["inverted_elements"] == 0 and smooth["min_scaled_jacobian"] >= 0.2
    classes = smooth["node_classes"]
    assert sum(classes.values()) == smooth["nodes"] == merged.n_points
    assert sum(classes[c] for c in "ABCDEF") == smooth["boundary_nodes"] and classes["X"] == 0
    assert min(classes[c] for c in "ABCDEF") > 0  # a triple corner (F) needs three materials

    # the deck: an element set, a material and a section per material, an interface node
    # set per pair of touching materials, each under its configured name
    text = (chain / "model.inp").read_text()
    names = _names(kinds)
    elsets = re.findall(r"^\*ELEMENT, TYPE=C3D8, ELSET=(\w+)$", text, re.M)
    assert elsets == [names[k - 1] for k in present]
    assert re.findall(r"^\*MATERIAL, NAME=(\w+)$", text, re.M) == elsets
    assert len(re.findall(r"^\*SOLID SECTION, ELSET=(\w+), MATERIAL=\1$", text, re.M)) == kinds
    nsets = set(re.findall(r"^\*NSET, NSET=(\w+)$", text, re.M))
    pairs = touching_pairs(fixed)
    assert len(pairs) > 500
    assert {f"{names[a - 1]}_{names[b - 1]}" for a, b in pairs} <= nsets
    assert len(nsets) == len(pairs) + kinds + 1  # + <name>_BOUNDARY, EXTERIOR (no node on a bounding plane)

    # quality: every material with its voxels, the volume of each kept within a few per cent
    quality = json.loads((chain / "quality.json").read_text())
    assert quality["inverted_elements"] == 0 and quality["elements"] == merged.n_cells
    assert sorted(quality["materials"]) == sorted(names)
    assert sum(m["voxels"] for m in quality["materials"].values()) == np.count_nonzero(fixed)
    changes = [abs(m["volume_change_percent"]) for m in quality["materials"].values()]
    assert np.median(changes) < 5


def test_unnamed_labels_stop_before_the_fix(tmp_path, capsys):
    # the default config names two materials: the fix refuses the atlas at once, with one
    # error line naming the highest label, and writes nothing
    write_labels(Volume(atlas_labels(16, 20, seed=1), (1.0, 1.0, 1.0)), tmp_path / "atlas.nii.gz")
    code = main(["fix", str(tmp_path / "atlas.nii.gz"), "-o", str(tmp_path / "fixed.nii.gz")])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1
    assert err[0].startswith("error: ") and "label 20 found" in err[0] and "names only 2" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atlas.nii.gz"]


@pytest.mark.parametrize("stage", ["fix", "labels"])
def test_more_than_255_labels_are_written_as_uint16(tmp_path, stage):
    """Label files read with more than 255 values come as int16; the stages that write them
    on their input's NIfTI header store them as uint16, the values unchanged."""
    import gzip
    import struct

    from dicer.io.images import read_labels

    lab = atlas_labels(24, 300, seed=2)
    present = np.unique(lab[lab > 0])
    assert present.size > 255
    write_labels(Volume(lab, (1.0, 1.0, 1.0)), tmp_path / "atlas.nii.gz")
    out = tmp_path / "out.nii.gz"
    materials = [{"name": n, "youngs_modulus": 1.0} for n in _names(int(lab.max()))]
    (tmp_path / "atlas.yaml").write_text(yaml.safe_dump({"materials": materials, "fix": {"min_component_voxels": 0}}))
    settings = ["--config", str(tmp_path / "atlas.yaml")] if stage == "fix" else []
    assert main([stage, str(tmp_path / "atlas.nii.gz"), "-o", str(out), *settings, "-q"]) == 0
    with gzip.open(out) as f:
        assert struct.unpack("<h", f.read(72)[70:72])[0] == 512  # NIfTI datatype: uint16
    written = read_labels(out).array
    if stage == "labels":  # values 1..K in increasing order: here the same values
        assert np.array_equal(written, np.searchsorted(np.r_[0, present], lab))
    else:
        assert np.unique(written[written > 0]).size > 255 and np.count_nonzero(written != lab) < 0.05 * lab.size
