"""Connectivity fixes (Box 1): Types A, B, C and the invariant they leave behind."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dicer.connectivity import boundary_edge_counts, connectivity_defects, fix_connectivity
from dicer.errors import DicerError


def test_type_a_2d_checkerboard_gets_one_connecting_pixel():
    lab = np.array([[1, 0], [0, 1]], np.uint8)
    out, rep = fix_connectivity(lab)
    assert out.sum() == 3 and out[0, 0] == 1 and out[1, 1] == 1
    assert rep["type_a"] == {"1": 1}
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}


def test_type_a_3d_edge_contact_in_every_orientation():
    for axes in ((0, 1), (0, 2), (1, 2)):
        lab = np.zeros((4, 4, 4), np.uint8)
        a = [1, 1, 1]
        b = [1, 1, 1]
        b[axes[0]] += 1
        b[axes[1]] += 1
        lab[tuple(a)] = 1
        lab[tuple(b)] = 1
        assert connectivity_defects(lab, type_c=False)["type_a"] == 1
        out, rep = fix_connectivity(lab, type_c=False)
        assert rep["type_a"] == {"1": 1}
        assert out.sum() == 3
        assert connectivity_defects(out)["type_a"] == 0


def test_type_a_multiclass_checkerboard_goes_to_higher_class():
    lab = np.array([[2, 1], [1, 2]], np.uint8)
    out, rep = fix_connectivity(lab)
    assert sorted(out.ravel().tolist()) == [1, 2, 2, 2]
    assert rep["type_a"] == {"2": 1}


def test_type_b_six_around_a_body_diagonal_are_filled():
    lab = np.ones((2, 2, 2), np.uint8)
    lab[0, 0, 0] = 0
    lab[1, 1, 1] = 0
    assert connectivity_defects(lab)["type_b"] == 1
    out, rep = fix_connectivity(lab)
    assert out.min() == 1
    assert rep["type_b"] == {"1": 2}


def test_type_b_body_diagonal_pair_is_joined_by_a_face_path():
    lab = np.zeros((2, 2, 2), np.uint8)
    lab[0, 0, 0] = 1
    lab[1, 1, 1] = 1
    out, rep = fix_connectivity(lab, type_c=False)
    # p = corner 0 -> p^1 = (1,0,0), p^3 = (1,1,0) join it to (1,1,1)
    assert out[1, 0, 0] == 1 and out[1, 1, 0] == 1
    assert out.sum() == 4
    assert connectivity_defects(out, type_c=False)["type_b"] == 0


def _hanging_element():
    lab = np.zeros((8, 8, 8), np.uint8)
    lab[1:6, 1:6, 1:6] = 1
    lab[3:6, 3:6, 1:6] = 0  # an L-shaped prism (two walls, two voxels thick) ...
    lab[3, 3, 3] = 1  # ... with one element in its inner corner, held by two adjacent faces
    return lab


def test_type_c_element_hanging_by_two_faces_is_removed():
    lab = _hanging_element()
    counts = boundary_edge_counts(lab)
    assert counts[4, 4, 3] == 3 and counts[4, 4, 4] == 3  # the two free corners are class A
    assert connectivity_defects(lab)["type_c"] >= 1
    out, rep = fix_connectivity(lab)
    assert out[3, 3, 3] == 0  # the paper's rule: the majority of its neighbours is background
    assert rep["type_c"] == {"0": 1} and rep["majority_rounds"] == 1 and rep["type_c_rounds"] == 0
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}


def test_type_c_raise_only_makes_the_hanging_element_fat():
    lab = _hanging_element()
    out, rep = fix_connectivity(lab, majority_rounds=0)
    # the element stays and now lies in a 2x2x2 block of its class; nothing was removed
    assert out[3, 3, 3] == 1 and np.all(out >= lab)
    assert any(np.all(out[x:x + 2, y:y + 2, z:z + 2] == 1)
               for x in (2, 3) for y in (2, 3) for z in (2, 3))
    assert 1 <= rep["type_c"]["1"] <= 7 and "0" not in rep["type_c"]
    assert rep["type_c_rounds"] >= 1 and rep["converged"]
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}


def test_type_c_single_void_is_filled():
    lab = np.ones((5, 5, 5), np.uint8)
    lab[2, 2, 2] = 0
    out, rep = fix_connectivity(lab)
    assert out.min() == 1
    assert rep["type_c"] == {"1": 1}


def test_thin_plate_is_thickened_not_eaten():
    lab = np.zeros((12, 6, 12), np.uint8)
    lab[1:11, 2, 1:11] = 1
    assert connectivity_defects(lab)["type_c"] == 4  # the plate's four corners
    out, rep = fix_connectivity(lab)
    # the plate keeps every voxel and becomes two voxels thick (one layer added)
    assert np.all(out >= lab)
    assert np.count_nonzero(out) == 2 * np.count_nonzero(lab)
    assert np.all(out[1:11, 2:4, 1:11] == 1) or np.all(out[1:11, 1:3, 1:11] == 1)
    assert rep["converged"] and rep["remaining"] == {"type_a": 0, "type_b": 0, "type_c": 0}


@pytest.mark.parametrize("seed, majority_rounds", [(7, 5), (8, 0)])
def test_invariant_on_a_volume_of_several_tiles(seed, majority_rounds):
    # larger than one 16^3 tile: later A/B sweeps run tile by tile
    lab = np.random.default_rng(seed).integers(0, 4, (40, 36, 34)).astype(np.uint8)
    out, rep = fix_connectivity(lab, majority_rounds=majority_rounds)
    assert rep["converged"] and rep["type_c_rounds"] >= 1
    _invariant_holds(out)
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}
    if majority_rounds == 0:
        assert np.all(out >= lab)


def test_majority_rule_with_large_label_values():
    lab = _hanging_element().astype(np.uint16) * 5000
    lab[7, 7, 7] = 6000
    out, rep = fix_connectivity(lab)
    # the hanging element goes to its neighbours' majority (background), not to a far class
    assert out[3, 3, 3] == 0 and rep["type_c"].get("6000", 0) == 0
    assert connectivity_defects(out)["type_c"] == 0


def test_round_cap_is_reported():
    lab = np.zeros((12, 6, 12), np.uint8)
    lab[1:11, 2, 1:11] = 1
    out, rep = fix_connectivity(lab, majority_rounds=0, max_type_c_rounds=0)
    assert np.array_equal(out, lab)
    assert not rep["converged"] and rep["type_c_sites"] == [4]
    assert rep["remaining"] == {"type_a": 0, "type_b": 0, "type_c": 4}


@pytest.mark.parametrize("length, majority_rounds", [(20, 5), (8, 0)])
def test_one_voxel_rod_becomes_two_by_two(length, majority_rounds):
    lab = np.zeros((length + 2, 6, 6), np.uint8)
    lab[1:-1, 2, 2] = 2
    out, rep = fix_connectivity(lab, majority_rounds=majority_rounds)
    assert np.all(out >= lab) and set(np.unique(out)) == {0, 2}
    assert np.count_nonzero(out) == 4 * length
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}


def test_short_one_voxel_rod_is_deleted_by_the_papers_rule():
    lab = np.zeros((10, 6, 6), np.uint8)
    lab[1:9, 2, 2] = 2  # each round deletes both ends: gone after four
    out, rep = fix_connectivity(lab)
    assert out.max() == 0 and rep["majority_rounds"] == 4 and rep["type_c"] == {"0": 8}


def test_well_connected_volume_is_unchanged_and_dtype_kept():
    lab = np.zeros((10, 10, 10), np.int16)
    lab[2:8, 2:8, 2:8] = 1
    lab[4:6, 4:6, 4:6] = 2
    out, rep = fix_connectivity(lab)
    assert out.dtype == np.int16
    assert np.array_equal(out, lab)
    assert rep["changed_voxels"] == 0 and rep["iterations"] == [1]


def test_ball_needs_few_iterations():
    n = 40
    g = np.arange(n) + 0.5 - 20.3
    r = np.sqrt(g[:, None, None] ** 2 + (g[None, :, None] - 0.2) ** 2 + (g[None, None, :] + 0.1) ** 2)
    lab = (r < 15).astype(np.uint8) + (r < 9).astype(np.uint8)
    out, rep = fix_connectivity(lab)
    assert rep["converged"] and max(rep["iterations"]) <= 3
    assert rep["changed_voxels"] < 50
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}


def test_bad_input():
    with pytest.raises(DicerError):
        fix_connectivity(np.zeros(5, np.uint8))
    with pytest.raises(DicerError):
        fix_connectivity(np.zeros((0, 3, 3), np.uint8))
    with pytest.raises(DicerError):
        fix_connectivity(np.zeros((3, 3, 3)))
    with pytest.raises(DicerError):
        fix_connectivity(-np.ones((3, 3, 3), np.int32))


def _invariant_holds(out: np.ndarray) -> None:
    """Check the invariant directly, class by class, without the module's own counters."""
    classes = np.unique(out)
    planes = [(0, 1)] if out.ndim == 2 else [(1, 2), (0, 2), (0, 1)]
    for c in classes:
        b = out == c
        for ax in planes:
            sl = [slice(None)] * out.ndim
            def v(i, j):
                s = list(sl)
                s[ax[0]] = slice(i, b.shape[ax[0]] - 1 + i)
                s[ax[1]] = slice(j, b.shape[ax[1]] - 1 + j)
                return b[tuple(s)]
            checker = (v(0, 0) & v(1, 1) & ~v(1, 0) & ~v(0, 1)) | (v(1, 0) & v(0, 1) & ~v(0, 0) & ~v(1, 1))
            assert not checker.any(), f"class {c}: planar checkerboard"
        if out.ndim == 3:
            nx, ny, nz = b.shape
            corners = [b[i : nx - 1 + i, j : ny - 1 + j, k : nz - 1 + k] for k in (0, 1) for j in (0, 1) for i in (0, 1)]
            total = sum(x.astype(int) for x in corners)
            for p in range(4):
                q = p ^ 7
                pair = corners[p] & corners[q]
                assert not (pair & (total == 2)).any(), f"class {c}: two voxels on a body diagonal"
                gap = ~corners[p] & ~corners[q]
                assert not (gap & (total == 6)).any(), f"class {c}: six voxels around a body diagonal"


