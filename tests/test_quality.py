import json

import numpy as np
import pytest

from dicer.config import load_config
from dicer.image import Volume
from dicer.mesh.voxel import voxel_mesh
from dicer.quality import quality_report, render_html


def test_report_counts_and_metrics():
    labels = np.zeros((4, 4, 4), np.uint8)
    labels[:2] = 1
    labels[2:, :2] = 2
    mesh = voxel_mesh(labels, spacing=(1.0, 1.0, 2.0))
    mesh.points[mesh.lattice[:, 0] == 4, 0] += 0.5  # stretch the x = 4 face: elements still valid
    report = quality_report(mesh, load_config(), labels=Volume(labels, (1.0, 1.0, 2.0)))
    assert report["elements"] == 48 and report["nodes"] == mesh.n_points
    soft, bone = report["materials"]["soft_tissue"], report["materials"]["bone"]
    assert soft["elements"] == 32 and bone["elements"] == 16
    assert soft["voxels"] == 32 and soft["volume_mm^3"] == pytest.approx(64.0)
    # 8 bone elements touch x = 4: each grows by half a voxel in x
    assert bone["volume_mm^3"] == pytest.approx(32.0 + 8 * 0.5 * 2.0)
    assert bone["volume_change_percent"] == pytest.approx(25.0)
    assert report["inverted_elements"] == 0 and report["poor_elements"] == 0
    assert report["scaled_jacobian"]["max"] == pytest.approx(1.0)
    assert report["edge_ratio"]["max"] == pytest.approx(2.0)
    assert report["element_volume_mm^3"]["total"] == pytest.approx(96.0 + 8.0)
    # volume over largest face: 1 mm for the 1 x 1 x 2 mm voxels, as for the stretched ones
    assert report["characteristic_length_mm"]["min"] == pytest.approx(1.0)
    assert report["characteristic_length_mm"]["max"] == pytest.approx(1.0)
    assert "<h2>characteristic_length_mm</h2>" in render_html(report)


