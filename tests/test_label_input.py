"""Label volumes made elsewhere: ``dicer run --labels`` and ``dicer labels``, the labels
section of the config, and material names in every mesh and export."""

import base64
import gzip
import json
import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest
import yaml

from dicer.cli import main
from dicer.config import load_config
from dicer.errors import DicerError
from dicer.io.images import read_labels
from dicer.io.meshes import read_mesh
from dicer.labels import resolve_materials

REPO = Path(__file__).resolve().parents[1]

# MNI-like placement: 1.5 mm voxels, origin at a negative corner, sform and qform code 4 (MNI152)
SPACING = 1.5
OFFSET = (-90.0, -125.0, -71.0)


def write_nifti(path: Path, array: np.ndarray, spacing=SPACING, offset=OFFSET, code=4) -> None:
    """A NIfTI-1 .nii.gz written byte by byte, as other tools write them (not through ITK)."""
    head = bytearray(348)
    struct.pack_into("<i", head, 0, 348)
    struct.pack_into("<8h", head, 40, 3, *array.shape, 1, 1, 1, 1)
    struct.pack_into("<2h", head, 70, 4, 16)  # int16
    # pixdim beyond the three axes: free too (a time step, or a birth date)
    struct.pack_into("<8f", head, 76, 1.0, spacing, spacing, spacing, 19840512.0, 445566.0, 1, 1)
    struct.pack_into("<f", head, 108, 352.0)
    struct.pack_into("<f", head, 112, 1.0)
    # free text as some tools fill it: a patient's name and record numbers (never passed on)
    head[14:14 + 10] = b"MRN445566\0"  # db_name
    head[148:148 + 26] = b"made by a tool: DOE^JANE\0"  # descrip
    head[228:228 + 10] = b"ACC998877\0"  # aux_file
    head[328:328 + 8] = b"DOEJANE\0"  # intent_name
    # and numbers that mean nothing for a label volume: a record number, a birth date
    struct.pack_into("<3f", head, 56, 445566.0, 19840512.0, 7.0)  # intent_p1..3
    struct.pack_into("<2f", head, 132, 19840512.0, 445566.0)  # slice_duration, toffset
    struct.pack_into("<2i", head, 140, 445566, 19840512)  # glmax, glmin
    struct.pack_into("<2h", head, 252, code, code)
    struct.pack_into("<6f", head, 256, 0.0, 0.0, 0.0, *offset)
    struct.pack_into("<4f", head, 280, spacing, 0, 0, offset[0])
    struct.pack_into("<4f", head, 296, 0, spacing, 0, offset[1])
    struct.pack_into("<4f", head, 312, 0, 0, spacing, offset[2])
    head[344:348] = b"n+1\0"
    with gzip.open(path, "wb") as f:
        f.write(bytes(head) + b"\0" * 4 + array.astype("<i2").tobytes(order="F"))


def affine(path: Path) -> dict:
    """The placement fields of a NIfTI-1 header: pixdim, qform and sform with their codes."""
    with gzip.open(path, "rb") as f:
        head = f.read(348)
    return {
        "pixdim": struct.unpack("<3f", head[80:92]),
        "codes": struct.unpack("<2h", head[252:256]),
        "quatern": struct.unpack("<6f", head[256:280]),
        "srow": struct.unpack("<12f", head[280:328]),
    }


def seven_labels() -> np.ndarray:
    """Nested boxes of a FreeSurfer-like labelling: 3 grey around 2 white around 4, a
    cerebellum split into 7 and 8, a table 99 under it and a blob of 98 in a corner."""
    a = np.zeros((20, 18, 14), np.int16)
    a[2:18, 2:16, 2:12] = 3
    a[5:15, 7:13, 5:10] = 2
    a[8:12, 9:11, 6:8] = 4
    a[2:10, 2:6, 2:6] = 7
    a[10:18, 2:6, 2:6] = 8
    a[:, :, 0] = 99
    a[0:2, 16:18, 12:14] = 98
    return a


CONFIG = {
    "labels": {"map": {2: "white_matter", 3: "grey_matter", 7: "cerebellum", 8: "cerebellum"}, "drop": [98, 99]},
    "materials": [
        {"name": "cerebellum", "youngs_modulus": 0.002, "poissons_ratio": 0.49, "density": 1.04e-9},
        {"name": "white_matter", "youngs_modulus": 0.003, "poissons_ratio": 0.49, "density": 1.04e-9},
        {"name": "grey_matter", "youngs_modulus": 0.001, "poissons_ratio": 0.49, "density": 1.04e-9},
    ],
}


def _cli(*args) -> int:
    return main([str(a) for a in args])


@pytest.fixture
def labelled(tmp_path):
    src = tmp_path / "aseg.nii.gz"
    write_nifti(src, seven_labels())
    config = tmp_path / "labels.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    return src, config


