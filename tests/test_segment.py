"""Segmentation: thresholds, morphology on nested classes, errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage as ndi

from dicer.config import load_config
from dicer.errors import DicerError
from dicer.image import Volume
from dicer.segment import class_priority, segment
from dicer.segment.morphology import (
    ball,
    clean_labels,
    closing,
    filter_components,
    opening_by_reconstruction,
)
from dicer.segment.thresholds import classify

AIR, SOFT, BONE = -1000.0, 40.0, 900.0
FACE3 = ndi.generate_binary_structure(3, 1)


def config(**segment):
    return load_config(settings={"segment": segment})


def one_class_config(**segment):
    return load_config(settings={"materials": [{"name": "solid"}], "segment": segment})


def head_like(n=32, noise=0.0, seed=0):
    """Air, a soft-tissue ball (radius 0.4 n) holding a bone shell (0.25..0.32 n); true labels too."""
    g = np.indices((n, n, n), dtype=np.float32) - (n - 1) / 2
    r = np.sqrt((g ** 2).sum(0))
    truth = np.zeros((n, n, n), np.uint8)
    truth[r <= 0.4 * n] = 1
    truth[(r >= 0.25 * n) & (r <= 0.32 * n)] = 2
    image = np.choose(truth, [AIR, SOFT, BONE]).astype(np.float32)
    if noise:
        image += np.random.default_rng(seed).normal(0, noise, image.shape).astype(np.float32)
    return Volume(image, (1.0, 1.0, 1.0)), truth


def dice(a, b):
    return 2 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)


# --- thresholds ---------------------------------------------------------------------


def test_classify_counts_thresholds_reached():
    a = np.array([-1000, -141, -140, 0, 225.9, 226, 3000], dtype=np.float32)
    assert classify(a, [-140, 226]).tolist() == [0, 0, 1, 1, 1, 2, 2]
    assert classify(np.array([np.nan, 1.0]), [0.5]).tolist() == [0, 1]


@settings(max_examples=40, deadline=None)
@given(arrays(np.int16, (7, 5), elements=st.integers(-500, 500)),
       st.lists(st.integers(-500, 500), min_size=1, max_size=4, unique=True))
def test_classify_matches_digitize(a, t):
    t = sorted(t)
    assert np.array_equal(classify(a, t), np.digitize(a, t))


def test_manual_exact_on_clean_volume():
    image, truth = head_like(32)
    labels, info = segment(image, config(method="manual", thresholds=[-140, 226], closing_radius=0),
                           "head.nii.gz")
    assert labels.array.dtype == np.uint8
    assert labels.spacing == image.spacing and labels.origin == image.origin
    assert np.array_equal(labels.array, truth)
    assert info["thresholds"] == [-140.0, 226.0]
    counts = info["classes"]
    assert counts["bone"]["voxels"] == np.count_nonzero(truth == 2)
    assert sum(v["fraction"] for v in counts.values()) == pytest.approx(1.0, abs=1e-5)
    closed, _ = segment(image, config(method="manual"), "head.nii.gz")  # closing fills 24 dents of the shell
    diff = closed.array != truth
    assert diff.sum() == 24 and (closed.array[diff] == 2).all() and (truth[diff] == 1).all()


def test_otsu_one_class_noisy():
    image, truth = head_like(32, noise=60, seed=1)
    image.array[truth == 2] = SOFT + np.random.default_rng(2).normal(0, 60, np.count_nonzero(truth == 2))
    labels, info = segment(image, one_class_config(method="otsu"), "one.nii.gz")
    assert AIR + 200 < info["thresholds"][0] < SOFT - 200
    assert dice(labels.array == 1, truth >= 1) > 0.999


def test_multiotsu_two_classes_noisy():
    image, truth = head_like(32, noise=60, seed=3)
    labels, info = segment(image, config(method="multiotsu"), "head.nii.gz")
    t1, t2 = info["thresholds"]
    assert AIR + 200 < t1 < SOFT - 150 and SOFT + 200 < t2 < BONE - 200
    assert dice(labels.array == 1, truth == 1) > 0.99
    assert dice(labels.array == 2, truth == 2) > 0.99


@settings(max_examples=60, deadline=None)
@given(counts=arrays(np.int64, st.integers(3, 14), elements=st.integers(0, 50)), thresholds=st.integers(1, 3))
def test_multiotsu_bins_are_the_best_split_of_all(counts, thresholds):
    """The dynamic programme finds the split an exhaustive search over every combination finds:
    the largest between-class sum."""
    import itertools

    from dicer.segment.thresholds import multiotsu_bins

    counts[0] += 1  # some value in the image
    b = counts.size
    if thresholds > b - 1:
        return

    def between(ends):
        edges = [0, *[e + 1 for e in ends], b]
        total = 0.0
        for lo, hi in zip(edges[:-1], edges[1:]):
            n, m = counts[lo:hi].sum(), (counts[lo:hi] * np.arange(lo, hi)).sum()
            total += m * m / n if n else 0.0
        return total

    scores = {ends: between(ends) for ends in itertools.combinations(range(b - 1), thresholds)}
    got = tuple(int(x) for x in multiotsu_bins(counts, thresholds))
    assert len(got) == thresholds and all(a < c for a, c in zip(got, got[1:]))
    assert between(got) == pytest.approx(max(scores.values()), rel=1e-12)


def test_multiotsu_splits_many_materials_as_skimage_splits_few():
    """Six materials (seven classes) of a seven-peak histogram are split in its valleys, in
    milliseconds (skimage's exhaustive search took hours beyond five classes); for three
    classes the thresholds are skimage's own."""
    from skimage.filters import threshold_multiotsu

    from dicer.segment.thresholds import multiotsu_thresholds

    rng = np.random.default_rng(5)
    peaks = np.arange(7) * 300.0
    values = np.concatenate([rng.normal(mu, 40.0, 20000) for mu in peaks])
    got = multiotsu_thresholds(values, 6, ["m"] * 6, "mr.nii.gz")
    valleys = (peaks[:-1] + peaks[1:]) / 2
    assert np.all(np.abs(np.array(got) - valleys) < 40.0)
    two = multiotsu_thresholds(values, 2, ["m"] * 2, "mr.nii.gz")
    assert np.array_equal(two, threshold_multiotsu(values, classes=3))
    # 16-bit integers: 256 bins too (scikit-image bins them one value a bin: 65,536 bins)
    scale = 65000.0 / np.ptp(values)
    got = multiotsu_thresholds(((values - values.min()) * scale).astype(np.uint16), 6, ["m"] * 6, "mr.nii.gz")
    assert np.all(np.abs(np.array(got) / scale + values.min() - valleys) < 40.0)


def test_thresholds_of_an_image_in_tiny_units_are_written_as_found():
    # an ADC map in m2/s: values about 1e-9. segmentation.json's thresholds are what the
    # smoothing reads back; rounded to 4 decimals they were both 0.0
    image, truth = head_like(32, noise=60, seed=3)
    scaled = Volume((image.array * 1e-12).astype(np.float32), image.spacing)
    labels, info = segment(scaled, config(method="multiotsu"), "adc.nii.gz")
    reference, ref_info = segment(image, config(method="multiotsu"), "head.nii.gz")
    t1, t2 = info["thresholds"]
    assert t1 < t2 and t1 != 0.0
    assert np.allclose(info["thresholds"], np.array(ref_info["thresholds"]) * 1e-12, rtol=1e-4)
    assert np.array_equal(labels.array, reference.array)


def test_multiotsu_warns_when_it_cuts_one_tissue_in_two():
    image, truth = head_like(32, noise=60, seed=3)
    _, info = segment(image, config(method="multiotsu"), "head.nii.gz")
    assert "warnings" not in info  # both thresholds in the valleys between air, soft tissue and bone
    image.array[truth == 2] = SOFT + np.random.default_rng(4).normal(0, 60, np.count_nonzero(truth == 2))
    _, info = segment(image, config(method="multiotsu"), "soft.nii.gz")  # no bone: two materials, one tissue
    said = [w for w in info["warnings"] if "at a peak of the image's histogram" in w]
    assert len(said) == 1 and "'soft_tissue'" in said[0]
    assert AIR - 200 < info["thresholds"][0] < AIR + 200  # the air cut in two: what the warning is for


@pytest.mark.parametrize("method", ["shape_connectivity", "multiotsu"])
def test_a_ct_with_its_contrast_inverted_is_warned_of(method):
    """Negated values (air bright, bone dark) put the air in the densest class: it covers the
    image's border, where a scan holds air; the scan as it is says nothing of it."""
    image, truth = head_like(32, noise=60, seed=3)
    _, info = segment(image, config(method=method), "head.nii.gz")
    assert not [w for w in info.get("warnings", []) if "of the image's border" in w]
    inverted = Volume(-image.array, image.spacing)
    labels, info = segment(inverted, config(method=method), "inverted.nii.gz")
    said = [w for w in info["warnings"] if "of the image's border" in w]
    assert len(said) == 1 and said[0].startswith("class 'bone', the densest, covers 100 % of the image's border")
    assert np.count_nonzero(labels.array[truth == 0] == 2) > 0.9 * np.count_nonzero(truth == 0)  # what it is for
    # a specimen filling an image of other units (a test plate of 0 and 1000 around a hole) is left alone
    from dicer.segment import _border_warnings

    plate = np.full((20, 20, 4), 2, np.uint8)
    plate[8:12, 8:12, :] = 0
    assert _border_warnings(plate, ["soft_tissue", "bone"], 0.0) == []
    assert len(_border_warnings(plate, ["soft_tissue", "bone"], -1000.0)) == 1


def test_otsu_on_an_image_without_air_in_hu_is_warned_of():
    # an MR under the CT materials: multi-Otsu split it and its brightest tissue became 'bone'
    image, truth = head_like(32, noise=60, seed=3)
    mr = Volume(np.where(truth == 0, 30.0, np.where(truth == 1, 1800.0, 3000.0))
                + np.random.default_rng(5).normal(0, 40, truth.shape).clip(-29), image.spacing)
    _, info = segment(mr, config(method="multiotsu"), "mr.nii.gz")
    said = [w for w in info["warnings"] if w.startswith("the image holds no value below -500")]
    assert len(said) == 1 and "named soft_tissue, bone in order of intensity" in said[0]
    # one class: no "brightest" of one
    one = load_config(settings={"materials": [{"name": "head"}], "segment": {"method": "otsu"}})
    _, info = segment(mr, one, "mr.nii.gz")
    said = [w for w in info["warnings"] if w.startswith("the image holds no value below -500")]
    assert len(said) == 1 and "named head: check that it holds what 'head' names" in said[0]
    assert "brightest" not in said[0]


def test_the_default_ct_ranges_on_an_image_without_air_in_hu_are_warned_of():
    """An MR offset below zero (its background -450) took its brain for 'bone' at 15 GPa under
    the default segment.ranges, exit 0 and not a line."""
    image, truth = head_like(32, noise=60, seed=3)
    mr = Volume(np.where(truth == 0, -450.0, np.where(truth == 1, 350.0, 1350.0))
                + np.abs(np.random.default_rng(5).normal(0, 40, truth.shape)), image.spacing)
    _, info = segment(mr, config(), "mr.nii.gz")
    said = [w for w in info["warnings"] if w.startswith("the image holds no value below -500")]
    assert len(said) == 1 and "the default segment.ranges are CT values in HU and made 'soft_tissue' from" in said[0]
    assert said[0].endswith("for an MR set segment.method: multiotsu (docs/segmentation.md), or segment.ranges for "
                            "this image's values")
    # a CT with air, or ranges of the user's own: no such line
    _, info = segment(image, config(), "ct.nii.gz")
    assert not [w for w in info.get("warnings", []) if w.startswith("the image holds no value below -500")]
    _, info = segment(mr, config(ranges=[[-200, 900], [900, 2000]]), "mr.nii.gz")
    assert not [w for w in info.get("warnings", []) if w.startswith("the image holds no value below -500")]


def test_histogram_thresholds_lie_midway_across_an_empty_gap():
    """Otsu's criterion is flat across an empty gap and the search took its lower end, the
    lower class's own value: smooth.fit_to_scan then grew a ball of 1000 on 0 (radius 8) by 11.5 %."""
    from dicer.segment.thresholds import multiotsu_thresholds, otsu_thresholds

    r = np.sqrt(((np.indices((40, 40, 40)) - 19.5) ** 2).sum(0))
    assert otsu_thresholds(np.where(r < 10, 1000.0, 0.0).ravel(), 1, ["x"], "s") == [500.0]
    t = multiotsu_thresholds(np.select([r < 6, r < 12], [234.0, 110.0], 0.0).ravel(), 2, ["a", "b"], "s")
    assert abs(t[0] - 55) < 1 and abs(t[1] - 172) < 1  # midway, within half a bin of 0.9
    # with values in the gap (noise, partial volume) the criterion decides alone
    noisy = np.where(r < 10, 1000.0, 0.0) + np.random.default_rng(0).normal(0, 150, r.shape)
    assert 300 < otsu_thresholds(noisy.ravel(), 1, ["x"], "s")[0] < 700


def test_otsu_of_one_material_at_a_peak_says_so_without_naming_materials_listed():
    noise = Volume(np.random.default_rng(2).normal(0, 400, (24, 24, 16)), (1.0, 1.0, 1.0))
    one = load_config(settings={"materials": [{"name": "head"}], "segment": {"method": "otsu"}})
    _, info = segment(noise, one, "n.nii.gz")
    said = [w for w in info["warnings"] if w.startswith("otsu put the threshold")]
    assert len(said) == 1 and "the image holds one tissue and its background alike" in said[0]
    assert "fewer tissues than the materials listed" not in said[0]


def test_segment_2d():
    image, truth = head_like(32)
    im2 = Volume(image.array[:, :, 16].copy(), (0.5, 0.7))
    labels, info = segment(im2, config(method="manual", closing_radius=0), "slice.png")
    assert labels.array.shape == (32, 32) and labels.spacing == (0.5, 0.7)
    assert np.array_equal(labels.array, truth[:, :, 16])


# --- morphology ---------------------------------------------------------------------


def test_ball_radius_1_is_the_face_cross():
    assert np.array_equal(ball(1, 3), FACE3)
    assert ball(2, 3).sum() == 33 and ball(2, 2).sum() == 13


def test_opening_by_reconstruction_removes_speck_keeps_attached_plate():
    m = np.zeros((30, 30, 30), bool)
    m[2:12, 2:12, 2:12] = True            # big block
    m[12:28, 5:20, 6] = True              # 1-voxel plate attached to it
    m[20, 25, 25] = True                  # isolated speck
    m[22:24, 25:27, 20:22] = True         # 2x2x2 blob (thinner than 3)
    out = opening_by_reconstruction(m, 1)
    expected = m.copy()
    expected[20, 25, 25] = False
    expected[22:24, 25:27, 20:22] = False
    assert np.array_equal(out, expected)
    assert out.sum() == 1000 + 16 * 15
    # a plain opening would strip the plate
    assert ndi.binary_opening(m, FACE3).sum() < 1000


def test_opening_keeps_objects_cut_by_the_border():
    m = np.zeros((10, 10, 10), bool)
    m[:, :, 0:2] = True                   # a 2-voxel slab on the border plane
    assert opening_by_reconstruction(m, 1).sum() == 200


def test_closing_fills_one_voxel_hole_and_keeps_border():
    m = np.ones((9, 9, 9), bool)
    m[4, 4, 4] = False
    out = closing(m, 1)
    assert out.all()
    m2 = np.zeros((9, 9, 9), bool)
    m2[:, :, :3] = True
    assert np.array_equal(closing(m2, 1), m2)


def test_keep_largest_drops_separate_arc():
    m = np.zeros((40, 40, 20), bool)
    g = np.indices(m.shape)
    m[((g[0] - 20) ** 2 + (g[1] - 18) ** 2) <= 100] = True            # the head: a cylinder of radius 10
    arc = (np.abs(np.hypot(g[0] - 20, g[1] - 18) - 14) < 1.0) & (g[1] < 12)
    m |= arc                                                         # a thin arc behind it, not touching
    assert ndi.label(m, FACE3)[1] == 2
    out = filter_components(m, "largest")
    assert out.sum() == m.sum() - arc.sum()
    assert not (out & arc).any()
    assert filter_components(m, "all", min_size=arc.sum() + 1).sum() == out.sum()


@settings(max_examples=30, deadline=None)
@given(arrays(bool, (8, 8, 6)), st.integers(1, 2))
def test_opening_keeps_or_drops_whole_components(m, r):
    out = opening_by_reconstruction(m, r)
    assert not (out & ~m).any()
    comp, n = ndi.label(m, FACE3)
    for c in range(1, n + 1):
        part = out[comp == c]
        assert part.all() or not part.any()


def test_nested_classes_closing_bone_leaves_no_holes():
    # soft tissue block with a bone plate holding a 1-voxel cavity: closing fills it with bone,
    # and a 1-voxel soft-tissue skin on the body survives the opening (cumulative masks).
    lab = np.zeros((20, 20, 20), np.uint8)
    lab[2:18, 2:18, 2:18] = 1
    lab[5:15, 5:15, 8:10] = 2
    lab[5:15, 5:15, 10] = 2
    lab[10, 10, 9] = 1                    # a cavity inside the bone plate
    lab[5:15, 5:15, 18] = 1               # a 1-voxel skin on the body surface
    out, info = clean_labels(lab, 2, 1, 1)
    assert out[10, 10, 9] == 2
    assert (out[5:15, 5:15, 18] == 1).all()
    assert np.count_nonzero(out == 2) == 300
    assert np.count_nonzero(out == 0) == np.count_nonzero(lab == 0)
    assert info["removed_by_opening"] == {1: 0, 2: 0}


def test_bone_speck_becomes_soft_tissue_and_soft_speck_becomes_background():
    lab = np.zeros((20, 20, 20), np.uint8)
    lab[2:18, 2:18, 2:12] = 1
    lab[8, 8, 6] = 2                      # bone speck in soft tissue
    lab[10, 10, 16] = 1                   # soft speck in air
    out, info = clean_labels(lab, 2, 1, 0)
    assert out[8, 8, 6] == 1 and out[10, 10, 16] == 0
    assert info["removed_by_opening"] == {1: 1, 2: 1}


def test_priority_settles_non_nested_voxels():
    # K=3, a middle class emptied between kept outer and inner masks: (1, 0, 1) voxels
    lab = np.zeros((12, 12, 12), np.uint8)
    lab[1:11, 1:11, 1:11] = 3
    out_default, _ = clean_labels(lab, 3, 0, 0)
    assert np.array_equal(out_default, lab)
    prio = class_priority(["a", "b", "c"], ["a"])
    assert prio == [1, 3, 2]


def test_headrest_dropped_by_keep_largest():
    image, truth = head_like(48)
    g = np.indices(image.array.shape)
    arc = (np.abs(np.hypot(g[0] - 23.5, g[1] - 23.5) - 22) < 1.4) & (g[1] < 10) & (g[2] > 5) & (g[2] < 40)
    image.array[arc] = SOFT
    cfg = config(method="manual", keep="largest", closing_radius=0)
    labels, info = segment(image, cfg, "head.nii.gz")
    assert not labels.array[arc].any()
    assert np.array_equal(labels.array, truth)
    # the defaults (keep: body, closing radius 1): the arc a voxel or two from the head is dropped
    # too, the parts being chosen before the closing bridges the gap (it kept the arc until then)
    labels_body, info = segment(image, config(method="manual"), "head.nii.gz")
    assert not labels_body.array[arc].any()
    assert info["removed_parts"]["soft_tissue"]["largest"] == int(np.count_nonzero(arc))
    labels_all, _ = segment(image, config(method="manual", keep="all"), "head.nii.gz")
    assert labels_all.array[arc].sum() > 0


def test_keep_per_class_list():
    image, truth = head_like(32)
    image.array[0:3, 0:3, 0:3] = BONE     # a separate dense block in the corner
    labels, _ = segment(image, config(method="manual", keep=["all", "largest"]), "x")
    assert (labels.array[0:3, 0:3, 0:3] == 1).all()  # dropped from bone, kept as the outer class
    labels, _ = segment(image, config(method="manual", keep="largest"), "x")
    assert (labels.array[0:3, 0:3, 0:3] == 0).all()


# --- errors -------------------------------------------------------------------------


@pytest.mark.parametrize("settings_, words", [
    ({"method": "manual", "thresholds": [0.0]}, ["head.nii", "1 value", "2 material", "soft_tissue, bone"]),
    ({"method": "manual", "thresholds": [300.0, 200.0]}, ["head.nii", "increase strictly", "'bone'"]),
    ({"method": "manual", "thresholds": [5000.0, 6000.0]}, ["head.nii", "no voxel >= 5000", "soft_tissue",
                                                            "lower segment.thresholds"]),
    ({"method": "otsu"}, ["head.nii", "otsu", "2 materials", "multiotsu"]),
    ({"method": "manual", "priority": ["marrow"]}, ["head.nii", "segment.priority", "marrow"]),
    ({"method": "manual", "keep": ["largest"]}, ["head.nii", "segment.keep", "1 entries", "2 materials"]),
])
def test_errors_name_file_key_and_fix(settings_, words):
    image, _ = head_like(16)
    with pytest.raises(DicerError) as err:
        segment(image, config(**settings_), "head.nii")
    message = str(err.value)
    assert "\n" not in message
    for w in words:
        assert w in message


def test_error_single_grey_level():
    with pytest.raises(DicerError, match=r"flat.nii: the image has a single grey level \(7\)"):
        segment(Volume(np.full((8, 8, 8), 7, np.int16), (1, 1, 1)), config(method="multiotsu"), "flat.nii")


def test_error_opening_removes_everything():
    a = np.full((20, 20, 20), AIR, np.float32)
    a[::4, ::4, ::4] = SOFT               # isolated single voxels only
    with pytest.raises(DicerError, match=r"dots.nii: the morphology removed every voxel.*lower segment.opening_radius"):
        segment(Volume(a, (1, 1, 1)), config(method="manual"), "dots.nii")
    labels, _ = segment(Volume(a, (1, 1, 1)), config(method="manual", opening_radius=0, closing_radius=0, keep="all"), "d")
    assert np.count_nonzero(labels.array) == 125


def test_error_4d_and_nan_image():
    with pytest.raises(DicerError, match="4D image"):
        segment(Volume(np.zeros((2, 2, 2, 2)), (1, 1, 1, 1)), config(), "four.nii")
    with pytest.raises(DicerError, match="no finite value"):
        segment(Volume(np.full((3, 3, 3), np.nan), (1, 1, 1)), config(), "nan.nii")


# --- shape connectivity ----------------------------------------------------------------

from pathlib import Path  # noqa: E402

from dicer.segment.thresholds import (  # noqa: E402
    bin_image,
    cooccurrence,
    shape_connectivity_thresholds,
)

CT = Path(__file__).resolve().parents[2] / "shared" / "data" / "cranium_ct.nii.gz"


def _pairs_brute(b, nbins):
    m = np.zeros((nbins, nbins), np.int64)
    for ax in range(b.ndim):
        a = np.moveaxis(b, ax, 0)
        np.add.at(m, (a[:-1].ravel(), a[1:].ravel()), 1)
    return m + m.T


@settings(max_examples=25, deadline=None)
@given(arrays(np.uint16, st.one_of(st.tuples(st.integers(1, 40), st.integers(1, 6), st.integers(1, 5)),
                                   st.tuples(st.integers(1, 9), st.integers(1, 9))),
              elements=st.integers(0, 4)),
       st.integers(1, 7))
def test_cooccurrence_matches_brute_force(b, slab):
    assert np.array_equal(cooccurrence(b, 5, slab=slab), _pairs_brute(b, 5))


def test_bin_image_lut_and_searchsorted_agree():
    rng = np.random.default_rng(0)
    a = rng.integers(-1024, 2000, (40, 40, 40)).astype(np.int16)
    edges = np.array([-300.0, -200.5, 0.0, 150.0, 700.0])
    expected = np.searchsorted(edges, a.astype(float).ravel(), side="right").reshape(a.shape)
    assert np.array_equal(bin_image(a, edges), expected)                       # lookup table
    assert np.array_equal(bin_image(a.astype(np.float32), edges), expected)    # whole-valued float
    assert np.array_equal(bin_image(a.astype(np.float32) + 0.25, edges),
                          np.searchsorted(edges, a.astype(float).ravel() + 0.25, side="right").reshape(a.shape))


def _solidity_sum(labels, k):
    """J computed directly from a label volume: sum over classes of same-class neighbour fraction."""
    m = _pairs_brute(labels.astype(np.int64), k + 1)
    rows = m.sum(axis=1)
    return sum(m[c, c] / rows[c] for c in range(k + 1) if rows[c])


def test_criterion_is_the_sum_of_class_solidities():
    image, _ = head_like(24, noise=150, seed=5)
    t, search = shape_connectivity_thresholds(image.array, [[-700, -100], [300, 700]], ["soft", "bone"], "h", bins=40)
    assert -700 <= t[0] <= -100 and 300 <= t[1] <= 700
    direct = _solidity_sum(classify(image.array, t), 2)
    assert search["criterion_max"] == pytest.approx(direct, abs=1e-6)
    # the curve of each class peaks at the chosen threshold and agrees with a direct evaluation
    curve = search["criterion"]["bone"]
    i = int(np.argmax(curve["values"]))
    assert curve["thresholds"][i] == pytest.approx(t[1], abs=1e-3)
    alt = curve["thresholds"][3]
    assert curve["values"][3] == pytest.approx(_solidity_sum(classify(image.array, [t[0], alt]), 2), abs=1e-5)


def test_plateau_centre_on_a_clean_two_level_image():
    a = np.zeros((20, 20, 20), np.int16)
    a[5:15, 5:15, 5:15] = 100
    t, _ = shape_connectivity_thresholds(a, [[10, 90]], ["solid"], "x", bins=80)
    assert t == [50.0]


def test_shape_connectivity_2d():
    image, truth = head_like(48, noise=80, seed=2)
    im2 = Volume(image.array[:, :, 24].copy(), (1.0, 1.0))
    labels, info = segment(im2, config(method="shape_connectivity", keep="all"), "slice.png")
    assert dice(labels.array == 2, truth[:, :, 24] == 2) > 0.97
    assert -400 <= info["thresholds"][0] <= 0 and 100 <= info["thresholds"][1] <= 1000


@pytest.mark.parametrize("noise", [30.0, 100.0])
def test_head_phantom_acceptance(head_phantom, noise):
    truth = head_phantom["truth"]
    image = head_phantom[noise]
    scores = {}
    for method in ("shape_connectivity", "multiotsu"):
        labels, info = segment(image, config(method=method), "head")
        a = labels.array
        scores[method] = [dice(a == c, truth == c) for c in (1, 2)]
        if method == "shape_connectivity":
            (lo1, hi1), (lo2, hi2) = info["ranges"]
            assert lo1 <= info["thresholds"][0] <= hi1 and lo2 <= info["thresholds"][1] <= hi2
            assert ndi.label(a == 2, FACE3)[1] == 1          # the thin skull stays one piece
            assert ndi.label(a > 0, FACE3)[1] == 1           # the headrest is gone
            assert not a[head_phantom["headrest"]].any()
    assert min(scores["shape_connectivity"]) >= 0.95
    for sc, otsu in zip(scores["shape_connectivity"], scores["multiotsu"]):
        assert sc >= otsu - 0.002


@pytest.fixture(scope="module")
def head_phantom():
    phantoms = pytest.importorskip("dicer.phantoms")
    truth = phantoms.phantom_labels("head", size=64).array
    out = {"truth": truth}
    for noise in (30.0, 100.0):
        out[noise] = phantoms.make_phantom("head", size=64, noise=noise, seed=0)
    clean = phantoms.make_phantom("head", size=64, noise=0.0).array
    out["headrest"] = (truth == 0) & (clean > -500)
    assert out["headrest"].sum() > 100
    return out


@pytest.mark.parametrize("ranges, words", [
    ([[-400, 0]], ["head.nii", "1 range(s) for 2 material", "missing: 'bone'"]),
    ([[-400, 200], [100, 1000]], ["head.nii", "'bone'", "overlaps or precedes", "'soft_tissue'"]),
    ([[100, 1000], [-400, 0]], ["head.nii", "'bone'", "overlaps or precedes"]),
    ([[-400, 0], [2000, 3000]], ["head.nii", "'bone'", "[2000, 3000]", "image's values span -1000 .. 900"]),
    ([[-3000, -2000], [100, 1000]], ["head.nii", "'soft_tissue'", "move the range inside"]),
    ([[0, -400], [100, 1000]], ["head.nii", "'soft_tissue'", "low must be below high"]),
])
def test_shape_connectivity_range_errors(ranges, words):
    image, _ = head_like(16)
    with pytest.raises(DicerError) as err:
        segment(image, config(method="shape_connectivity", ranges=ranges), "head.nii")
    for w in words:
        assert w in str(err.value)


def test_shape_connectivity_single_grey_level():
    with pytest.raises(DicerError, match="single grey level"):
        segment(Volume(np.zeros((6, 6, 6), np.int16), (1, 1, 1)), config(method="shape_connectivity"), "f.nii")


def test_default_method_is_shape_connectivity():
    assert load_config()["segment"]["method"] == "shape_connectivity"
    image, truth = head_like(32, noise=50, seed=4)
    labels, info = segment(image, load_config(), "head")
    assert info["method"] == "shape_connectivity"
    assert dice(labels.array == 2, truth == 2) > 0.98


# --- pictures -------------------------------------------------------------------------


def test_overlay_and_threshold_plot_are_deterministic(tmp_path):
    from dicer.io.pictures import save_overlay_png, save_threshold_plot

    image, _ = head_like(24, noise=40, seed=1)
    labels, info = segment(image, config(method="shape_connectivity"), "head")
    paths = []
    for i in range(2):
        p = save_overlay_png(image, labels, tmp_path / f"o{i}.png", f"thresholds {info['thresholds']}", 2,
                             ["soft_tissue", "bone"])
        q = save_threshold_plot(info, tmp_path / f"c{i}.png")
        paths.append((p.read_bytes(), q.read_bytes()))
    assert paths[0] == paths[1]
    data = paths[0][0]
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and b"Software" not in data and b"matplotlib" not in data
    assert sorted(x.name for x in tmp_path.iterdir()) == ["c0.png", "c1.png", "o0.png", "o1.png"]
    two_d = save_overlay_png(Volume(image.array[:, :, 12].copy(), (1, 1)),
                             Volume(labels.array[:, :, 12].copy(), (1, 1)), tmp_path / "s.png")
    assert two_d.stat().st_size > 1000


def test_threshold_plot_needs_a_curve(tmp_path):
    from dicer.io.pictures import save_threshold_plot

    with pytest.raises(DicerError, match="needs segment.method=shape_connectivity"):
        save_threshold_plot({"method": "manual", "thresholds": [0.0]}, tmp_path / "c.png")
    assert not list(tmp_path.iterdir())


# --- the real head CT -------------------------------------------------------------------


@pytest.mark.skipif(not CT.exists(), reason="shared head CT not present")
def test_real_head_ct():
    import SimpleITK as sitk

    img = sitk.ReadImage(str(CT))
    a = sitk.GetArrayFromImage(img).transpose(2, 1, 0)
    image = Volume(a, img.GetSpacing())
    labels, info = segment(image, load_config(), str(CT))
    t1, t2 = info["thresholds"]
    assert -400 <= t1 <= 0 and 100 <= t2 <= 1000
    assert -170 <= t1 <= -120 and 120 <= t2 <= 240      # measured: -144 and 140 HU
    lab = labels.array
    assert ndi.label(lab > 0, FACE3)[1] == 1
    # the raw body mask holds the head and the two headrest parts; only the head remains
    comp, n = ndi.label(a >= t1, FACE3)
    sizes = np.bincount(comp.ravel())[1:]
    big = np.argsort(sizes)[::-1][:3] + 1
    assert sizes[big[1] - 1] > 20000 and sizes[big[2] - 1] > 20000
    assert not lab[(comp == big[1]) | (comp == big[2])].any()
    bone = ndi.label(lab == 2, FACE3)
    bone_sizes = np.bincount(bone[0].ravel())[1:]
    assert bone_sizes.max() > 0.99 * bone_sizes.sum()    # the skull is one component (plus specks < 1000)
    assert 0.05 < info["classes"]["bone"]["fraction"] < 0.08
    assert 0.23 < info["classes"]["soft_tissue"]["fraction"] < 0.28


def test_keep_body_warns_when_it_drops_a_part_like_the_one_kept():
    """keep: body drops a headrest quietly (a small part), but a second leg scanned beside the
    first is anatomy: dropping it is said, with its size against the part kept."""
    shape = (60, 40, 20)
    g = np.indices(shape)
    image = np.full(shape, AIR, np.float32)
    for cx, r in ((16, 12), (44, 11)):  # two legs, 12 and 11 voxels in radius
        leg = np.hypot(g[0] - cx, g[1] - 20) <= r
        image[leg] = SOFT
        image[leg & (np.hypot(g[0] - cx, g[1] - 20) <= 4)] = BONE
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), config(method="manual", keep="body"), "legs.nii.gz")
    part = info["removed_parts"]["soft_tissue"]
    kept = int(np.count_nonzero(labels.array))
    assert part["parts"] == 1 and part["largest_kept"] == kept and 0.8 < part["largest"] / kept < 0.9
    assert len(info["warnings"]) == 1 and "set segment.keep: all" in info["warnings"][0]
    assert not labels.array[35:, :, :].any()
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), config(method="manual", keep="all"), "legs.nii.gz")
    assert "warnings" not in info and info["removed_parts"] == {} and labels.array[35:, :, :].any()
    # a headrest-sized part: dropped without a warning, but counted
    image[32:, :, :] = AIR
    image[48:58, 36:39, :] = SOFT  # 600 voxels, 7 % of the leg
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), config(method="manual", keep="body"), "rest.nii.gz")
    part = info["removed_parts"]["soft_tissue"]
    assert "warnings" not in info and part["parts"] == 1 and 500 <= part["voxels"] <= 700