def test_stretched_elements_are_counted_against_the_edge_ratio_limit(tmp_path, caplog):
    # a 4 x 1 x 1 bar on 0.2 x 1 x 1 mm voxels: edge ratio 5; one end element pulled out to 6
    mesh = voxel_mesh(np.ones((4, 1, 1), np.uint8), spacing=(0.2, 1.0, 1.0))
    report = quality_report(mesh, load_config())
    assert report["stretched_elements"] == 0 and report["stretched_threshold"] == 20.0
    assert report["edge_ratio"]["max"] == pytest.approx(5.0)
    assert quality_report(mesh, load_config(), stretched_edge_ratio=4.5)["stretched_elements"] == 4
    mesh.points[mesh.lattice[:, 0] == 4, 0] += 5.8  # the last element 6 mm long: ratio 6
    assert quality_report(mesh, load_config(), stretched_edge_ratio=5.5)["stretched_elements"] == 1
    assert "<th>stretched_elements</th><td>1</td>" in render_html(
        quality_report(mesh, load_config(), stretched_edge_ratio=5.5))
    # the command warns, naming the limit and the count
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    write_mesh(mesh, tmp_path / "m.vtu")
    with caplog.at_level("WARNING"):
        assert main(["quality", str(tmp_path / "m.vtu"), "-o", str(tmp_path / "q.json"),
                     "--set", "quality.stretched_edge_ratio=4.5"]) == 0
    said = [r.getMessage() for r in caplog.records if "edge ratio above" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("quality: 4 element(s) have an edge ratio above 4.5 (largest 6)")
    assert "elongated voxels" in said[0] and "pillow" not in said[0]  # 0.2 x 1 x 1 mm voxels, no layer
    # the same stretch on cubic voxels: not the voxels' doing
    cubic = voxel_mesh(np.ones((4, 1, 1), np.uint8))
    cubic.points[cubic.lattice[:, 0] == 4, 0] += 5.0
    write_mesh(cubic, tmp_path / "c.vtu")
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert main(["quality", str(tmp_path / "c.vtu"), "-o", str(tmp_path / "q2.json"),
                     "--set", "quality.stretched_edge_ratio=4.5"]) == 0
    said = [r.getMessage() for r in caplog.records if "edge ratio above" in r.getMessage()]
    assert len(said) == 1 and "elongated voxels" not in said[0] and "smoothing that shortens an edge" in said[0]


def test_inverted_elements_are_counted_and_html_renders():
    labels = np.ones((2, 2, 2), np.uint8)
    mesh = voxel_mesh(labels)
    centre = np.flatnonzero((mesh.lattice == 1).all(axis=1))[0]
    mesh.points[centre] = [2.6, 2.6, 2.6]  # centre node pushed out through the far corner
    report = quality_report(mesh, load_config())
    assert report["inverted_elements"] >= 1
    assert report["poor_elements"] >= report["inverted_elements"]
    page = render_html(report)
    assert page.startswith("<!DOCTYPE html>") and "soft_tissue" in page
    # what made the model: dicer's version and its libraries' (constraints.txt pins them)
    from dicer import LIBRARIES, library_versions

    assert report["library_versions"] == library_versions() and list(report["library_versions"])[1:] == list(LIBRARIES)
    assert f"numpy {library_versions()['numpy']}, scipy {library_versions()['scipy']}" in page


def test_html_shows_stage_reports_and_pictures():
    mesh = voxel_mesh(np.ones((2, 2, 2), np.uint8))
    report = quality_report(mesh, load_config())
    report["stages"] = {"fix": {"changed_voxels": 7, "type_a": {"bone": 3}}, "merge": {"elements_after": 1}}
    png = b"\x89PNG\r\n\x1a\n-a-picture"
    page = render_html(report, [("Segmentation", png)])
    assert "<h2>Stage: fix</h2>" in page and "<h2>Stage: merge</h2>" in page
    assert "<td>7</td>" in page and "{&quot;bone&quot;: 3}" in page
    # embedded, so the page shows it wherever it is opened (inside snakemake --report too)
    import base64

    assert f"<img src='data:image/png;base64,{base64.b64encode(png).decode()}' alt='Segmentation'>" in page


def test_counts_of_hundreds_of_materials():
    # 400 labels (some unnamed): each material's counts equal a count over its own elements
    rng = np.random.default_rng(5)
    labels = rng.integers(0, 401, (12, 11, 10)).astype(np.uint16)
    mesh = voxel_mesh(labels)
    mesh.points += rng.normal(0, 0.05, mesh.points.shape)
    config = load_config(settings={"materials": [{"name": f"m{i}"} for i in range(1, 301)]})
    report = quality_report(mesh, config, labels=Volume(labels, (1.0, 1.0, 1.0)))
    present = np.unique(mesh.material)
    assert len(report["materials"]) == present.size > 350
    from dicer.mesh.metrics import element_volumes, scaled_jacobian

    sj = scaled_jacobian(mesh.points, mesh.cells)
    vol = element_volumes(mesh.points, mesh.cells)
    for k in present.tolist():
        entry = report["materials"][f"m{k}" if k <= 300 else f"material_{k}"]
        sel = mesh.material == k
        assert entry["label"] == k and entry["elements"] == np.count_nonzero(sel)
        assert entry["nodes"] == np.unique(mesh.cells[sel]).size
        assert entry["voxels"] == np.count_nonzero(labels == k)
        assert entry["volume_mm^3"] == pytest.approx(vol[sel].sum(), rel=1e-5)
        assert entry["min_scaled_jacobian"] == pytest.approx(sj[sel].min(), rel=1e-5)
    assert sum(e["nodes"] for e in report["materials"].values()) > mesh.n_points  # shared nodes count twice


@pytest.mark.parametrize("materials", [2, 90])
def test_nodes_per_material_by_flags_and_by_sorting(materials):
    """Few materials count their nodes in a table of flags, many by sorting keys: both
    give the distinct nodes of each material's elements."""
    from dicer.quality import _material_nodes

    rng = np.random.default_rng(materials)
    labels = rng.integers(0, materials + 1, (9, 8, 7)).astype(np.uint8)
    mesh = voxel_mesh(labels)
    material = mesh.material.astype(np.int64)
    present = np.unique(material)
    expect = [np.unique(mesh.cells[material == k]).size for k in present]
    got = _material_nodes(mesh.cells, material, present, int(material.max()) + 1, mesh.n_points)
    assert got.tolist() == expect
    # 2 materials take the flags, 90 the sort (a table of 90 flags per node outgrows the keys)
    assert (mesh.n_points * present.size <= mesh.cells.size * 8) == (materials == 2)


# --- floating parts: the voxel grid and the face graph against a plain reference ------------

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays


def _reference_parts(mesh) -> dict:
    """Face-connected parts the plain way: faces keyed by their set of nodes, elements of one
    face joined in a union-find; per material only faces between elements of one material."""
    from dicer.mesh.topology import HEX_FACES, QUAD_EDGES

    table = HEX_FACES if mesh.dim == 3 else QUAD_EDGES
    owners: dict[frozenset, list[int]] = {}
    for e, cell in enumerate(mesh.cells.tolist()):
        for face in table:
            owners.setdefault(frozenset(cell[i] for i in face), []).append(e)
    material = mesh.material.tolist()

    def parts(same_material: bool) -> list[tuple[int, int]]:
        root = list(range(mesh.n_cells))

        def find(i):
            while root[i] != i:
                root[i] = root[root[i]]
                i = root[i]
            return i

        for elements in owners.values():
            for a, b in zip(elements, elements[1:]):
                if not same_material or material[a] == material[b]:
                    root[find(a)] = find(b)
        count: dict[int, int] = {}
        for e in range(mesh.n_cells):
            count[find(e)] = count.get(find(e), 0) + 1
        return [(material[r], n) for r, n in count.items()]

    model = [n for _, n in parts(False)]
    out = {"model": {"parts": len(model), "largest": max(model), "smallest": min(model),
                     "floating_elements": mesh.n_cells - max(model)}, "materials": {}}
    for k in sorted(set(material)):
        sizes = [n for mk, n in parts(True) if mk == k]
        out["materials"][k] = {"parts": len(sizes), "largest": max(sizes), "smallest": min(sizes)}
    return out


def _graph_floating_parts(mesh) -> dict:
    """floating_parts through the face graph whatever the mesh (the path of merged and graded
    meshes), by hiding the lattice."""
    from dicer.quality import floating_parts

    graph = mesh.copy()
    graph.lattice = np.full_like(graph.lattice, -1)
    return floating_parts(graph)


_labels_2d = arrays(np.uint8, st.tuples(st.integers(1, 7), st.integers(1, 7)), elements=st.integers(0, 3))
_labels_3d = arrays(np.uint8, st.tuples(st.integers(1, 5), st.integers(1, 5), st.integers(1, 5)),
                    elements=st.integers(0, 3))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(_labels_2d, _labels_3d))