def test_resolve_materials_map_drop_merge():
    config = load_config(settings=CONFIG)
    lut, materials = resolve_materials([0, 2, 3, 4, 7, 8, 98, 99], config)
    assert lut == {0: 0, 2: 1, 3: 2, 4: 3, 7: 4, 8: 4, 98: 0, 99: 0}
    assert [m["name"] for m in materials] == ["white_matter", "grey_matter", "label_4", "cerebellum"]
    assert materials[0]["youngs_modulus"] == 0.003 and materials[3]["youngs_modulus"] == 0.002
    assert materials[2] == {"name": "label_4", "youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1.0e-9}


def test_a_map_name_that_an_unmapped_value_takes_is_refused():
    """{5: label_7} with 7 unmapped joined values 5 and 7 into one material in silence."""
    with pytest.raises(DicerError, match=r"seg: labels.map names value 5 'label_7', the name value 7 takes when it "
                                         r"has no entry, so the two would become one material; map value 7 too"):
        resolve_materials([0, 5, 7], {"labels": {"map": {"5": "label_7"}}}, source="seg")
    # asked for: both mapped to it, or the other value dropped or absent
    assert resolve_materials([0, 5, 7], {"labels": {"map": {"5": "label_7", "7": "label_7"}}})[0] == {0: 0, 5: 1, 7: 1}
    assert resolve_materials([0, 5, 7], {"labels": {"map": {"5": "label_7"}, "drop": [7]}})[0] == {0: 0, 5: 1, 7: 0}
    assert resolve_materials([0, 5], {"labels": {"map": {"5": "label_7"}}})[0] == {0: 0, 5: 1}


def test_a_map_name_without_materials_entry_beside_an_unused_entry_is_warned_of(caplog):
    """labels.map: marrow, materials: bone_marrow -- a typo that would give marrow E 1000 MPa."""
    settings = {"labels": {"map": {"3": "cortical_bone", "17": "marrow"}},
                "materials": [{"name": "cortical_bone", "youngs_modulus": 17000.0},
                              {"name": "bone_marrow", "youngs_modulus": 0.5}]}
    with caplog.at_level("INFO", logger="dicer"):
        _, materials = resolve_materials([0, 3, 17], load_config(settings=settings))
    assert materials[1] == {"name": "marrow", "youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1.0e-9}
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "names marrow, which no materials entry has" in warned[0]
    assert "entries bone_marrow are used by no label" in warned[0]
    caplog.clear()
    settings["materials"][1]["name"] = "marrow"  # spelt alike: no warning
    with caplog.at_level("INFO", logger="dicer"):
        _, materials = resolve_materials([0, 3, 17], load_config(settings=settings))
    assert materials[1]["youngs_modulus"] == 0.5
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    # no materials section: the defaults (a scan's soft_tissue and bone) are no entries the
    # user wrote, so "used by no label" would be a false alarm on every mapped run
    caplog.clear()
    with caplog.at_level("INFO", logger="dicer"):
        resolve_materials([0, 3, 17], load_config(settings={"labels": settings["labels"]}))
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_a_map_name_and_an_entry_that_differ_in_case_are_refused():
    """labels.map: white_matter, materials: White_Matter -- solvers read both as WHITE_MATTER, and
    the material took default properties (E 1000 MPa for 0.003) with a warning, exit 0."""
    settings = {"labels": {"map": {"2": "white_matter", "3": "grey_matter"}},
                "materials": [{"name": "White_Matter", "youngs_modulus": 0.003},
                              {"name": "grey_matter", "youngs_modulus": 0.002}]}
    with pytest.raises(DicerError, match=r"seg: labels.map names 'white_matter' and the materials entry "
                                         r"'White_Matter': the names differ only in case"):
        resolve_materials([0, 2, 3], load_config(settings=settings), source="seg")
    settings["materials"][0]["name"] = "white_matter"
    _, materials = resolve_materials([0, 2, 3], load_config(settings=settings))
    assert [m["youngs_modulus"] for m in materials] == [0.003, 0.002]


def test_materials_entries_without_a_map_are_warned_of(caplog):
    """materials [soft_tissue E 2.5, bone E 12000] and no labels.map: both labels took the
    default E 1000 MPa (the stages, taking label i as the i-th entry, gave the user's)."""
    settings = {"materials": [{"name": "soft_tissue", "youngs_modulus": 2.5},
                              {"name": "bone", "youngs_modulus": 12000.0}]}
    with caplog.at_level("INFO", logger="dicer"):
        _, materials = resolve_materials([0, 1, 2], load_config(settings=settings))
    assert [m["youngs_modulus"] for m in materials] == [1000.0, 1000.0]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["labels: the config's materials soft_tissue, bone are used by no label: without labels.map "
                      "each label value is its own material (label_<value>, default properties: E 1000 MPa); name "
                      "the values with labels.map, e.g. labels.map: {1: soft_tissue, 2: bone}"]
    # the default materials (no entries the user wrote): quiet
    caplog.clear()
    with caplog.at_level("INFO", logger="dicer"):
        resolve_materials([0, 1, 2], load_config())
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_an_image_of_grey_values_given_as_labels_is_refused(tmp_path, capsys):
    """An MR given to --labels was meshed as 814 materials of scattered voxels, exit 0."""
    from dicer.image import Volume
    from dicer.io.images import write_image

    g = np.indices((24, 24, 24)) - 11.5
    head = np.sqrt((g ** 2).sum(0)) < 10
    rng = np.random.default_rng(0)
    mr = np.where(head, 1500 + rng.normal(0, 300, head.shape), 0).clip(0).astype(np.int16)
    write_image(Volume(mr, (1.0, 1.0, 1.0)), tmp_path / "t1.nii.gz")
    assert main(["run", "--labels", str(tmp_path / "t1.nii.gz"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    distinct = np.unique(mr).size
    assert err.startswith(f"error: {tmp_path / 't1.nii.gz'}: {distinct} distinct values, and only ")
    assert "looks like an image of grey values, not labels; give it as the IMAGE of dicer run" in err
    assert not (tmp_path / "out").exists()
    # the same head in blocks of 3 voxels a side, each its own value (an atlas): taken
    blocks = [(g[0] + 12).astype(int) // 3, (g[1] + 12).astype(int) // 3, (g[2] + 12).astype(int) // 3]
    atlas = np.where(head, 1 + blocks[0] * 64 + blocks[1] * 8 + blocks[2], 0).astype(np.int16)
    assert np.unique(atlas).size > 100
    write_image(Volume(atlas, (1.0, 1.0, 1.0)), tmp_path / "atlas.nii.gz")
    assert main(["labels", str(tmp_path / "atlas.nii.gz"), "-o", str(tmp_path / "mapped.nii.gz"), "-q"]) == 0


def test_a_map_value_the_volume_lacks_beside_an_unnamed_value_is_warned_of(caplog):
    """labels.map: 12 where the volume holds 21: label 21 would fall to default properties."""
    settings = {"labels": {"map": {"3": "bone", "12": "brain"}}}
    with caplog.at_level("INFO", logger="dicer"):
        lut, materials = resolve_materials([0, 3, 21], load_config(settings=settings))
    assert [m["name"] for m in materials] == ["bone", "label_21"]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["labels: labels.map names value(s) 12 that the volume does not hold, while value(s) 21 "
                      "have no labels.map entry (materials label_21, default properties); check the label values"]
    caplog.clear()
    # a map value absent from this volume (a cohort config), every value present named: quiet
    with caplog.at_level("INFO", logger="dicer"):
        resolve_materials([0, 3], load_config(settings=settings))
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def _resolved(caplog, values, settings=None) -> tuple[list[dict], list[str]]:
    """The materials ``resolve_materials`` makes of ``values`` under ``settings``, and its warnings."""
    caplog.clear()
    with caplog.at_level("INFO", logger="dicer"):
        _, materials = resolve_materials(values, load_config(settings=settings))
    return materials, [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]


def test_a_drop_value_the_volume_lacks_beside_an_unnamed_value_is_warned_of(caplog):
    """labels.drop: [24] where the volume holds 42: label 42 was meshed at 1000 MPa, without a word."""
    materials, warned = _resolved(caplog, [0, 3, 42], {"labels": {"drop": [24]}})
    assert [m["name"] for m in materials] == ["label_3", "label_42"]
    assert warned == ["labels: labels.drop names value(s) 24 that the volume does not hold, while value(s) 3, 42 "
                      "are meshed without a labels.map entry (materials label_3, label_42, default properties); "
                      "check the label values"]
    # a value to drop absent from this volume (a cohort config), every value present named: quiet
    assert _resolved(caplog, [0, 3], {"labels": {"drop": [24], "map": {"3": "bone"}}})[1] == []


def test_a_label_left_to_default_properties_beside_given_ones_is_warned_of(caplog):
    """materials entries for label_2 and label_3 (E 5.5, 7.5 MPa) and none for label_1: it was
    meshed at 1000 MPa, said at info level only, so -q showed nothing."""
    given = {"materials": [{"name": "label_3", "youngs_modulus": 5.5}, {"name": "label_2", "youngs_modulus": 7.5}]}
    materials, warned = _resolved(caplog, [0, 1, 2, 3], given)
    assert [m["youngs_modulus"] for m in materials] == [1000.0, 7.5, 5.5]
    assert len(warned) == 1 and warned[0].startswith("labels: no materials entry for label_1: default properties")
    # no entries written: every label at the defaults, said as info
    assert not [m for m in _resolved(caplog, [0, 1, 2, 3])[1] if "no materials entry" in m]


def test_yaml_and_settings_keys_give_one_config(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("labels:\n  map: {3: brain}\n")
    assert load_config(path)["labels"] == load_config(settings={"labels": {"map": {"3": "brain"}}})["labels"]
    assert load_config(sets=["labels.map.3=brain"])["labels"]["map"] == {"3": "brain"}


@pytest.mark.parametrize("labels, message", [
    ({"map": {"x": "brain"}}, "labels.map"),
    ({"map": {"3": "9brain"}}, "labels.map.3"),
    ({"map": {"3": "brain"}, "drop": [3]}, "both in labels.map and in labels.drop"),
])
def test_bad_labels_section(labels, message):
    with pytest.raises(DicerError, match=re.escape(message)):
        load_config(settings={"labels": labels})


def _without_pixels(html: bytes) -> bytes:
    """The report with each figure as its PNG chunks but the pixels: base64 text and
    compressed pixels hold any three letters by chance ("DOE" in a figure of the head)."""

    def chunks(match):
        png, pos, kept = base64.b64decode(match.group(1)), 8, []
        while pos + 8 <= len(png):
            size, kind = struct.unpack_from(">I", png, pos)[0], png[pos + 4 : pos + 8]
            if kind != b"IDAT":
                kept.append(png[pos + 4 : pos + 8 + size])
            pos += 12 + size
        return b"".join(kept)

    return re.sub(rb"data:image/png;base64,([A-Za-z0-9+/=]+)", chunks, html)


def test_run_labels_end_to_end(labelled, tmp_path, caplog):
    src, config = labelled
    out = tmp_path / "out"
    caplog.set_level("INFO", logger="dicer")
    assert _cli("run", "--labels", src, "-o", out, "--config", config) == 0
    assert "labels: no materials entry for label_4: default properties" in caplog.text
    # the mapped labels keep the input's header: grid, qform, sform and codes
    assert affine(out / "labels.nii.gz") == affine(src)
    mapped = read_labels(out / "labels.nii.gz").array
    assert sorted(np.unique(mapped).tolist()) == [0, 1, 2, 3, 4]
    assert np.array_equal(mapped == 4, np.isin(seven_labels(), (7, 8)))
    assert not np.any(mapped[:, :, 0]) and not (out / "labels_ds.nii.gz").exists()  # factor 1: no downsample
    # the fixed labels (written through ITK) keep the placement too
    fixed = affine(out / "labels_fixed.nii.gz")
    assert fixed["srow"] == affine(src)["srow"] and fixed["pixdim"] == affine(src)["pixdim"]
    deck = (out / "model.inp").read_text()
    elsets = re.findall(r"^\*ELEMENT, TYPE=C3D8, ELSET=(\w+)$", deck, flags=re.M)
    assert elsets == ["white_matter", "grey_matter", "label_4", "cerebellum"]
    assert "*MATERIAL, NAME=cerebellum\n*ELASTIC\n0.002," in deck
    assert "LABEL_98" not in deck.upper() and "LABEL_99" not in deck.upper() and "LABEL_7" not in deck.upper()
    materials = json.loads((out / "materials.json").read_text())
    assert [m["name"] for m in materials["materials"]] == ["white_matter", "grey_matter", "label_4", "cerebellum"]
    assert materials["values"]["99"] == "background" and materials["values"]["8"] == "cerebellum"
    names = ["white_matter", "grey_matter", "label_4", "cerebellum"]
    for name in ("mesh.vtu", "merged.vtu", "smoothed.vtu", "model.vtu"):
        assert read_mesh(out / name).names == names, name
    assert meshio.read(out / "model.vtu").field_data["cerebellum"].tolist() == [4, 3]  # meshio's [tag, dim]
    # no free text of the input's header reaches an output
    for path in out.iterdir():
        data = gzip.decompress(path.read_bytes()) if path.name.endswith(".gz") else path.read_bytes()
        if path.suffix == ".html":
            data = _without_pixels(data)
        assert not any(text in data for text in (b"DOE", b"JANE", b"MRN445566", b"ACC998877")), path.name
        if path.name.endswith(".nii.gz"):  # nor its free numbers, nor the sizes of axes it has not
            assert not any(data[a:b].strip(b"\0") for a, b in ((32, 38), (56, 68), (74, 76), (120, 123), (132, 148)))
            assert struct.unpack_from("<4h", data, 48) == (1, 1, 1, 1)
            assert struct.unpack_from("<4f", data, 92) == (0.0, 0.0, 1.0, 1.0)  # the input's 1s stay
    # a rerun writes the same bytes
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    assert _cli("run", "--labels", src, "-o", tmp_path / "again", "--config", config) == 0
    for name, data in first.items():
        assert (tmp_path / "again" / name).read_bytes() == data, name


def test_run_labels_defaults_without_map(tmp_path, caplog):
    src = tmp_path / "seg.nii.gz"
    a = np.zeros((12, 10, 8), np.int16)
    a[2:10, 2:8, 2:6] = 5
    a[4:8, 4:6, 3:5] = 12
    write_nifti(src, a)
    out = tmp_path / "out"
    caplog.set_level("INFO", logger="dicer")
    assert _cli("run", "--labels", src, "-o", out) == 0
    err = caplog.text
    assert "no labels.map in the config: each of the 2 label value(s) is its own material" in err
    assert "default properties" in err
    assert affine(out / "labels.nii.gz") == affine(src)
    mapped = read_labels(out / "labels.nii.gz").array
    assert np.array_equal(mapped, np.where(a == 5, 1, np.where(a == 12, 2, 0)))
    deck = (out / "model.inp").read_text()
    assert re.findall(r"^\*ELEMENT, TYPE=C3D8, ELSET=(\w+)$", deck, flags=re.M) == ["label_5", "label_12"]
    assert read_mesh(out / "model.vtu").names == ["label_5", "label_12"]


@pytest.mark.parametrize("dim", [2, 3])
def test_a_npy_label_volume_takes_image_spacing(tmp_path, dim):
    """A .npy carries no voxel size: image.spacing gives it, as for a .npy scan (it was
    ignored, and the model came out at 1 mm voxels)."""
    a = np.zeros((20, 16, 6)[:dim], np.uint8)
    a[2:18, 2:14] = 1
    np.save(tmp_path / "seg.npy", a)
    spacing = [0.5, 0.25, 3.0][:dim]
    out = tmp_path / "out"
    assert _cli("run", "--labels", tmp_path / "seg.npy", "-o", out, "--set", f"image.spacing={spacing}",
                "--set", "smooth.coefficient=0", "--set", "merge.passes=[0,0,0]",
                "--set", "preset=explicit-dynamics") == 0  # no layer over the labels' box
    assert read_labels(out / "labels.nii.gz").spacing == pytest.approx(spacing)
    if dim == 3:  # the stages that read a .npy themselves take it too (they took 1 mm)
        assert _cli("mesh", tmp_path / "seg.npy", "-o", tmp_path / "m.vtu", "--set", f"image.spacing={spacing}") == 0
        assert read_mesh(tmp_path / "m.vtu").points.max(axis=0) == pytest.approx(np.multiply([18, 14, 6], spacing))
        assert _cli("fix", tmp_path / "seg.npy", "-o", tmp_path / "f.nii.gz", "--set", f"image.spacing={spacing}") == 0
        assert read_labels(tmp_path / "f.nii.gz").spacing == pytest.approx(spacing)
    points = read_mesh(out / "model.vtu").points[:, :dim]
    assert points.min(axis=0) == pytest.approx(np.multiply([2, 2], spacing[:2]).tolist() + [0.0] * (dim - 2))
    assert points.max(axis=0) == pytest.approx(np.multiply([18, 14, 6][:dim], spacing).tolist())


def test_a_npy_label_volume_without_image_spacing_is_warned_of(tmp_path, caplog):
    """A .npy label volume without image.spacing is meshed at 1 mm voxels, and the log says so
    once per read, naming the file, as for a .npy scan (it was said of a scan only: a 0.5 mm
    segmentation came out twice its size without a word)."""
    a = np.zeros((12, 10, 8), np.uint8)
    a[2:10, 2:8, 2:6] = 1
    np.save(tmp_path / "seg.npy", a)
    warning = "seg.npy: the file carries no voxel size; using 1 mm per axis (set image.spacing to override)"
    caplog.set_level("WARNING", logger="dicer")
    assert _cli("run", "--labels", tmp_path / "seg.npy", "-o", tmp_path / "out") == 0
    assert caplog.text.count(warning) == 1
    assert read_labels(tmp_path / "out" / "labels.nii.gz").spacing == pytest.approx([1.0, 1.0, 1.0])
    for stage, output in (("mesh", "m.vtu"), ("fix", "f.nii.gz")):
        caplog.clear()
        assert _cli(stage, tmp_path / "seg.npy", "-o", tmp_path / output) == 0
        assert caplog.text.count(warning) == 1, stage
    caplog.clear()
    assert read_labels(tmp_path / "seg.npy", spacing=0.5).spacing == pytest.approx([0.5, 0.5, 0.5])
    assert "voxel size" not in caplog.text


def test_run_labels_says_settings_it_does_not_read(tmp_path, caplog):
    """--set segment.keep=largest on a label volume not downsampled drops no floating part: said."""
    a = np.zeros((12, 10, 8), np.uint8)
    a[1:6, 1:9, 1:7] = 1
    a[8:11, 2:8, 2:6] = 1  # a second part
    np.save(tmp_path / "seg.npy", a)
    caplog.set_level("WARNING", logger="dicer")
    assert _cli("run", "--labels", tmp_path / "seg.npy", "-o", tmp_path / "out", "--set", "image.spacing=[1, 1, 1]",
                "--set", "segment.keep=largest", "--set", "fix.min_component_voxels=0") == 0
    assert ("run: --set segment.keep acts when the labels are downsampled, and these are not (downsample.factor 1, "
            "no downsample.voxel_size), so it changes nothing") in caplog.text
    assert json.loads((tmp_path / "out" / "quality.json").read_text())["parts"]["model"]["parts"] == 2


def test_a_fix_that_rewrites_most_of_the_model_says_so(tmp_path, caplog):
    """Shells under a voxel thick: the connectivity fixes rewrote 90 % of the voxels, said only
    per material (29 more ...); now as a whole, with the share."""
    n = 32
    r = np.sqrt(((np.indices((n, n, n)) - n / 2 + 0.5) ** 2).sum(axis=0))
    shells = np.where(r < n / 2 - 1, (r / (n / 2 - 1) * 30).astype(np.int32) + 1, 0) * 3
    np.save(tmp_path / "shells.npy", shells)
    assert _cli("labels", tmp_path / "shells.npy", "-o", tmp_path / "l.nii.gz", "--materials", tmp_path / "m.json",
                "--set", "image.spacing=[1, 1, 1]") == 0
    caplog.set_level("WARNING", logger="dicer")
    assert _cli("fix", tmp_path / "l.nii.gz", "-o", tmp_path / "f.nii.gz", "--materials", tmp_path / "m.json") == 0
    said = [m for m in (r.getMessage() for r in caplog.records) if "labelled voxels" in m]
    labelled = int(np.count_nonzero(shells))
    changed = int(np.count_nonzero(read_labels(tmp_path / "f.nii.gz").array != read_labels(tmp_path / "l.nii.gz").array))
    assert len(said) == 1 and said[0].startswith(f"fix: changed {changed} of the {labelled} labelled voxels")
    assert changed > 0.5 * labelled


def test_run_labels_with_downsample_keeps_placement(labelled, tmp_path):
    src, config = labelled
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "--config", config, "--set", "downsample.factor=2") == 0
    ds = affine(out / "labels_ds.nii.gz")
    # the first voxel's corner stays where it was: its centre moves half a coarse voxel inwards
    assert ds["srow"][3::4] == tuple(o + 0.75 for o in OFFSET)
    assert ds["srow"][0::5] == (3.0, 3.0, 3.0) and ds["pixdim"] == (3.0, 3.0, 3.0)


def test_downsample_with_the_materials_file_downsamples_as_run_labels_does(labelled, tmp_path):
    """`dicer labels`, then `dicer downsample --materials`: the label volume's defaults
    (no morphology, the plurality vote), as `dicer run --labels` takes them. Until 6 December
    2026 the stage took a scan's (opening and closing, the priority vote): 1,748 of 20,480
    voxels other than the run's on a 64^3 two-label volume, 29 of an atlas's parcels lost."""
    src, config = labelled
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "--config", config, "--set", "downsample.factor=2") == 0
    assert _cli("labels", src, "-o", tmp_path / "l.nii.gz", "--materials", tmp_path / "m.json",
                "--config", config) == 0
    assert _cli("downsample", tmp_path / "l.nii.gz", "-o", tmp_path / "d.nii.gz", "--materials", tmp_path / "m.json",
                "--config", config, "--set", "downsample.factor=2") == 0
    assert (tmp_path / "d.nii.gz").read_bytes() == (out / "labels_ds.nii.gz").read_bytes()
    # without the file: a scan's segmentation, the scan's defaults
    assert _cli("downsample", tmp_path / "l.nii.gz", "-o", tmp_path / "s.nii.gz", "--config", config,
                "--set", "downsample.factor=2", "--set", "materials=[{name: a}, {name: b}, {name: c}, {name: d}]") == 0
    assert (tmp_path / "s.nii.gz").read_bytes() != (out / "labels_ds.nii.gz").read_bytes()


def test_run_needs_image_or_labels(labelled, tmp_path, capsys):
    src, config = labelled
    assert _cli("run", "-o", tmp_path / "o") == 2
    assert "give either an IMAGE" in capsys.readouterr().err
    assert _cli("run", src, "--labels", src, "-o", tmp_path / "o") == 2
    assert not (tmp_path / "o").exists()


def test_run_labels_all_dropped_is_one_error(tmp_path, capsys):
    src = tmp_path / "seg.nii.gz"
    a = np.zeros((6, 6, 6), np.int16)
    a[1:5, 1:5, 1:5] = 3
    write_nifti(src, a)
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "--set", "labels.drop=[3]") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"error: {src}: no labelled voxels are left") and "labels.drop" in err[-1]
    assert not out.exists()


def test_run_labels_all_background_says_so(tmp_path, capsys):
    """A volume of zeros: nothing was dropped, so the message does not send the user to labels.drop."""
    src = tmp_path / "seg.npy"
    np.save(src, np.zeros((3, 3, 3), np.uint8))
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {src}: every voxel is 0 (background): there is nothing to mesh; give the label volume "
                   "of the part (labelled voxels 1 or more) (dicer run stopped at the labels stage)"]
    assert not out.exists()
    assert _cli("fix", src, "-o", tmp_path / "fixed.nii.gz") == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"error: {src}: every voxel is 0 (background): there is nothing to fix or mesh; give the label volume of "
        "the part (labelled voxels 1 or more)"]
    assert not (tmp_path / "fixed.nii.gz").exists()


def test_run_names_the_given_file_for_a_fault_of_its_labels(tmp_path, capsys):
    src = tmp_path / "seg.nii.gz"
    a = np.zeros((6, 6, 6), np.int16)
    a[2, 2, 2] = 1  # one voxel: smaller than fix.min_component_voxels
    write_nifti(src, a)
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"error: {src}: every part of the model is smaller than fix.min_component_voxels=64")
    assert err[-1].endswith(f"(dicer run stopped at the fix stage; its finished stage files are in {out}.failed)")
    assert not out.exists()