def test_a_class_left_without_voxels_is_warned_of():
    """A material with no voxel gets no elements and no element set: said, with the cause."""
    g = np.indices((24, 24, 24))
    image = np.full((24, 24, 24), AIR, np.float32)
    image[(np.abs(g - 12) <= 6).all(axis=0)] = BONE  # a bone block in air: no soft tissue
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), config(method="manual"), "block.nii.gz")
    assert info["classes"]["soft_tissue"]["voxels"] == 0 and info["classes"]["bone"]["voxels"] == 13 ** 3
    assert len(info["warnings"]) == 1
    assert info["warnings"][0].startswith("class 'soft_tissue' holds no voxel: no image value lies at or above -140")
    # no value reaches the bone threshold: bone is empty
    image[image == BONE] = SOFT
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), config(method="manual"), "soft.nii.gz")
    assert info["classes"]["bone"]["voxels"] == 0 and len(info["warnings"]) == 1
    assert "class 'bone' holds no voxel" in info["warnings"][0] and "no image value lies at or above 226" in \
        info["warnings"][0]
    # bone thresholded, then opened away (a 1-voxel bone speck): emptied by the morphology
    image[12, 12, 12] = BONE
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), config(method="manual"), "speck.nii.gz")
    assert info["thresholded"]["bone"] == 1 and info["classes"]["bone"]["voxels"] == 0
    assert info["warnings"] == [info["warnings"][0]] and "after the morphology (1 thresholded" in info["warnings"][0]
    assert "segment.min_component_size" in info["warnings"][0]  # a setting that removes classes too