def test_floating_parts_match_a_reference_on_random_labels(labels):
    """Random labels, 2D and 3D (islands, elements touching only along an edge or at a node,
    empty voxels): the voxel grid's labelling and the face graph both give the parts of a
    plain union-find over faces keyed by their nodes."""
    from dicer.mesh.faces import face_neighbours, voxel_elements, voxel_face_neighbours
    from dicer.quality import floating_parts

    if not labels.any():
        labels = labels.copy()
        labels.flat[0] = 1
    mesh = voxel_mesh(labels)
    expect = _reference_parts(mesh)
    assert voxel_elements(mesh) is not None
    assert floating_parts(mesh) == expect
    assert _graph_floating_parts(mesh) == expect
    # the voxel grid's neighbours are the face sort's, face for face
    assert np.array_equal(voxel_face_neighbours(mesh), face_neighbours(mesh.cells, mesh.dim, mesh.n_points))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays(np.uint8, (12, 12, 10), elements=st.sampled_from([0, 1, 1, 1, 2])))
def test_floating_parts_of_graded_meshes_match_a_reference(labels):
    """A graded mesh (templates: not a voxel mesh) goes through the face graph."""
    from dicer.mesh.coarsen import coarsen_mesh
    from dicer.mesh.faces import voxel_elements
    from dicer.quality import floating_parts

    labels = labels.copy()
    labels[:, :, :7] = 1  # a solid slab that coarsens; random voxels above it
    graded, _ = coarsen_mesh(voxel_mesh(labels), levels=1, min_distance=1, keep_fine=())
    assert graded.cell_data["coarsening_level"].max() == 1 and voxel_elements(graded) is None
    assert floating_parts(graded) == _reference_parts(graded)