def test_run_writes_the_formats_workflow_exports_names(tmp_path):
    src = tmp_path / "seg.nii.gz"
    a = np.zeros((8, 8, 8), np.int16)
    a[2:6, 2:6, 2:6] = 1
    write_nifti(src, a)
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "-q", "--set", "workflow.exports=[inp,vtu,k,feb]") == 0
    models = sorted(p.name for p in out.glob("model.*") if p.suffix != ".png")
    assert models == ["model.feb", "model.inp", "model.k", "model.vtu"]
    assert "*ELEMENT_SOLID" in (out / "model.k").read_text()
    # a run without them: the models of the run before go, as the other stale results do
    assert _cli("run", "--labels", src, "-o", out, "-q") == 0
    assert sorted(p.name for p in out.glob("model.*") if p.suffix != ".png") == ["model.inp", "model.vtu"]


def test_run_refuses_a_2d_model_for_a_3d_only_format_before_any_stage(tmp_path, capsys):
    """Refused at the fix stage, two stages in, with out.failed left, and one of two such formats named."""
    src = tmp_path / "seg.npy"
    a = np.zeros((24, 24), np.uint8)
    a[3:19, 3:19] = 1
    np.save(src, a)
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "--set", "workflow.exports=[inp,feb]") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {src}: a 2D image, and workflow.exports names feb (febio), which holds 3D models only; "
                   "drop feb from workflow.exports"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seg.npy"]
    np.save(src, a[None])  # one slice of a 3D array: read as 2D too
    assert _cli("run", "--labels", src, "-o", out, "--set", "workflow.exports=[k,inp,feb]") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"error: {src}: a 2D image, and workflow.exports names k (lsdyna), feb (febio), which hold 3D models only; "
        "drop k and feb from workflow.exports")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seg.npy"]
    # an element type of the other dimension (found at the export, every stage run and out.failed left)
    assert _cli("run", "--labels", src, "-o", out, "--set", "export.element_type=C3D8") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"error: {src}: a 2D image, and export.element_type C3D8 is for 3D models; use one of CPS4, CPS4R, CPE4, CPE4R, or "
        "leave export.element_type out (null: the default of the order)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seg.npy"]