def test_thresholds_at_the_end_of_their_range_are_warned_of():
    """An MR-like image (values 0..~1000, slightly negative noise) under the CT defaults: the
    soft-tissue threshold runs to the end of its range and the whole box becomes body."""
    rng = np.random.default_rng(3)
    g = np.indices((32, 32, 32)) - 15.5
    r = np.sqrt((g ** 2).sum(0))
    image = np.where(r < 12, 600.0, 250.0) + rng.normal(0, 20, r.shape) - 20
    image[r >= 14] = rng.normal(8, 3, np.count_nonzero(r >= 14))  # dark surround, a few below 0
    labels, info = segment(Volume(image.astype(np.float32), (1.0, 1.0, 1.0)), config(), "mr.nii.gz")
    assert info["thresholds"][0] == 0.0  # the soft-tissue range is [-400, 0]: its end
    assert any("threshold of 'soft_tissue' (0) lies at an end of its search range [-400, 0]" in w
               for w in info["warnings"])
    assert any(w.startswith("only ") and "% of the image is background" in w for w in info["warnings"])
    # ranges that fit the image: no warning
    labels, info = segment(Volume(image.astype(np.float32), (1.0, 1.0, 1.0)),
                           config(ranges=[[40, 240], [300, 550]]), "mr.nii.gz")
    assert "warnings" not in info, info.get("warnings")