def test_a_voxel_mesh_with_split_nodes_is_no_voxel_mesh():
    """Two elements side by side on their own nodes share no face: the voxel grid would join
    them, so such a mesh goes through the face graph."""
    from dicer.mesh.faces import voxel_elements
    from dicer.quality import floating_parts

    mesh = voxel_mesh(np.array([[[1]], [[1]]], np.uint8))  # two voxels along x
    assert voxel_elements(mesh) is not None
    assert floating_parts(mesh)["model"]["parts"] == 1
    split = mesh.copy()
    shared = np.unique(split.cells[1][np.isin(split.cells[1], split.cells[0])])
    copies = np.arange(split.n_points, split.n_points + shared.size)
    split.points = np.vstack([split.points, split.points[shared]])
    split.lattice = np.vstack([split.lattice, split.lattice[shared]])
    remap = np.arange(mesh.n_points)
    remap[shared] = copies
    split.cells = split.cells.copy()
    split.cells[1] = remap[split.cells[1]]  # the second element on copies of the shared nodes
    assert voxel_elements(split) is None
    assert floating_parts(split)["model"] == {"parts": 2, "largest": 1, "smallest": 1, "floating_elements": 1}
    assert floating_parts(split) == _reference_parts(split)


def test_stage_reports_and_pictures_are_named_by_content_not_by_file_name(tmp_path, capsys):
    """A stage report was keyed by its file name up to the first dot and a picture captioned
    with its file name: patient-coded names (MRN4711.smooth.json, DOE_overlay.png) reached
    quality.json and report.html, and the same content under other names gave other bytes."""
    import json
    import shutil

    from dicer.cli import main

    lab = np.zeros((8, 8, 8), np.uint8)
    lab[1:7, 1:7, 1:7] = 1
    run = tmp_path / "run"
    np.save(tmp_path / "l.npy", lab)
    assert main(["run", "--labels", str(tmp_path / "l.npy"), "-o", str(run), "-q"]) == 0
    outputs = []
    for prefix in ("", "MRN4711."):
        folder = tmp_path / (prefix or "plain")
        folder.mkdir()
        for stage in ("fix", "merge", "smooth"):
            shutil.copy(run / f"{stage}.json", folder / f"{prefix}{stage}.json")
        shutil.copy(run / "jacobian.png", folder / f"{prefix}DOE_overlay.png")
        args = ["quality", str(run / "smoothed.vtu"), "-o", str(folder / "q.json"), "--html", str(folder / "q.html"),
                "--picture", str(folder / f"{prefix}DOE_overlay.png"), "-q"]
        for stage in ("smooth", "fix", "merge"):
            args += ["--stage-report", str(folder / f"{prefix}{stage}.json")]
        assert main(args) == 0
        outputs.append(((folder / "q.json").read_bytes(), (folder / "q.html").read_bytes()))
    assert outputs[0] == outputs[1]
    report = json.loads(outputs[1][0])
    assert sorted(report["stages"]) == ["fix", "merge", "smooth"]
    assert b"MRN4711" not in outputs[1][0] + outputs[1][1] and b"DOE" not in outputs[1][1]
    # a report of no stage (filed under its file name before) and a second report of one stage: refused
    base = ["quality", str(run / "smoothed.vtu"), "-o", str(tmp_path / "bad.json"), "-q"]
    (tmp_path / "SMITH_JOHN_1970.json").write_text('{"anything": 1}')
    for extra, said in ((["SMITH_JOHN_1970.json"], "SMITH_JOHN_1970.json: not a report of dicer fix, merge or smooth"),
                        (["q.json"], "q.json: not a report of dicer fix, merge or smooth"),
                        (["fix.json", "fix.json"], "fix.json: a second fix report")):
        folder = tmp_path / "plain"
        args = base + [a for name in extra for a in ("--stage-report", str(folder / name if name != "SMITH_JOHN_1970.json"
                                                                               else tmp_path / name))]
        capsys.readouterr()
        assert main(args) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and said in err and err.count("\n") == 1
        assert not (tmp_path / "bad.json").exists()
    # a picture that is no PNG (a slip for segmentation.png) was embedded as a broken image
    html = tmp_path / "bad.html"
    assert main(base + ["--html", str(html), "--picture", str(run / "fix.json")]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: {run / 'fix.json'}: not a PNG picture (the report would show a broken image); give a PNG "
                   "with --picture, such as segmentation.png\n")
    assert not html.exists() and not (tmp_path / "bad.json").exists()