@pytest.mark.parametrize("sets, key", [
    (["workflow.exports=[inp,k]", "export.order=2"], "workflow.exports"),
    (["smooth.keep_bounding_planes=false"], "smooth.keep_bounding_planes"),
])
def test_run_refuses_contradicting_settings_before_any_stage(tmp_path, capsys, sets, key):
    src = tmp_path / "seg.nii.gz"
    write_nifti(src, np.ones((4, 4, 4), np.int16))
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, *[a for s in sets for a in ("--set", s)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: config with --set: key '{key}'")
    assert not out.exists() and not (tmp_path / "out.failed").exists()


def test_stage_commands_with_materials_file(labelled, tmp_path):
    src, config = labelled
    assert _cli("labels", src, "-o", tmp_path / "l.nii.gz", "--materials", tmp_path / "m.json",
                "--config", config) == 0
    assert _cli("fix", tmp_path / "l.nii.gz", "-o", tmp_path / "f.nii.gz", "--materials", tmp_path / "m.json") == 0
    assert _cli("mesh", tmp_path / "f.nii.gz", "-o", tmp_path / "m.vtu", "--materials", tmp_path / "m.json") == 0
    assert read_mesh(tmp_path / "m.vtu").names[3] == "cerebellum"
    # without the materials file the config's two default materials are too few
    assert _cli("mesh", tmp_path / "f.nii.gz", "-o", tmp_path / "n.vtu") == 2
    for ext in ("msh", "k", "vtu"):
        assert _cli("export", tmp_path / "m.vtu", "-o", tmp_path / f"model.{ext}",
                    "--materials", tmp_path / "m.json") == 0
    # Gmsh: $PhysicalNames read back by meshio
    msh = meshio.read(tmp_path / "model.msh")
    assert {k: int(v[0]) for k, v in msh.field_data.items()} == {
        "white_matter": 1, "grey_matter": 2, "label_4": 3, "cerebellum": 4}
    assert all(int(v[1]) == 3 for v in msh.field_data.values())
    # LS-DYNA: *PART titles are the material names, PID the label
    k = (tmp_path / "model.k").read_text()
    parts = re.findall(r"^\*PART\n(\w+)\n\$#[^\n]*\n\s*(\d+)", k, flags=re.M)
    assert parts == [("white_matter", "1"), ("grey_matter", "2"), ("label_4", "3"), ("cerebellum", "4")]
    assert read_mesh(tmp_path / "model.vtu").names == ["white_matter", "grey_matter", "label_4", "cerebellum"]


def test_order2_vtu_has_names(labelled, tmp_path):
    src, config = labelled
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "--config", config) == 0
    assert _cli("export", out / "smoothed.vtu", "-o", tmp_path / "q.vtu", "--order", "2",
                "--materials", out / "materials.json") == 0
    m = meshio.read(tmp_path / "q.vtu")
    assert {k: v.tolist() for k, v in m.field_data.items()} == {
        "white_matter": [1, 3], "grey_matter": [2, 3], "label_4": [3, 3], "cerebellum": [4, 3]}