volumes3d = st.tuples(st.integers(2, 7), st.integers(2, 7), st.integers(2, 7), st.integers(1, 3)).flatmap(
    lambda t: arrays(np.uint8, t[:3], elements=st.integers(0, t[3])))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(volumes3d)
@pytest.mark.parametrize("majority_rounds", [5, 0])
def test_invariant_on_random_multiclass_volumes(majority_rounds, lab):
    out, rep = fix_connectivity(lab, majority_rounds=majority_rounds)
    assert rep["converged"]
    _invariant_holds(out)
    left = connectivity_defects(out)
    assert left["type_a"] == 0 and left["type_b"] == 0 and rep["remaining"] == left
    # no Type C site is left; without the paper's rule every fix only raised classes
    assert left["type_c"] == 0
    if majority_rounds == 0:
        assert np.all(out >= lab)
    # fixing again changes nothing
    again, rep2 = fix_connectivity(out, majority_rounds=majority_rounds)
    assert np.array_equal(again, out) and rep2["changed_voxels"] == 0


@settings(max_examples=100, deadline=None)
@given(st.tuples(st.integers(2, 12), st.integers(2, 12), st.integers(1, 3)).flatmap(
    lambda t: arrays(np.uint8, t[:2], elements=st.integers(0, t[2]))))