def test_node_classes_in_the_report_count_the_irregular_ones():
    # class X (code 7) was left out of quality.json while smooth.json counted it
    labels = np.ones((3, 3, 3), np.uint8)
    mesh = voxel_mesh(labels)
    codes = np.zeros(mesh.n_points, np.int8)
    codes[:7] = np.arange(1, 8)  # one node of each class A..F and X
    codes[7:9] = 7
    mesh.point_data["node_class"] = codes
    classes = quality_report(mesh, load_config())["node_classes"]
    assert classes == {"interior": mesh.n_points - 9, "A": 1, "B": 1, "C": 1, "D": 1, "E": 1, "F": 1, "X": 3}
    assert sum(classes.values()) == mesh.n_points


@pytest.mark.parametrize("dim", [2, 3])
def test_a_hole_that_merging_closes_is_reported_as_a_change_of_topology(dim):
    # a 2-voxel channel through a block (2D: a hole in a plate) closed by plane merging, exit 0
    # and no word: the volume grew by 0.7 %, under the warning
    from dicer.mesh.merge import merge_mesh

    shape = (24,) * dim
    labels = np.ones(shape, np.uint8)
    labels[(slice(11, 13), slice(11, 13))] = 0
    volume = Volume(labels, (1.0,) * dim)
    voxels = quality_report(voxel_mesh(labels), load_config(), labels=volume)
    assert voxels["topology_changed"] == []
    merged, _ = merge_mesh(voxel_mesh(labels))
    report = quality_report(merged, load_config(), labels=volume)
    assert report["elements"] < voxels["elements"] and report["topology_changed"] == ["soft_tissue"]
    assert "<td>surface topology unlike the voxels</td><td>soft_tissue</td>" in render_html(report)
    entry = report["materials"]["soft_tissue"]
    assert entry["voxel_surface_euler"] == 0 and entry["surface_euler"] == (2 if dim == 3 else 1)
    # a cavity and a second material: counted per material, nothing changed unmerged
    nested = np.zeros((20,) * dim, np.uint8)
    nested[(slice(2, 18),) * dim] = 1
    nested[(slice(8, 12),) * dim] = 2
    nested[(slice(9, 11),) * dim] = 0
    report = quality_report(voxel_mesh(nested), load_config(), labels=Volume(nested, (1.0,) * dim))
    assert report["topology_changed"] == [] and "surface_euler" not in report["materials"]["bone"]  # its voxels
    from dicer.quality import element_neighbours, region_euler, surface_euler, voxel_euler

    mesh = voxel_mesh(nested)
    counted = surface_euler(mesh, element_neighbours(mesh)) if dim == 3 else region_euler(mesh)
    assert counted == voxel_euler(nested, [1, 2]) == ({1: 4, 2: 4} if dim == 3 else {1: 0, 2: 0})