@pytest.mark.parametrize("shape", [(1, 20, 24), (20, 24, 1)])
def test_a_single_slice_keeps_its_3d_grid_in_the_label_files(tmp_path, shape):
    """A one-slice 3D label file is meshed as a 2D image, but its label files stay on the
    input's 3D grid: the slice's position and axes are kept for viewers."""
    import SimpleITK as sitk

    lab = np.zeros(shape, np.uint8)
    lab[(slice(None),) * 3] = 1
    lab.reshape(-1)[:40] = 0
    img = sitk.GetImageFromArray(np.ascontiguousarray(lab.transpose(2, 1, 0)))  # [z, y, x]
    img.SetSpacing((3.0, 0.5, 2.0))
    img.SetOrigin((75.0, 100.0, -50.0))
    sitk.WriteImage(img, str(tmp_path / "slice.nii.gz"))
    assert main(["labels", str(tmp_path / "slice.nii.gz"), "-o", str(tmp_path / "l.nii.gz"), "-q"]) == 0
    assert main(["fix", str(tmp_path / "l.nii.gz"), "-o", str(tmp_path / "f.nii.gz"), "-q"]) == 0
    for name in ("l.nii.gz", "f.nii.gz"):
        out = sitk.ReadImage(str(tmp_path / name))
        assert out.GetSize() == shape and out.GetOrigin() == (75.0, 100.0, -50.0)
        assert out.GetSpacing() == (3.0, 0.5, 2.0)
        assert np.array_equal(sitk.GetArrayFromImage(out).transpose(2, 1, 0), lab)