def test_invariant_on_random_2d_images(lab):
    out, rep = fix_connectivity(lab)
    assert rep["converged"]
    _invariant_holds(out)


def test_deterministic():
    rng = np.random.default_rng(3)
    lab = rng.integers(0, 3, (9, 8, 7)).astype(np.uint8)
    a, ra = fix_connectivity(lab)
    b, rb = fix_connectivity(lab.copy())
    assert np.array_equal(a, b) and ra == rb


def _joined_by_labelling(w: np.ndarray, mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The voxels of ``mask`` 26-connected to a seed in ``mask`` through ``mask`` voxels of
    its class: one labelling per class."""
    from scipy import ndimage

    out = np.zeros(w.shape, bool)
    for value in np.unique(w[seeds & mask]):
        comp, _ = ndimage.label(mask & (w == value), structure=np.ones((3, 3, 3), bool))
        chosen = np.unique(comp[seeds & mask & (w == value)])
        out |= np.isin(comp, chosen[chosen > 0])
    return out


@settings(max_examples=80, deadline=None)
@given(st.tuples(st.integers(1, 8), st.integers(1, 8), st.integers(1, 8), st.integers(1, 400)).flatmap(
    lambda t: st.tuples(arrays(np.uint16, t[:3], elements=st.integers(0, t[3])), arrays(bool, t[:3]),
                        arrays(bool, t[:3]))))
def test_components_of_all_classes_at_once_equal_one_labelling_per_class(volumes):
    from dicer.connectivity import _joined_to_seeds

    w, mask, seeds = volumes
    assert np.array_equal(_joined_to_seeds(w, mask, seeds), _joined_by_labelling(w, mask, seeds))


def test_hundreds_of_classes_are_fixed():
    # Voronoi cells of 400 classes with 2 % of the voxels set to random classes: every
    # arrangement is repaired, and the Type C thickening ran
    rng = np.random.default_rng(4)
    n, k = 30, 400
    seeds = rng.uniform(0, n, (k, 3))
    centres = np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    lab = (1 + ((centres - seeds) ** 2).sum(axis=2).argmin(axis=1)).astype(np.uint16).reshape(n, n, n)
    noise = rng.random(lab.shape) < 0.02
    lab[noise] = rng.integers(0, k + 1, int(noise.sum()))
    out, rep = fix_connectivity(lab)
    assert rep["converged"] and rep["type_c_rounds"] >= 1 and out.dtype == np.uint16
    assert connectivity_defects(out) == {"type_a": 0, "type_b": 0, "type_c": 0}
    _invariant_holds(out)
    assert np.unique(out).size > 390


def test_floating_parts_below_the_size_are_removed():
    from dicer.connectivity import remove_islands

    labels = np.zeros((20, 20, 20), np.uint8)
    labels[2:12, 2:12, 2:12] = 1
    labels[4:8, 4:8, 4:8] = 2  # inside the body: not floating
    labels[15:17, 15:17, 15:17] = 2  # 8 voxels, floating
    labels[15, 2, 2] = 1  # 1 voxel
    labels[12, 12, 12] = 1  # touches the body at a corner only: floating as a mesh
    out, report = remove_islands(labels, 9)
    assert report["parts"] == 4 and report["removed_parts"] == 3
    assert report["removed_voxels"] == 10
    assert report["removed_by_material"] == {"1": 2, "2": 8}
    assert np.array_equal(out[2:12, 2:12, 2:12], labels[2:12, 2:12, 2:12])
    assert out.sum() == labels.sum() - 2 - 16
    same, report = remove_islands(labels, 0)
    assert same is labels and report["removed_parts"] == 0
    # through edges and corners the corner voxel belongs to the body
    out, report = remove_islands(labels, 9, joined_by="corners")
    assert report["parts"] == 3 and report["removed_parts"] == 2 and report["removed_voxels"] == 9
    assert out[12, 12, 12] == 1


@pytest.mark.parametrize("dim", [2, 3])
def test_a_structure_one_voxel_thick_across_the_diagonal_is_joined_not_removed(dim):
    """A strut and a plate one voxel thick across the voxels' diagonal (thin oblique bone,
    downsampled) are rows of parts a voxel each through faces: removed whole as floating
    parts before the fixes could join them, they now reach the fixes and become a model
    held together through faces."""
    from scipy import ndimage

    from dicer.connectivity import fix_stage

    labels = np.zeros((24,) * dim, np.uint8)
    labels[tuple(slice(2, 10) for _ in range(dim))] = 1  # a body of 8^dim voxels
    i = np.arange(10, 22)
    if dim == 2:  # a strut off the body's corner, 12 parts of a voxel
        labels[i, i] = 1
    else:  # a plate off the body's edge, 8 deep: 12 parts of 8 voxels
        labels[i[:, None], i[:, None], np.arange(2, 10)] = 1
    fixed, report = fix_stage(labels, names={"1": "bone"}, min_component_voxels=64, max_iterations=10, type_c=True,
                              max_type_c_rounds=4, majority_rounds=0, priority=None)
    assert report["islands"]["removed_voxels"] == 0
    assert np.all(fixed[labels == 1] == 1)  # every voxel kept: the fixes only add
    assert ndimage.label(fixed != 0)[1] == 1 and report["islands"]["parts"] == 1
    assert report["joined_parts"] == 12


def test_fix_priority_makes_the_result_independent_of_the_label_numbers():
    """Nested shells one voxel thick (scalp, skull, CSF, brain): with the highest label first,
    renumbering the same anatomy changed 2,516 voxels; with fix.priority naming the order the
    two numberings give the same model, and the label order itself gives the default's."""
    from dicer.connectivity import fix_stage

    n = 24
    x, y, z = np.mgrid[:n, :n, :n].astype(float)
    r = np.sqrt((x - 11.3) ** 2 + (y - 12.1) ** 2 + (z - 11.7) ** 2)
    lab = np.zeros((n,) * 3, np.uint8)
    lab[r < 11], lab[r < 10], lab[r < 9], lab[r < 6] = 1, 2, 3, 4
    names = {"1": "scalp", "2": "skull", "3": "csf", "4": "brain"}
    perm = np.array([0, 4, 3, 2, 1], np.uint8)  # brain 1, csf 2, skull 3, scalp 4
    renamed = {str(perm[int(k)]): v for k, v in names.items()}
    a, _ = fix_stage(lab, names=names)
    b, _ = fix_stage(perm[lab], names=renamed)
    assert (perm[a] != b).sum() > 1000  # the default: the numbers decide
    order = ["skull", "scalp", "brain", "csf"]
    c, rc = fix_stage(lab, names=names, priority=order)
    d, rd = fix_stage(perm[lab], names=renamed, priority=order)
    assert np.array_equal(perm[c], d) and c.dtype == lab.dtype
    assert rc["type_a"] == rd["type_a"] and rc["type_c"] == rd["type_c"] and rc["changed_voxels"] == rd["changed_voxels"]
    assert set(rc["type_c"]) <= set(names.values())
    assert connectivity_defects(c) == {"type_a": 0, "type_b": 0, "type_c": 0}
    same, _ = fix_stage(lab, names=names, priority=["brain", "csf", "skull", "scalp"])
    assert np.array_equal(same, a)
    with pytest.raises(DicerError, match="fix.priority names 'bone', which the materials do not hold"):
        fix_stage(lab, names=names, priority=["bone"])
    with pytest.raises(DicerError, match="the fixes take integer labels"):
        fix_stage(lab.astype(np.float32), names=names, priority=order)


def test_the_growth_and_faces_reached_leave_out_the_specks_removed_first():
    from dicer.connectivity import fix_stage

    lab = np.zeros((12, 12, 12), np.uint8)
    lab[2:10, 2:10, 2:10] = 1
    lab[0, 0, 11] = 1  # a speck on faces X0, Y0, Z1: removed as a floating part, no face reached
    fixed, report = fix_stage(lab, names={"1": "bone"}, min_component_voxels=8)
    assert report["solid_voxels"] == {"before": 512, "after": 512} and report["faces_reached"] == []
    assert report["islands"]["removed_voxels"] == 1 and report["joined_parts"] == 0
