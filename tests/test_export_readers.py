"""Strict read-back of the text decks: dicer's Abaqus reader against meshio's, and every
strict reader (Abaqus, PATRAN, LS-DYNA) against truncated and corrupted files."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import meshio
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dicer.config import load_config
from dicer.errors import DicerError
from dicer.export import export_mesh, prepare_model
from dicer.export.abaqus import _meshio_abaqus_types, check_abaqus, read_abaqus
from dicer.export.lsdyna import read_lsdyna
from dicer.export.patran import read_patran
from dicer.export.textparse import FormatError, layout_of, parse_records
from dicer.mesh.voxel import voxel_mesh


def _config(n_materials: int, **export) -> dict:
    rng = np.random.default_rng(n_materials)
    materials = [{"name": f"mat{k}", "youngs_modulus": float(rng.uniform(0.5, 2e4)),
                  "poissons_ratio": float(rng.uniform(0.0, 0.49)), "density": float(rng.uniform(1e-10, 3e-9))}
                 for k in range(1, n_materials + 1)]
    return load_config(settings={"materials": materials, "export": export})


@pytest.fixture
def mesh():
    lab = np.zeros((4, 5, 6), np.uint8)
    lab[:, :, :3] = 1
    lab[1:3, 1:4, 3:] = 2
    return voxel_mesh(lab, spacing=(0.5, 0.75, 1.25), origin=(-3.0, 10.0, 0.125))


# --- the strict Abaqus reader agrees with meshio's --------------------------------------------


@st.composite
def meshes(draw):
    """A random small voxel mesh (2D or 3D), its material count and coordinates of any sign and size."""
    dim = draw(st.sampled_from([2, 3]))
    shape = tuple(draw(st.integers(1, 4)) for _ in range(dim))
    k = draw(st.integers(1, 4))
    flat = draw(st.lists(st.integers(0, k), min_size=int(np.prod(shape)), max_size=int(np.prod(shape))))
    labels = np.array(flat, np.uint8).reshape(shape)
    if not labels.any():
        labels.flat[draw(st.integers(0, labels.size - 1))] = draw(st.integers(1, k))
    spacing = tuple(draw(st.floats(0.01, 5.0)) for _ in range(dim))
    origin = tuple(draw(st.floats(-1e3, 1e3)) for _ in range(dim))
    mesh = voxel_mesh(labels, spacing=spacing, origin=origin)
    # smoothed-looking coordinates, scaled over many decades (exponents far from the usual few)
    seed = draw(st.integers(0, 2**32 - 1))
    scale = 10.0 ** draw(st.integers(-40, 40))
    noise = np.random.default_rng(seed).normal(scale=0.2, size=mesh.points.shape)
    if dim == 2:
        noise[:, 2] = 0.0
    mesh.points = (mesh.points + noise) * scale
    mesh.spacing, mesh.origin = np.multiply(mesh.spacing, scale), np.multiply(mesh.origin, scale)  # the same model
    return mesh, k


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=meshes(), order=st.sampled_from([1, 2]), digits=st.sampled_from([9, 13]))
def test_strict_reader_agrees_with_meshio(case, order, digits):
    mesh, k = case
    config = _config(k, order=order, digits=digits)
    model = prepare_model(mesh, config)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.inp"
        info = export_mesh(mesh, path, config)  # the default read-back is the strict reader
        assert info["verified"] and info["elements"] == mesh.n_cells
        got = read_abaqus(path)
        with _meshio_abaqus_types():
            ref = meshio.read(path, file_format="abaqus")
    # nodes: bit for bit what Python's float() gives for every printed number
    assert got["points"].shape == (model.n_points, 3)
    assert np.array_equal(got["points"], ref.points)
    assert np.array_equal(got["points"].view(np.int64), np.asarray(ref.points, np.float64).view(np.int64))
    # elements: one block per material in label order, meshio's block data in the same order
    assert [name for name, _ in got["blocks"]] == [config["materials"][lab - 1]["name"] for lab in model.labels()]
    assert len(ref.cells) == len(got["blocks"])
    for (name, ids), block in zip(got["blocks"], ref.cells):
        assert np.array_equal(got["cells"][ids], block.data)
        assert np.array_equal(ref.cell_sets[name][[b.data is block.data for b in ref.cells].index(True)],
                              np.arange(ids.size))
    assert np.array_equal(got["cells"], model.cells)
    assert got["element_type"] == model.element_type
    # node sets: meshio's point sets, 0-based
    assert sorted(got["node_sets"]) == sorted(ref.point_sets) == sorted(model.node_sets)
    for name, ids in got["node_sets"].items():
        assert np.array_equal(ids, ref.point_sets[name]) and np.array_equal(ids, model.node_sets[name])
    # element sets: meshio gives each block's members as indices into that block
    for name, ids in got["element_sets"].items():
        per_block = [np.flatnonzero(np.isin(block_ids, ids)) for _, block_ids in got["blocks"]]
        assert [a.tolist() for a in per_block] == [np.asarray(a).tolist() for a in ref.cell_sets[name]]
    n_faces = sum(rows.shape[0] for rows in (model.exterior, model.cavities) if rows is not None)
    assert sum(ids.size for ids in got["element_sets"].values()) == n_faces
    # the strict check passes on the deck as written
    for label in model.labels():
        name = config["materials"][label - 1]["name"]
        assert got["materials"][name]["elastic"][0] == pytest.approx(model.props[label]["youngs_modulus"], rel=1e-11)
        assert got["sections"][name] == (name, [1.0] if mesh.dim == 2 else [])


def test_strict_and_meshio_checks_write_the_same_deck(tmp_path, mesh):
    a = export_mesh(mesh, tmp_path / "a.inp", load_config())
    b = export_mesh(mesh, tmp_path / "b.inp", load_config(sets=["export.verify=meshio"]))
    assert a == {**b, "file": "a.inp"}
    # export.verify changes how the deck is checked, not the deck (nor its heading's hash)
    assert (tmp_path / "a.inp").read_bytes() == (tmp_path / "b.inp").read_bytes()


def test_textparse_layout_and_exact_values():
    record = b"     12, 1.25000000e+00,-3.00000000e-07,     7,\n   8, 0.00000000e+00\n"
    layout = layout_of(record)
    assert layout.kinds == "iffiif" and layout.length == len(record)
    ints, reals = parse_records(np.frombuffer(record * 3, np.uint8), layout)
    assert ints.tolist() == [[12, 7, 8]] * 3
    assert reals.tolist() == [[1.25, -3e-07, 0.0]] * 3
    bad = record.replace(b"  12", b" 1 2")
    with pytest.raises(FormatError, match="not right-aligned") as info:
        parse_records(np.frombuffer(record + bad, np.uint8), layout)
    assert info.value.offset == len(record) + 4
    with pytest.raises(FormatError, match="record of 10 bytes"):
        parse_records(np.frombuffer(record + record[:10], np.uint8), layout)


# --- truncated and corrupted files ------------------------------------------------------------


def _lines(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True)


def _line_no(lines: list[bytes], prefix: bytes, after: int = 0) -> int:
    """0-based index of the first line from ``after`` on that starts with ``prefix``."""
    return next(i for i in range(after, len(lines)) if lines[i].startswith(prefix))


@pytest.mark.parametrize("order", [1, 2])
def test_abaqus_reader_rejects_truncated_decks(tmp_path, mesh, order):
    export_mesh(mesh, tmp_path / "m.inp", _config(2, order=order))
    data = (tmp_path / "m.inp").read_bytes()
    lines = _lines(tmp_path / "m.inp")
    first_element = _line_no(lines, b"*ELEMENT") + 1
    cases = {
        # cut inside a line
        len(data) // 2 + 3: r"line \d+, column \d+: the file ends in the middle of this line \(truncated\?\)",
        # cut at a line end inside the node block: no elements at all
        len(b"".join(lines[:12])): r"at the end of the file: no \*NODE or no \*ELEMENT block \(truncated\?\)",
        # cut at a line end inside the first element block (order 2: between a record's two lines)
        len(b"".join(lines[: first_element + 3])): (
            r"at the end of the file: ELSET=mat1 has no \*SOLID SECTION \(truncated\?\)" if order == 1 else
            rf"line {first_element + 3}, column 1: a \*ELEMENT line of ELSET=mat1: a record of \d+ bytes"),
    }
    for size, message in cases.items():
        cut = tmp_path / f"cut{size}.inp"
        cut.write_bytes(data[:size])
        with pytest.raises(DicerError, match=rf"^{re.escape(str(cut))}: {message}") as info:
            read_abaqus(cut)
        assert "export the mesh again" in str(info.value)
    # cut at a line end among the materials
    cut = tmp_path / "cut_material.inp"
    cut.write_bytes(b"".join(lines[: _line_no(lines, b"*DENSITY") + 2]))
    with pytest.raises(DicerError, match=r"at the end of the file: ELSET=mat1 has no \*SOLID SECTION"):
        read_abaqus(cut)
    (tmp_path / "empty.inp").write_bytes(b"")
    with pytest.raises(DicerError, match="the file is empty"):
        read_abaqus(tmp_path / "empty.inp")


def test_abaqus_reader_names_the_line_and_column_of_a_corrupted_number(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.inp", _config(2))
    lines = _lines(tmp_path / "m.inp")
    node = _line_no(lines, b"*NODE") + 5  # the 5th node line
    cases = [
        (node, 9, b"x", r"'x' where a digit belongs"),  # a digit of the x coordinate
        (node, 16, b"E", r"'E' where 'e' belongs"),
        (node, 17, b"*", r"'\*' where '\+' or '-' belongs"),
        (node, 1, b"7", r"an integer that is not right-aligned in its field"),  # "7 5," for "  5,"
        (_line_no(lines, b"*ELEMENT") + 2, 8, b";", r"';' where ',' belongs"),
        (_line_no(lines, b"*NSET, NSET=EXTERIOR") + 2, 4, b" ", r"' ' where ',' belongs"),
        (_line_no(lines, b"*NSET, NSET=EXTERIOR") + 2, 3, b"-", r"'-' where a digit belongs"),
    ]
    for row, col, byte, message in cases:
        bad = list(lines)
        bad[row] = bad[row][: col - 1] + byte + bad[row][col:]
        path = tmp_path / f"bad{row}_{col}.inp"
        path.write_bytes(b"".join(bad))
        with pytest.raises(DicerError, match=rf"^{re.escape(str(path))}: line {row + 1}, column {col}: .*{message}"):
            read_abaqus(path)


def test_strict_check_finds_changed_numbers_the_reader_accepts(tmp_path, mesh):
    config = _config(2)
    model = prepare_model(mesh, config)
    export_mesh(mesh, tmp_path / "m.inp", config)
    lines = _lines(tmp_path / "m.inp")
    node = _line_no(lines, b"*NODE") + 5
    element = _line_no(lines, b"*ELEMENT") + 4  # element 4 (mat1 holds elements 1, 2, 3, ...)
    nset = _line_no(lines, b"*NSET, NSET=Z0") + 1
    cases = [
        (node, lines[node].replace(b"e+01", b"e+02", 1), r"node coordinates differ by 9\d\.\d mm"),
        (element, lines[element][:-3] + b"99\n", rf"connectivity of element {int(lines[element][:3])} differs"),
        (nset, b"  3" + lines[nset][3:], "node set Z0 differs"),
        (_line_no(lines, b"*DENSITY") + 1, b"2e-09\n", r"materials .* read back, expected"),
    ]
    for row, text, message in cases:
        bad = list(lines)
        bad[row] = text
        (tmp_path / "bad.inp").write_bytes(b"".join(bad))
        read_abaqus(tmp_path / "bad.inp")  # well-formed: only the comparison can tell
        with pytest.raises(DicerError, match=message):
            check_abaqus(tmp_path / "bad.inp", model)


def test_corrupted_write_fails_the_export_and_leaves_no_file(tmp_path, mesh, monkeypatch):
    import dataclasses

    from dicer.export import abaqus, registry

    write = abaqus.write_abaqus
    keep = {"bytes": None}

    def corrupting(model, path):
        write(model, path)
        data = Path(path).read_bytes()
        Path(path).write_bytes(data[: keep["bytes"]])  # as if the disk had kept less

    monkeypatch.setitem(registry.BY_SUFFIX, ".inp", dataclasses.replace(abaqus.FORMAT, write=corrupting))
    export_mesh(mesh, tmp_path / "full.inp", _config(2), check=False)
    size = (tmp_path / "full.inp").stat().st_size
    (tmp_path / "full.inp").unlink()
    keep["bytes"] = size // 2  # inside the element blocks: both checks see it
    for verify in ("strict", "meshio"):
        with pytest.raises(DicerError, match=r"m\.inp: read-back check failed: .*the file was not written"):
            export_mesh(mesh, tmp_path / "m.inp", _config(2, verify=verify))
        assert not list(tmp_path.iterdir())
    # the last material's section cut off: meshio's reader ignores materials, the strict check does not
    keep["bytes"] = size - 50
    with pytest.raises(DicerError, match=r"m\.inp: read-back check failed: line \d+, column \d+: the file "
                                         r"ends in the middle of this line \(truncated\?\)"):
        export_mesh(mesh, tmp_path / "m.inp", _config(2))
    assert export_mesh(mesh, tmp_path / "m.inp", _config(2, verify="meshio"))["verified"]


def test_patran_reader_rejects_truncated_and_corrupted_files(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.out", _config(2))
    data = (tmp_path / "m.out").read_bytes()
    lines = _lines(tmp_path / "m.out")
    (tmp_path / "cut.out").write_bytes(data[: len(data) // 2 + 5])
    with pytest.raises(DicerError, match=r"cut\.out: the file ends in the middle of a line \(truncated\?\)"):
        read_patran(tmp_path / "cut.out")
    (tmp_path / "cut2.out").write_bytes(b"".join(lines[:-40]))  # whole lines: packets missing
    with pytest.raises(DicerError, match=r"cut2\.out: the file ends after \d+ lines, before its element header cards"):
        read_patran(tmp_path / "cut2.out")
    row = 4 + 3 * 6 + 1  # coordinates of node 7
    bad = list(lines)
    bad[row] = bad[row][:20] + b"x" + bad[row][21:]
    (tmp_path / "bad.out").write_bytes(b"".join(bad))
    with pytest.raises(DicerError, match=rf"bad\.out: line {row + 1}: node coordinate: '.*x.*' in columns "
                                         r"17-32 is not a number"):
        read_patran(tmp_path / "bad.out")


def test_lsdyna_reader_rejects_truncated_and_corrupted_files(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.k", _config(2))
    data = (tmp_path / "m.k").read_bytes()
    lines = _lines(tmp_path / "m.k")
    (tmp_path / "cut.k").write_bytes(data[: len(data) // 2 + 5])
    with pytest.raises(DicerError, match=r"cut\.k: the file ends in the middle of a line \(truncated\?\)"):
        read_lsdyna(tmp_path / "cut.k")
    (tmp_path / "cut2.k").write_bytes(b"".join(lines[:-3]))  # whole lines: *END missing
    with pytest.raises(DicerError, match=r"cut2\.k: an LS-DYNA keyword file starts with \*KEYWORD and ends "
                                         r"with \*END"):
        read_lsdyna(tmp_path / "cut2.k")
    row = _line_no(lines, b"*ELEMENT_SOLID") + 2 + 4  # element 5
    bad = list(lines)
    bad[row] = bad[row][:30] + b"?" + bad[row][31:]
    (tmp_path / "bad.k").write_bytes(b"".join(bad))
    with pytest.raises(DicerError, match=rf"bad\.k: line {row + 1}: \*ELEMENT_SOLID node: '.*\?.*' in columns "
                                         r"25-32 is not an integer"):
        read_lsdyna(tmp_path / "bad.k")
    got = read_lsdyna(tmp_path / "m.k")
    assert got["points"].shape == (mesh.n_points, 3) and np.array_equal(got["cells"], mesh.cells)


@pytest.mark.parametrize("order", [1, 2])
def test_abaqus_reader_names_a_line_cut_short_or_run_on(tmp_path, mesh, order):
    # a line of another length breaks the record grid the block's end is found on; the error
    # must still name that line
    export_mesh(mesh, tmp_path / "m.inp", _config(2, order=order))
    lines = _lines(tmp_path / "m.inp")
    for key, offset in ((b"*NODE", 5), (b"*ELEMENT", 3), (b"*NSET, NSET=EXTERIOR", 1)):
        row = _line_no(lines, key) + offset
        for text in (lines[row][:10] + lines[row][11:], lines[row][:10] + b"1" + lines[row][10:]):
            bad = list(lines)
            bad[row] = text
            (tmp_path / "bad.inp").write_bytes(b"".join(bad))
            with pytest.raises(DicerError, match=rf"bad\.inp: line {row + 1}, column 1[0-6]: .* belongs"):
                read_abaqus(tmp_path / "bad.inp")


def test_patran_names_the_materials_in_packet_21(tmp_path):
    import numpy as np

    from dicer.config import load_config
    from dicer.export import export_mesh
    from dicer.export.patran import read_patran
    from dicer.mesh.voxel import voxel_mesh

    labels = np.zeros((4, 3, 3), np.uint8)
    labels[:2] = 1
    labels[2:, :2] = 2
    labels[3, 2, 2] = 3
    mesh = voxel_mesh(labels)
    config = load_config(settings={"materials": [{"name": "white_matter_left"}, {"name": "white_matter_right"},
                                                 {"name": "csf"}]})
    for order in (1, 2):
        config["export"]["order"] = order
        path = tmp_path / f"m{order}.out"
        export_mesh(mesh, path, config)  # read back and checked, components included
        got = read_patran(path)["components"]
        # names cut to the card's 12 columns, made distinct by their label where the cut makes them equal
        assert {k: v[0] for k, v in got.items()} == {1: "white_matt_1", 2: "white_matt_2", 3: "csf"}
        for label, (_, pairs) in got.items():
            assert np.array_equal(pairs[:, 1], np.flatnonzero(mesh.material == label) + 1)
            assert set(pairs[:, 0].tolist()) == {12 if order == 1 else 112}
        assert sum(len(v[1]) for v in got.values()) == mesh.n_cells == 31


@pytest.mark.parametrize("names, want", [
    # a suffixed name meeting a name that fits: the suffixed one is cut shorter
    (["white_matter_a", "white_matter_b", "white_matt_1"], ["white_mat_1", "white_matt_2", "white_matt_1"]),
    # a name that fits stays the user's own, not another material's
    (["white_matt_2", "white_matter_a", "white_matter_b"], ["white_matt_2", "white_mat_2", "white_matt_3"]),
    # a plain name that already ends in its own label keeps it
    (["abcdefghij_1x", "abcdefghij_1y"], ["abcdefghij_1", "abcdefghij_2"]),
    (["a" * 20] * 1 + ["a" * 13 + str(i) for i in range(11)], None),
    # names that differ in case only once cut: one name to a solver reading upper case
    (["Left_Hippocampus_head", "LEFT_HIPPOCAMpus_tail", "left_hippocaMPUS_body"],
     ["Left_Hippo_1", "LEFT_HIPPO_2", "left_hippo_3"]),
    # a name ending in a number keeps it whole: label_697050 would read as another label
    (["label_69705095", "label_2", "Cortex_left_1001"], ["lab_69705095", "label_2", "Cortex_1001"]),
])
def test_patran_component_names_are_unique(names, want):
    from types import SimpleNamespace

    from dicer.export.patran import component_names

    model = SimpleNamespace(names=dict(enumerate(names, start=1)), labels=lambda: range(1, len(names) + 1))
    got = component_names(model)
    assert len({v.upper() for v in got.values()}) == len(names) and all(len(v) <= 12 for v in got.values())
    if want is not None:
        assert [got[k] for k in range(1, len(names) + 1)] == want


@pytest.mark.parametrize("records, star_at", [(10, 3), (5000, 4097), (40000, 21000), (40000, None), (1, 0)])
def test_block_end_finds_the_next_keyword_in_doubling_windows(records, star_at):
    from dicer.export.abaqus import _block_end

    stride = 12
    lines = [b"%11d\n" % i for i in range(records)]
    head = b"*NODE\n"
    if star_at is not None:
        lines[star_at] = b"*ELSET, X\n1\n"[:stride - 1] + b"\n"
    data = head + b"".join(lines)
    arr = np.frombuffer(data, np.uint8)
    a = len(head)
    expected = a + star_at * stride if star_at is not None else len(data)
    assert _block_end(data, arr, a, stride) == expected
    assert _block_end(data, arr, a, 0) == expected  # the byte scan agrees


def test_abaqus_reader_refuses_a_second_block_of_one_element_set(tmp_path, mesh):
    """Looked up in a set since an atlas's 12,000 blocks made the linear search most of the check."""
    export_mesh(mesh, tmp_path / "m.inp", _config(2))
    text = (tmp_path / "m.inp").read_text()
    assert "ELSET=mat2" in text
    (tmp_path / "twice.inp").write_text(text.replace("*ELEMENT, TYPE=C3D8, ELSET=mat2", "*ELEMENT, TYPE=C3D8, ELSET=mat1"))
    with pytest.raises(DicerError, match=r"a second element block for ELSET=mat1"):
        read_abaqus(tmp_path / "twice.inp")