def test_image_spacing_beside_a_header_spacing_is_said_to_be_unused(tmp_path, caplog):
    """A micro-CT exported with 1 mm in its header: image.spacing was dropped without a word."""
    src = tmp_path / "seg.nii.gz"
    write_nifti(src, seven_labels())
    caplog.set_level("INFO", logger="dicer")
    assert _cli("run", "--labels", src, "-o", tmp_path / "out", "--set", "image.spacing=[0.5,0.5,0.5]") == 0
    assert caplog.text.count("image.spacing is set ([0.5, 0.5, 0.5]), but the file carries its own voxel size "
                             "(1.5 x 1.5 x 1.5 mm), which is used") == 1
    assert read_labels(tmp_path / "out" / "labels.nii.gz").spacing == (1.5, 1.5, 1.5)


def test_quality_and_surface_name_materials_as_the_mesh_does(labelled, tmp_path, capsys):
    """A label volume's mesh carries its materials' names: quality and surface took the
    config's (soft_tissue, bone) for them, and surface wrote white matter to grey_matter.stl."""
    src, config = labelled
    out = tmp_path / "out"
    assert _cli("run", "--labels", src, "-o", out, "--config", config) == 0
    names = ["white_matter", "grey_matter", "label_4", "cerebellum"]
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q.json") == 0  # the default config
    assert set(json.loads((tmp_path / "q.json").read_text())["materials"]) == set(names)
    assert _cli("surface", out / "smoothed.vtu", "-o", tmp_path / "stl") == 0
    assert sorted(p.stem for p in (tmp_path / "stl").glob("*.stl")) == sorted(names)
    # labels of another voxel size than the mesh's, and a stage report that is no object: one error line each
    write_nifti(tmp_path / "other.nii.gz", seven_labels(), spacing=3.0)
    capsys.readouterr()
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q2.json", "--labels", tmp_path / "other.nii.gz") == 2
    assert "other.nii.gz: the labels' voxels are 3 x 3 x 3 mm but the mesh's 1.5 x 1.5 x 1.5 mm" in capsys.readouterr().err
    # the raw atlas on the mesh's own grid (labels before labels.map): 0 voxels for most materials, exit 0
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q2.json", "--labels", src) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {src}: ") and " elements of the mesh hold no voxel of their material in these " \
        "labels, so it was not made from them; give the label volume the mesh was made from" in err
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q5.json", "--labels", out / "labels_fixed.nii.gz") == 0
    # an original that is not the mesh's segmentation: the raw atlas, or another scan's labels
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q4.json", "--original", src) == 2
    assert "aseg.nii.gz: the original segmentation holds label 99, past the mesh's 4 materials" in capsys.readouterr().err
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q4.json", "--original", tmp_path / "other.nii.gz") == 2
    assert "other.nii.gz: the original segmentation spans 60 x 54 x 42 mm from" in capsys.readouterr().err
    # a slice of it: its areas would be taken for volumes
    from dicer.image import Volume
    from dicer.io.images import write_image

    write_image(Volume(seven_labels()[:, :, 0].astype(np.int16), (1.5, 1.5)), tmp_path / "slice.nii.gz")
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q4.json", "--original", tmp_path / "slice.nii.gz") == 2
    assert "slice.nii.gz: a 2D segmentation for a 3D mesh" in capsys.readouterr().err
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q4.json", "--original", out / "labels.nii.gz") == 0
    (tmp_path / "list.json").write_text("[1, 2, 3]")
    assert _cli("quality", out / "smoothed.vtu", "-o", tmp_path / "q3.json", "--html", tmp_path / "q3.html",
                "--stage-report", tmp_path / "list.json") == 2
    assert "list.json: not a stage report (a JSON object" in capsys.readouterr().err
    assert not (tmp_path / "q2.json").exists() and not (tmp_path / "q3.json").exists()