def _two_materials(e_bone):
    """A 4 x 2 x 2 bar of 1 mm voxels: soft tissue (E 1000 MPa) at x < 2, bone (E ``e_bone``) at
    x >= 2, both nu 0.3 and rho 1e-9 t/mm^3."""
    labels = np.ones((4, 2, 2), np.uint8)
    labels[2:] = 2
    mesh = voxel_mesh(labels)
    props = [{"name": "soft_tissue", "youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1e-9},
             {"name": "bone", "youngs_modulus": e_bone, "poissons_ratio": 0.3, "density": 1e-9}]
    return mesh, props


def test_wave_speed_is_the_dilatational_one():
    from dicer.quality import wave_speeds

    c = wave_speeds([{"youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1e-9},
                     {"youngs_modulus": 15000.0, "poissons_ratio": 0.0, "density": 2e-9}])
    assert np.isnan(c[0])
    assert c[1] == pytest.approx(np.sqrt(1000.0 * 0.7 / (1e-9 * 1.3 * 0.4)), rel=1e-12)  # 1.160e6 mm/s
    assert c[2] == pytest.approx(np.sqrt(15000.0 / 2e-9), rel=1e-12)  # nu = 0: the bar speed


def test_explicit_time_step_and_the_mass_that_scaling_adds():
    """Bone four times as stiff: waves twice as fast, its 1 mm elements' step half the soft
    tissue's. Scaling to 1.5 and 2 times the smallest step slows only the bone's 8 elements
    (mass x 2.25 and x 4: +62.5 % and +150 % of their half of the mass); to 4 times, the soft
    tissue's too (x 4)."""
    from dicer.quality import wave_speeds

    mesh, props = _two_materials(4000.0)
    report = quality_report(mesh, load_config(), properties=props)
    step = report["explicit_time_step"]
    soft = 1.0 / wave_speeds(props)[1]
    assert step["smallest_s"] == pytest.approx(soft / 2, rel=1e-5) and step["material"] == "bone"
    assert 9 <= step["element"] <= 16  # numbered from 1 in mesh order: the bone's are the second half
    assert report["materials"]["soft_tissue"]["smallest_time_step_s"] == pytest.approx(soft, rel=1e-5)
    assert report["materials"]["bone"]["smallest_time_step_s"] == pytest.approx(soft / 2, rel=1e-5)
    got = [(m["times_smallest"], m["elements_scaled"], m["mass_added_percent"]) for m in step["mass_scaling"]]
    assert got == [(1.5, 8, pytest.approx(0.5 * 125.0)), (2.0, 8, pytest.approx(0.5 * 300.0)),
                   (4.0, 16, pytest.approx(0.5 * 1500.0 + 0.5 * 300.0))]
    page = render_html(report)
    assert "<h2>Explicit time step</h2>" in page and "+62.5 % mass on 8 element(s)" in page


def test_a_thin_element_sets_the_time_step():
    """One voxel layer squeezed to a tenth of its thickness: its elements' length, and the
    step, a tenth; scaling to twice that step costs them x4 of their (tenth) mass."""
    mesh = voxel_mesh(np.ones((3, 3, 3), np.uint8))
    top = mesh.lattice[:, 2] == 3
    mesh.points[top, 2] = 2.1
    props = [{"name": "soft_tissue", "youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1e-9}]
    step = quality_report(mesh, load_config(), properties=props)["explicit_time_step"]
    from dicer.quality import wave_speeds

    assert step["smallest_s"] == pytest.approx(0.1 / wave_speeds(props)[1], rel=1e-5)
    twice = step["mass_scaling"][1]
    assert twice["elements_scaled"] == 9
    assert twice["mass_added_percent"] == pytest.approx(100.0 * 9 * 0.1 * 3.0 / (18 + 0.9), rel=1e-5)


def test_no_time_step_without_properties_for_every_label_or_with_an_inverted_element():
    mesh, props = _two_materials(4000.0)
    assert "explicit_time_step" not in quality_report(mesh, load_config())
    assert "explicit_time_step" not in quality_report(mesh, load_config(), properties=props[:1])
    centre = np.flatnonzero((mesh.lattice == [1, 1, 1]).all(axis=1))[0]
    mesh.points[centre] = [3.6, 2.6, 2.6]
    report = quality_report(mesh, load_config(), properties=props)
    assert report["inverted_elements"] >= 1 and "explicit_time_step" not in report


def test_a_2d_model_in_plane_stress_or_strain_takes_that_wave_speed(tmp_path):
    """Quads of 1 mm (length: area over longest edge, 1 mm): plane stress (CPS4, the 2D
    default) sqrt(E / (rho (1 - nu^2))), plane strain (CPE4) the dilatational speed; the command
    takes the deck's element type."""
    from dicer.cli import main
    from dicer.quality import wave_speeds

    props = [{"name": "soft_tissue", "youngs_modulus": 1000.0, "poissons_ratio": 0.3, "density": 1e-9}]
    mesh = voxel_mesh(np.ones((3, 2), np.uint8))
    stress = quality_report(mesh, load_config(), properties=props)["explicit_time_step"]["smallest_s"]
    strain = quality_report(mesh, load_config(), properties=props, plane_stress=False)["explicit_time_step"]
    assert stress == pytest.approx(1.0 / np.sqrt(1000.0 / (1e-9 * 0.91)), rel=1e-5)
    assert strain["smallest_s"] == pytest.approx(1.0 / wave_speeds(props)[1], rel=1e-5)
    np.save(tmp_path / "s.npy", np.ones((3, 2), np.uint8))
    assert main(["mesh", str(tmp_path / "s.npy"), "-o", str(tmp_path / "s.vtu"), "-q"]) == 0
    for etype, expected in (("CPS4", stress), ("CPE4", strain["smallest_s"])):
        assert main(["quality", str(tmp_path / "s.vtu"), "-o", str(tmp_path / f"{etype}.json"), "-q",
                     "--set", f"export.element_type={etype}", "--set",
                     "materials=[{name: soft_tissue, youngs_modulus: 1000, poissons_ratio: 0.3, density: 1e-9}]"]) == 0
        report = json.loads((tmp_path / f"{etype}.json").read_text(encoding="utf-8"))
        assert report["explicit_time_step"]["smallest_s"] == pytest.approx(expected, rel=1e-5)


def test_a_mesh_named_otherwise_than_the_config_is_warned_of(tmp_path, caplog):
    """A label volume's mesh (label_3, label_7) read with the config's materials (soft_tissue,
    bone): the report keeps the mesh's names, and its time step the config's properties by
    material number, as the decks do; it said nothing, so a step put under label_3 was soft
    tissue's (53 times slower waves than bone's). With the run's materials.json no word."""
    from dicer.cli import main

    labels = np.zeros((10, 8, 6), np.uint8)
    labels[1:9, 1:7, 1:5] = 3
    labels[3:6, 2:5, 2:4] = 7
    np.save(tmp_path / "b.npy", labels)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "b.npy"), "-o", str(out), "-q"]) == 0
    said = "the mesh names its materials label_3, label_7, the config soft_tissue, bone"
    with caplog.at_level("WARNING"):
        assert main(["quality", str(out / "smoothed.vtu"), "-o", str(tmp_path / "q.json")]) == 0
    assert caplog.text.count(said) == 1
    assert "explicit time step the properties of soft_tissue, bone by material number" in caplog.text
    report = json.loads((tmp_path / "q.json").read_text(encoding="utf-8"))
    assert report["explicit_time_step"]["material"] == "label_7"  # material 2: bone's properties
    assert set(report["materials"]) == {"label_3", "label_7"}
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert main(["quality", str(out / "smoothed.vtu"), "-o", str(tmp_path / "q2.json"),
                     "--materials", str(out / "materials.json")]) == 0
    assert "names its materials" not in caplog.text


def test_a_mesh_with_inverted_elements_is_warned_of_by_the_quality_command(tmp_path, caplog):
    """An all-inverted mesh (corners of another order) passed quality with exit 0, no word, and
    a total volume of minus the model's."""
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    mesh = voxel_mesh(np.ones((3, 3, 3), np.uint8))
    mesh.cells = mesh.cells[:, [4, 5, 6, 7, 0, 1, 2, 3]].copy()  # top and bottom swapped: mirrored
    write_mesh(mesh, tmp_path / "inv.vtu", allow_inverted=True)
    assert main(["quality", str(tmp_path / "inv.vtu"), "-o", str(tmp_path / "q.json"), "-q"]) == 0
    said = [r.getMessage() for r in caplog.records if "inverted or degenerate" in r.getMessage()]
    assert said == ["quality: 27 of the 27 elements are inverted or degenerate (scaled Jacobian 0 or less: corners in "
                    "another order or folded); no solver takes them, and the volumes here count them negative; export "
                    "and surface refuse them: remesh from the labels with dicer mesh"]
    caplog.clear()
    write_mesh(voxel_mesh(np.ones((3, 3, 3), np.uint8)), tmp_path / "ok.vtu")
    assert main(["quality", str(tmp_path / "ok.vtu"), "-o", str(tmp_path / "q.json"), "-q"]) == 0
    assert not [r for r in caplog.records if "inverted or degenerate" in r.getMessage()]