def _padded_ct(pad: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A CT slab (HU) with ``pad`` outside its field-of-view circle, noisy air inside it, a
    body of 40 HU with a 1000 HU ring; and the true labels."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(48) - 23.5, np.arange(48) - 23.5, indexing="ij")
    r = np.hypot(x, y)
    truth = np.where(r < 14, np.where((r > 9) & (r < 12), 2, 1), 0)[:, :, None].repeat(12, axis=2)
    hu = np.choose(truth, [-1000.0, 40.0, 1000.0]) + rng.normal(0, 15, truth.shape)
    hu[r >= 22] = pad
    return np.rint(hu).astype(np.int16), truth


@pytest.mark.parametrize("pad", [-3024, -2000, -2048])
@pytest.mark.parametrize("method", ["multiotsu", "otsu", "shape_connectivity", "wide ranges"])
def test_padding_outside_the_field_of_view_is_air_for_the_thresholds(pad, method):
    """Otsu and multi-Otsu split the padding from the scan (thresholds -3000 and -947: the
    air in the field of view became soft tissue, the body bone), and so did search ranges
    reaching below -1000."""
    image, truth = _padded_ct(pad)
    names = ["tissue"] if method == "otsu" else ["soft_tissue", "bone"]
    settings = {"method": method, "opening_radius": 0, "closing_radius": 0}
    if method == "wide ranges":
        settings.update(method="shape_connectivity", ranges=[[-2900, 0], [100, 1000]])
    labels, info = segment(Volume(image, (0.8, 0.8, 2.0)), {"materials": [{"name": n} for n in names],
                                                            "segment": settings})
    assert info["padding"] == {"value": float(pad), "voxels": int(np.count_nonzero(image == pad))}
    want = (truth > 0).astype(np.uint8) if method == "otsu" else truth
    assert np.count_nonzero(labels.array != want) <= 0.002 * want.size


def test_a_shifted_ct_with_padding_is_refused_as_one_without():
    """A CT stored as HU + 1024 with padding outside its field of view (-2000): the padding, taken
    for air at -1024, put the default soft-tissue range [-400, 0] inside the image's values, and
    the search made the air soft tissue and the body bone (exit 0, no word). The ranges are
    checked against the scan's own values, as without padding."""
    image, _ = _padded_ct(-2000)
    shifted = np.where(image == -2000, -2000, np.maximum(image + 1024, 0)).astype(np.int16)  # stored unsigned
    with pytest.raises(DicerError, match=r"span 0 \.\. \d+; .* a CT stored as HU \+ 1024 .* 1024 subtracted"):
        segment(Volume(shifted, (0.8, 0.8, 2.0)), source="ct.nii.gz")
    # in HU with the same padding: segmented as before
    labels, info = segment(Volume(image, (0.8, 0.8, 2.0)), {"segment": {"opening_radius": 0, "closing_radius": 0}})
    assert info["padding"]["value"] == -2000.0 and labels.array.max() == 2


def test_a_box_without_air_names_a_lost_rescale_intercept():
    """A CT stored as HU + 1024 and resampled (a few values below 0): the defaults' ranges lie
    within its values and the whole box becomes the body; the warning names the intercept."""
    image, _ = _padded_ct(-1000)
    dips = (np.arange(image.size) % 997 == 0).reshape(image.shape)  # the resampling's few values below 0
    shifted = np.maximum(image.astype(np.float32) + 1024.0, 0.0) - 60.0 * dips
    _, info = segment(Volume(shifted, (0.8, 0.8, 2.0)), {"segment": {"opening_radius": 0, "closing_radius": 0}})
    said = [w for w in info["warnings"] if w.startswith("only ")]
    assert len(said) == 1 and "with no value near air's -1000 HU: a CT stored as HU + 1024" in said[0]
    # a scan in HU, its air there, gets no such word
    _, info = segment(Volume(image.astype(np.float32), (0.8, 0.8, 2.0)))
    assert not any("HU + 1024" in w for w in info.get("warnings", []))


def test_air_at_its_lowest_values_is_no_padding():
    """A CT stored down to -1024 (unsigned with intercept -1024), or noisy air reaching
    below it, has no padding; nor has an MR."""
    from dicer.segment import padding_value

    image, _ = _padded_ct(-1024)
    assert padding_value(image) is None
    noisy = image.astype(float)
    noisy[noisy == -1024] = np.random.default_rng(1).normal(-1040, 30, int(np.count_nonzero(noisy == -1024)))
    assert padding_value(noisy) is None
    assert padding_value(np.random.default_rng(2).normal(300, 100, (20, 20, 5))) is None


def test_a_threshold_plot_without_a_criterion_is_said_not_to_be_written(tmp_path, caplog):
    from dicer.cli import main
    from dicer.io.images import write_image

    image, _ = _padded_ct(-1024)
    write_image(Volume(image.astype(np.float32), (1.0, 1.0, 1.0)), tmp_path / "ct.nii.gz")
    assert main(["segment", str(tmp_path / "ct.nii.gz"), "-o", str(tmp_path / "l.nii.gz"), "--plot",
                 str(tmp_path / "t.png"), "--set", "segment.method=multiotsu", "-q"]) == 0
    assert "segment.method multiotsu has none, so" in caplog.text and not (tmp_path / "t.png").exists()


def test_the_opening_keeps_its_size_in_mm_on_thick_slices():
    """On 5 mm slices a 10 mm bone plate is two voxels thick: a ball of one voxel along every
    axis (15 mm across the slices) removed it whole, 64 % of the bone (until 6 December 2026);
    a ball of one voxel of the finest axis, 0.5 mm, is one slice thick."""
    image = np.full((40, 40, 12), -1000.0)
    image[5:35, 5:35, 2:10] = 40.0
    image[10:26, 10:30, 5:7] = 1000.0  # the plate: 2 slices
    image[28:31, 28:31, 2:10] = 1000.0  # a rod along z, 3 voxels across
    thick = Volume(image, (0.5, 0.5, 5.0))
    manual = {"segment": {"method": "manual", "thresholds": [-300, 300]}}
    labels, info = segment(thick, manual)
    assert info["removed_by_opening"]["bone"] == 0 and "warnings" not in info
    assert (labels.array[10:26, 10:30, 5:7] == 2).all() and (labels.array[28:31, 28:31, 2:10] == 2).all()
    # the same voxels on an isotropic grid: the ball is one voxel along z too, the plate goes
    _, iso = segment(Volume(image, (0.5, 0.5, 0.5)), manual)
    assert iso["removed_by_opening"]["bone"] == 640


def test_an_opening_that_removes_much_of_a_class_is_warned_of():
    """A wall 1 mm thick (two 0.5 mm voxels) goes whole, 82 % of the bone, and is said with
    the ball's size per axis."""
    image = np.full((40, 40, 12), -1000.0)
    image[5:35, 5:35, 2:10] = 40.0
    image[10:12, 10:30, 2:10] = 1000.0  # the wall
    image[28:31, 28:31, 2:10] = 1000.0  # a rod along z, 3 voxels across
    manual = {"segment": {"method": "manual", "thresholds": [-300, 300]}}
    labels, info = segment(Volume(image, (0.5, 0.5, 5.0)), manual)
    said = [w for w in info.get("warnings", []) if w.startswith("the opening removed")]
    assert said == ["the opening removed 320 of the 392 thresholded voxels of 'bone' (82 %): parts narrower than "
                    "1.5 x 1.5 x 5 mm (3x3x1 voxels) go; lower segment.opening_radius"]
    # a tenth is said (a quarter let 14 % pass)
    image[10:12, 10:30, 2:10] = 40.0
    image[10:12, 10:17, 5] = 1000.0  # a patch two voxels wide: 14 voxels beside the rod's 72
    _, info = segment(Volume(image, (0.5, 0.5, 5.0)), manual)
    assert info["removed_by_opening"]["bone"] == 14 and info["thresholded"]["bone"] == 86
    assert [w for w in info["warnings"] if w.startswith("the opening removed 14 of the 86")]


def test_a_few_metal_voxels_leave_multi_otsu_on_the_bulk_of_the_image():
    """Eight voxels at 30,000 HU spread multi-Otsu's 256 bins over 31,000 HU: its bone
    threshold, 1057, lay above the skull (1000 HU), which became soft tissue."""
    image, truth = _padded_ct(-1024)
    image[20:22, 20:22, 4:6] = 30000
    truth = truth.copy()
    truth[20:22, 20:22, 4:6] = 2
    labels, info = segment(Volume(image, (1.0, 1.0, 1.0)), {"segment": {"method": "multiotsu", "opening_radius": 0,
                                                                        "closing_radius": 0}})
    assert info["thresholds"][1] < 900
    assert np.count_nonzero(labels.array != truth) <= 0.002 * truth.size


@settings(max_examples=150, deadline=None)
@given(mask=st.integers(2, 3).flatmap(lambda dim: arrays(bool, st.tuples(*[st.integers(1, 12)] * dim))),
       radius=st.integers(1, 7))
def test_ball_morphology_by_distance_is_scipy_s(mask, radius):
    """From radius 4 on, erosion and dilation by a ball go through the distance transform
    (a closing of radius 20 took 254 s and 18 GB on a 48^3 phantom by scipy's binary
    morphology, 0.75 s now): the same voxels as scipy's, border conventions included."""
    from dicer.segment.morphology import ball, dilate, erode

    fp = ball(radius, mask.ndim)
    assert np.array_equal(dilate(mask, radius, by_distance=True), ndi.binary_dilation(mask, structure=fp))
    assert np.array_equal(erode(mask, radius, by_distance=True),
                          ndi.binary_erosion(mask, structure=fp, border_value=1))


@settings(max_examples=150, deadline=None)
@given(mask=st.integers(2, 3).flatmap(lambda dim: arrays(bool, st.tuples(*[st.integers(1, 12)] * dim))),
       radius=st.integers(1, 7), spacing=st.lists(st.sampled_from([0.3, 0.5, 0.96, 1.0, 1.5, 2.5, 5.0]),
                                                  min_size=3, max_size=3))
def test_ellipsoid_morphology_by_distance_is_scipy_s(mask, radius, spacing):
    """On anisotropic voxels the ball keeps its size in mm: per-axis radii, an ellipsoid in
    voxels; by the distance transform (axes scaled) the same voxels as scipy's by the element."""
    from dicer.segment.morphology import axis_radii, ball, dilate, ellipsoid, erode

    radii = axis_radii(radius, spacing, mask.ndim)
    assert min(radii) >= 0 and max(radii) == radius
    fp = ellipsoid(radii)
    assert fp.shape == tuple(2 * r + 1 for r in radii) and fp[tuple(radii)]
    if len(set(radii)) == 1:
        assert np.array_equal(fp, ball(radius, mask.ndim))
    assert np.array_equal(dilate(mask, radii, by_distance=True), ndi.binary_dilation(mask, structure=fp))
    assert np.array_equal(erode(mask, radii, by_distance=True),
                          ndi.binary_erosion(mask, structure=fp, border_value=1))


def test_ranges_outside_a_shifted_ct_name_the_lost_rescale_intercept():
    import pytest as _pytest

    from dicer.errors import DicerError
    from dicer.segment.thresholds import check_ranges

    names = ["soft_tissue", "bone"]
    # a CT stored as HU + 1024 (0 .. 2089): the defaults' [-400, 0] lies below it
    with _pytest.raises(DicerError, match=r"span 0 \.\. 2089; .* a CT stored as HU \+ 1024 .* 1024 subtracted"):
        check_ranges([[-400.0, 0.0], [100.0, 1000.0]], 2, names, 0.0, 2089.0, "ct.nii.gz")
    # a scan in HU whose range simply misses: no such guess
    with _pytest.raises(DicerError) as info:
        check_ranges([[-400.0, -300.0], [100.0, 1000.0]], 2, names, -200.0, 800.0, "ct.nii.gz")
    assert "1024" not in str(info.value)
    # an MR (0 .. 993), a CT exported as 0 .. 1 or as a windowed 8-bit image: no value near air's
    # -1000 HU (the hint was given only above 1000)
    for hi in (993.0, 1.0, 255.0):
        with _pytest.raises(DicerError, match=r"move the range inside the image's values; the image has no value "
                                              r"near air's -1000 HU: if it is an MR, or a scan in other units than "
                                              r"HU, give segment.ranges \(or segment.thresholds\) in its own values, "
                                              r"or segment.method: multiotsu$"):
            check_ranges([[-400.0, 0.0], [100.0, 1000.0]], 2, names, 0.0, hi, "mr.nii.gz")


def test_a_second_peak_of_the_criterion_as_high_as_the_first_is_said():
    """The head phantom at 64 voxels (3.5 mm): the bone criterion peaks at 180 and at 956 HU,
    2.59547 against 2.59219, so cutting its field of view a little outside the head swapped them
    (bone -31 %, with no word): the segment says so, with the voxels between the two; at 96
    voxels the peaks lie further apart and nothing is said."""
    from dicer.phantoms import make_phantom
    from dicer.segment import _second_peak

    _, info = segment(make_phantom("head", 64), load_config(), "head.nii.gz")
    assert info["ambiguous_thresholds"] == {"bone": {"taken": 180.0, "other": 956.0,
                                                     "criterion": [2.595469, 2.592193], "voxels_between": 4902}}
    said = [w for w in info["warnings"] if w.startswith("two thresholds of 'bone' score alike")]
    assert len(said) == 1 and "180 (taken, J 2.59547) and 956 (J 2.59219); the 4902 voxels between them" in said[0]
    _, info = segment(make_phantom("head", 96), load_config(), "head.nii.gz")
    assert "ambiguous_thresholds" not in info
    assert not any("score alike" in w for w in info.get("warnings", []))
    # a second peak within the margin behind a dip deeper than it; a shoulder of the first
    # peak, or a peak further below, is none
    t = np.arange(9.0)
    assert _second_peak(t, np.array([0.0, 1.0, 0.9, 0.5, 0.4, 0.5, 0.998, 0.9, 0.0]), 1) == 6
    assert _second_peak(t, np.array([0.0, 1.0, 0.999, 0.998, 0.9, 0.5, 0.4, 0.3, 0.0]), 1) is None
    assert _second_peak(t, np.array([0.0, 1.0, 0.9, 0.5, 0.4, 0.5, 0.99, 0.9, 0.0]), 1) is None


def test_a_threshold_at_its_ranges_end_in_a_ct_names_large_voxels_not_other_units():
    """The head CT as 1.91 x 1.91 x 6 mm slices put the bone threshold at 100, its range's end:
    the warning told a CT in HU to set ranges 'if it is not CT in HU'; with air's -1000 in the
    image it names the voxels' partial volume instead, and without air the other units."""
    from dicer.segment import _range_warnings

    names = ["soft_tissue", "bone"]
    info = {"criterion": {n: {"thresholds": [a, a + 50.0, a + 100.0]} for n, a in zip(names, (-400.0, 100.0))},
            "thresholds": [-350.0, 100.0], "ranges": [[-400.0, 0.0], [100.0, 1000.0]],
            "classes": {"background": {"fraction": 0.4}}}
    ct = _range_warnings(info, names, -1024.0, 2500.0, (1.91, 1.91, 6.0))
    assert ct == ["the threshold of 'bone' (100) lies at an end of its search range [100, 1000]: the best split may "
                  "lie outside it; the image spans -1024 .. 2500; the image holds air's -1000, so it is most likely a "
                  "CT in HU: on voxels of 1.91 x 1.91 x 6 mm thin tissue averages with its surroundings (partial "
                  "volume) and its values move towards theirs; check segmentation.png and set segment.thresholds, "
                  "or segment.ranges"]
    other = _range_warnings(info, names, 0.0, 2500.0, (1.0, 1.0, 1.0))
    assert len(other) == 1 and other[0].endswith("if it is not CT in HU, set segment.ranges (or segment.thresholds) "
                                                 "for its values")


def test_a_table_a_voxel_below_the_head_is_dropped():
    """The head phantom at 64 voxels (3.5 mm) on a +300 HU table three voxels thick, its
    headrest taken away: a voxel below the head the table is dropped (the closing bridged the
    gap before the parts were chosen, and the table became bone: 15,594 bone voxels); touching
    the head it is one part with it and stays (documented)."""
    from dicer.phantoms import _head

    lab, hu, spacing = _head(64)
    hu = np.where(hu == 300.0, -1000.0, hu).astype(np.float32)  # the headrest gone
    y0 = int(np.flatnonzero(lab.any(axis=(0, 2)))[0])
    rng = np.random.default_rng(1)
    bone = {}
    for gap in (1, 0):
        image = hu.copy()
        image[:, y0 - gap - 3:y0 - gap, :] = 300.0
        image += rng.normal(0, 30, image.shape).astype(np.float32)
        labels, info = segment(Volume(image, spacing), config(), "table.nii.gz")
        bone[gap] = int(np.count_nonzero(labels.array == 2))
        if gap:
            assert info["removed_parts"]["soft_tissue"]["largest"] == lab.shape[0] * 3 * lab.shape[2]
            assert any(w.startswith("segment.keep dropped 1 part(s) of 'soft_tissue'") for w in info["warnings"])
    truth = int(np.count_nonzero(lab == 2))
    assert abs(bone[1] - truth) < 0.01 * truth and bone[0] > truth + lab.shape[0] * 2 * lab.shape[2]


def test_a_label_image_given_as_a_scan_is_told_how_to_give_it_as_labels():
    """A label PNG was told to be given with --labels, which reads no PNG."""
    lab = np.zeros((24, 24), np.float32)
    lab[4:20, 4:20], lab[8:12, 8:12] = 3, 7
    for source, after in (("lab.png", " after saving it as NIfTI (.nii.gz), which --labels reads"),
                          ("lab.nii.gz", "")):
        with pytest.raises(DicerError) as refused:
            segment(Volume(lab, (1.0, 1.0)), config(), source)
        assert str(refused.value).endswith("most likely a label volume: give it with --labels (dicer run --labels, "
                                           f"dicer labels){after}")


def test_multiotsu_names_far_values_that_crowd_the_histogram():
    """0.5 % of the voxels at 1e6 (above the 99.9 % clip) left the image in 2 of 256 bins:
    'holds 2 values' blamed the materials, not the outliers."""
    from dicer.segment.thresholds import histogram_values, multiotsu_thresholds

    r = np.sqrt(((np.indices((40, 40, 40)) - 19.5) ** 2).sum(0))
    a = np.select([r < 6, r < 12], [234.0, 110.0], 0.0) + np.random.default_rng(0).normal(0, 5, r.shape)
    a.ravel()[np.random.default_rng(1).choice(a.size, a.size // 200, replace=False)] = 1e6
    with pytest.raises(DicerError, match=r"holds 2 values: its values crowd into 2 of the 256 bins, the histogram "
                                         r"stretched to 998047 by 320 voxels far above the others"):
        multiotsu_thresholds(histogram_values(a), 2, ["a", "b"], "s")
    with pytest.raises(DicerError, match=r"holds 2 values\); use fewer materials"):  # two values indeed
        multiotsu_thresholds(np.r_[np.zeros(100), np.ones(100)], 2, ["a", "b"], "s")


def test_more_ranges_than_materials_says_so():
    """'(missing: none)' named no cause where one material was given against two ranges."""
    one = load_config(settings={"materials": [{"name": "a"}]})
    with pytest.raises(DicerError, match=r"segment\.ranges has 2 range\(s\) for 1 material\(s\) \(a\); give one "
                                         r"\[low, high\] per material \(1 more than the materials: the materials "
                                         r"section lists fewer than segment\.ranges\)"):
        segment(Volume(np.random.default_rng(0).normal(0, 500, (10, 10, 10)), (1.0, 1.0, 1.0)), one, "x.nii.gz")