def _slicer_nrrd(path: Path, array: np.ndarray, names: list[tuple[int, str]]) -> Path:
    """A 3D Slicer segmentation file: ``array`` (x, y, z) or (layer, x, y, z) uint8, with
    Slicer's segment fields for ``names`` [(label value, name)], one layer per segment when 4D."""
    import gzip

    layered = array.ndim == 4
    segments = "".join(f"Segment{i}_ID:=Segment_{i + 1}\nSegment{i}_LabelValue:={v}\n"
                       f"Segment{i}_Layer:={i if layered else 0}\nSegment{i}_Name:={name}\n"
                       for i, (v, name) in enumerate(names))
    sizes = " ".join(map(str, array.shape))
    header = (f"NRRD0004\ntype: uint8\ndimension: {array.ndim}\nspace: left-posterior-superior\nsizes: {sizes}\n"
              f"space directions: {'none ' if layered else ''}(1,0,0) (0,1,0) (0,0,1)\n"
              f"kinds: {'list ' if layered else ''}domain domain domain\nencoding: gzip\nspace origin: (0,0,0)\n"
              + segments + "\n")
    data = np.ascontiguousarray(array.transpose(tuple(range(array.ndim))[::-1])).tobytes()
    path.write_bytes(header.encode() + gzip.compress(data))
    return path


def test_a_layered_slicer_segmentation_is_refused_with_the_export_to_make(tmp_path, capsys):
    """3D Slicer stores overlapping segments as layers, one per component of a 4D NRRD: the
    error said 'colour or vector data ... convert it to greyscale', which would mix the layers."""
    layers = np.zeros((2, 6, 5, 4), np.uint8)  # layer, x, y, z
    layers[0, 1:5, 1:4, 1:3] = 1
    layers[1, 2:4, 2:3, 1:3] = 2
    path = _slicer_nrrd(tmp_path / "bones.seg.nrrd", layers, [(1, "femur"), (2, "tibia")])
    capsys.readouterr()
    assert _cli("run", "--labels", path, "-o", tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {path}: a segmentation in 2 layers of overlapping "
                                                    "segments (2 segments; 3D Slicer's .seg.nrrd)"), err
    assert "export it as one labelmap" in err and "greyscale" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bones.seg.nrrd"]


def test_slicer_segments_named_apart_stay_apart(caplog):
    """Segments whose names differ only in letters outside ASCII or past 32 characters became one
    material without a word: two tissues with one set of properties and no interface."""
    from dicer.labels import segment_map

    long = "Left hippocampus subfield CA1 head "
    caplog.clear()
    assert segment_map({1: "Muskel Ä", 2: "Muskel Ö", 3: "Knochen", 4: "Ünïcode/name"}, "k.seg.nrrd") == {
        "1": "Muskel_A", "2": "Muskel_O", "3": "Knochen", "4": "Unicode_name"}
    assert caplog.records == []
    assert segment_map({1: long + "part", 2: long + "tail", 3: "Amygdala", 12: long + "x"}, "h.seg.nrrd") == {
        "1": "Left_hippocampus_subfield_CA1_1", "2": "Left_hippocampus_subfield_CA1_2", "3": "Amygdala",
        "12": "Left_hippocampus_subfield_CA1_12"}
    assert [r.getMessage() for r in caplog.records] == [
        "labels: segments of h.seg.nrrd named apart come out alike as material names, so each takes its label "
        "value: 'Left hippocampus subfield CA1 head part' -> Left_hippocampus_subfield_CA1_1, 'Left hippocampus "
        "subfield CA1 head tail' -> Left_hippocampus_subfield_CA1_2, 'Left hippocampus subfield CA1 head x' -> "
        "Left_hippocampus_subfield_CA1_12; give labels.map to name them"]
    # segments of one name share their material ("Bone " is "Bone"), and take its smallest value;
    # said, as two tissues named alike lose the interface between them
    caplog.clear()
    assert segment_map({1: "Bone", 2: "Bone", 3: "Skin"}, "b.seg.nrrd") == {"1": "Bone", "2": "Bone", "3": "Skin"}
    assert [r.getMessage() for r in caplog.records] == [
        "labels: segments of b.seg.nrrd share a name and become one material: 'Bone' (values 1, 2); give labels.map "
        "to keep them apart"]
    assert segment_map({1: "Bone", 2: "Bone ", 3: "Bone."}) == {"1": "Bone_1", "2": "Bone_1", "3": "Bone_3"}
    # letters NFKD keeps whole are spelled, not dropped
    assert segment_map({1: "Øre", 2: "Straße"}) == {"1": "Ore", "2": "Strasse"}
    # a new name another segment has already: the label values name the materials
    caplog.clear()
    assert segment_map({1: "Muscle", 2: "Muscle!", 3: "Muscle_1"}, "m.seg.nrrd") == {}
    assert [r.getMessage() for r in caplog.records] == [
        "labels: the segment names of m.seg.nrrd do not name the materials (two come out alike even with their "
        "label values); give labels.map to name them"]


def test_a_slicer_segmentation_names_its_materials_after_its_segments(tmp_path, caplog):
    """The segments' names (femur, tibia) were ignored: the materials came out as label_1, label_2."""
    lab = np.zeros((12, 10, 8), np.uint8)
    lab[1:11, 1:9, 1:4] = 1
    lab[1:11, 1:9, 4:7] = 2
    lab[4:7, 4:7, 7] = 3
    path = _slicer_nrrd(tmp_path / "knee.seg.nrrd", lab, [(1, "Left femur"), (2, "tibia"), (3, "3rd (patella)")])
    config = tmp_path / "c.yaml"
    config.write_text("materials:\n  - {name: tibia, youngs_modulus: 17000}\n")
    assert _cli("labels", path, "-o", tmp_path / "l.nii.gz", "--materials", tmp_path / "m.json", "--config",
                config) == 0
    materials = json.loads((tmp_path / "m.json").read_text())["materials"]
    assert [(m["name"], m["youngs_modulus"]) for m in materials] == [
        ("Left_femur", 1000.0), ("tibia", 17000.0), ("s_3rd_patella", 1000.0)]
    # labels.map replaces the segments' names
    assert _cli("labels", path, "-o", tmp_path / "l.nii.gz", "--materials", tmp_path / "m.json",
                "--set", "labels.map={1: bone, 2: bone, 3: kneecap}") == 0
    assert [m["name"] for m in json.loads((tmp_path / "m.json").read_text())["materials"]] == ["bone", "kneecap"]
    # names that cannot name materials (alike but for case): said, and the values name them
    _slicer_nrrd(path, lab, [(1, "Bone"), (2, "bone"), (3, "patella")])
    caplog.clear()
    assert _cli("labels", path, "-o", tmp_path / "l.nii.gz", "--materials", tmp_path / "m.json") == 0
    assert [m["name"] for m in json.loads((tmp_path / "m.json").read_text())["materials"]] == [
        "label_1", "label_2", "label_3"]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and warned[0].startswith(f"labels: the segment names of {path} do not name the "
                                                     "materials (names Bone and bone differ only in case")


def test_label_volumes_of_the_wrong_kind_say_what_they_look_like(tmp_path, capsys, caplog):
    """A CT given as labels, a label volume given as the image, labels resampled by linear
    interpolation and a volume with no background were refused or meshed with advice that did
    not name the likely cause."""
    import SimpleITK as sitk

    from dicer.image import Volume
    from dicer.io.images import write_image

    lab = np.zeros((10, 9, 8), np.float32)
    lab[2:8, 2:7, 2:6] = 1
    lab[4:6, 4:6, 3:5] = 2
    # a detached NRRD header (.nhdr and its .raw), as images are read
    sitk.WriteImage(sitk.GetImageFromArray(lab.astype(np.uint8).T), str(tmp_path / "knee.nhdr"))
    assert np.array_equal(read_labels(tmp_path / "knee.nhdr").array, lab.astype(np.uint8))
    # resampled by linear interpolation
    smooth = lab.copy()
    smooth[5, 5, 4] = 1.9999998
    write_image(Volume(smooth, (1.0, 1.0, 1.0)), tmp_path / "resampled.nii.gz")
    with pytest.raises(DicerError, match=r"resampled.nii.gz: 1 of 720 labels are not whole numbers \(e.g. 1.99999976\)"
                                         r": a label volume resampled or smoothed by linear interpolation mixes its "
                                         r"classes; resample it by nearest neighbour, or round it"):
        read_labels(tmp_path / "resampled.nii.gz")
    # a CT
    write_image(Volume(np.full((6, 6, 6), -1000.0, np.float32), (1.0, 1.0, 1.0)), tmp_path / "ct.nii.gz")
    with pytest.raises(DicerError, match="min -1000.*a CT's air is near -1000.*are segmented from the IMAGE of dicer "
                                         "run"):
        read_labels(tmp_path / "ct.nii.gz")
    # a label volume as the image
    write_image(Volume(lab, (1.0, 1.0, 1.0)), tmp_path / "labels.nii.gz")
    assert _cli("run", tmp_path / "labels.nii.gz", "-o", tmp_path / "out") == 2
    assert "the image's values span 0 .. 2; move the range inside the image's values; an image of 3 whole values " \
           "from 0 is most likely a label volume: give it with --labels" in capsys.readouterr().err
    # no background: the whole box is solid, said (values in whole: %g printed 15229600 as 1.52296e+07)
    write_image(Volume(lab.astype(np.int32) + 15229600, (1.0, 1.0, 1.0)), tmp_path / "shifted.nii.gz")
    caplog.clear()
    assert _cli("labels", tmp_path / "shifted.nii.gz", "-o", tmp_path / "l.nii.gz") == 0
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"labels: every voxel of {tmp_path / 'shifted.nii.gz'} is a material (values 15229600, 15229601, 15229602), "
        "so the model fills "
        "the whole image box; if the background has a value of its own (a header's scl_inter, an atlas's 'unknown'), "
        "set labels.drop: [value]"]


def test_lines_of_the_image_reader_name_the_stage_not_the_module():
    """The reader's warnings (``dicer.io.images``) read as the stage's own lines on stderr."""
    import logging

    from dicer.cli import _LineFormatter, _Stage

    record = logging.LogRecord("dicer.io.images", logging.WARNING, __file__, 1,
                               "%s: the file carries no voxel size", ("seg.npy",), None)
    formatter = _LineFormatter("%(name)s %(message)s")
    with _Stage("fix"):
        assert formatter.format(record) == "dicer fix: seg.npy: the file carries no voxel size"
    assert formatter.format(record) == "dicer seg.npy: the file carries no voxel size"
    own = logging.LogRecord("dicer", logging.INFO, __file__, 1, "fix: done", (), None)
    assert formatter.format(own) == "dicer fix: done"
