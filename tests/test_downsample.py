"""Downsampling: the thin-class vote, factors, voxel sizes, morphology again, errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dicer.config import load_config
from dicer.downsample import downsample, reduction_factor, vote
from dicer.errors import DicerError
from dicer.image import Volume


def config(segment=None, **ds):
    return load_config(settings={"downsample": ds, "segment": segment or {}})


def test_two_voxel_plate_survives_factor_4():
    lab = np.zeros((32, 32, 32), np.uint8)
    lab[4:28, 4:28, 4:28] = 1
    lab[4:28, 4:28, 13:15] = 2            # a 2-voxel bone plate inside soft tissue (z = 13, 14)
    out, info = downsample(Volume(lab, (0.5, 0.5, 0.5), (1.0, 2.0, 3.0)), config(factor=4, morphology=False),
                           "plate.nii")
    a = out.array
    assert a.shape == (8, 8, 8) and out.spacing == (2.0, 2.0, 2.0) and out.origin == (1.0, 2.0, 3.0)
    assert (a[1:7, 1:7, 3] == 2).all()    # the plate fills half of block z = 3
    assert np.count_nonzero(a == 2) == 36
    assert np.count_nonzero(a == 1) == 6 * 6 * 6 - 36
    # a plain majority vote loses the plate
    blocks = (lab == 2).reshape(8, 4, 8, 4, 8, 4).sum(axis=(1, 3, 5))
    assert (blocks > 32).sum() == 0
    assert info["factor"] == [4, 4, 4] and info["shape_before"] == [32, 32, 32] and info["shape_after"] == [8, 8, 8]
    assert info["voxels_before"]["bone"] == 24 * 24 * 2 and info["voxels_after"]["bone"] == 36


def test_thin_plate_attached_to_thick_bone_survives_morphology_after_reduction():
    lab = np.zeros((32, 32, 32), np.uint8)
    lab[4:28, 4:28, 4:28] = 1
    lab[4:28, 4:28, 13:15] = 2            # the 2-voxel plate ...
    lab[4:16, 4:16, 4:16] = 2             # ... grown out of a thick bone block
    out, _ = downsample(Volume(lab, (0.5, 0.5, 0.5)), config(factor=4), "plate.nii")
    a = out.array
    assert (a[1:7, 1:7, 3] == 2).all()
    assert (a[1:4, 1:4, 1:4] == 2).all()
    # vote: 36 + 27 - 9 bone voxels; the closing adds the 4 in the re-entrant edge where plate meets block
    assert np.count_nonzero(a == 2) == 36 + 27 - 9 + 4
    assert a[4, 3, 2] == 2 and a[5, 3, 2] == 1
    # alone, the one-voxel coarse plate is thinner than the opening and goes
    lab[4:16, 4:16, 4:16] = 1
    out, _ = downsample(Volume(lab, (0.5, 0.5, 0.5)), config(factor=4), "plate.nii")
    assert np.count_nonzero(out.array == 2) == 0


def test_factor_1_is_identity():
    lab = np.random.default_rng(0).integers(0, 3, (9, 8, 7)).astype(np.uint8)
    vol = Volume(lab, (1, 1, 2))
    out, info = downsample(vol, config(factor=1), "x")
    assert out is vol
    assert info["factor"] == [1, 1, 1] and info["voxels_after"] == info["voxels_before"]


@pytest.mark.parametrize("spacing, target, expected", [
    ((0.957, 0.957, 1.5), 2.0, (2, 2, 1)),
    ((0.957, 0.957, 1.5), 3.0, (3, 3, 2)),
    ((0.957, 0.957, 1.5), [1.0, 4.0, 0.5], (1, 4, 1)),
    ((1.0, 1.0), 2.5, (3, 3)),
    ((0.3, 0.3, 0.3), 0.1, (1, 1, 1)),
])
def test_voxel_size_arithmetic(spacing, target, expected):
    assert reduction_factor(spacing, factor=1, voxel_size=target) == expected


def test_voxel_size_wins_over_factor_and_padding():
    lab = np.ones((10, 9, 5), np.uint8)
    out, info = downsample(Volume(lab, (1.0, 1.0, 1.5)), config(voxel_size=3.0, factor=7), "x.nii")
    assert info["factor"] == [3, 3, 2]
    assert out.array.shape == (4, 3, 3)
    assert out.spacing == (3.0, 3.0, 3.0)
    # the padded last block along x holds 1 of 3 layers: 1/3 >= 0.25 keeps it
    assert (out.array == 1).all()


@pytest.mark.parametrize("target, said", [(0.25, True), ([0.7, 0.7, 2.0], True), ([1.0, 1.0, 2.0], False),
                                          ([1.2, 1.2, 2.0], False), (1.0, True)])
def test_a_voxel_size_the_whole_factors_miss_is_said(caplog, target, said):
    """The factor is a whole number of voxels per axis: 0.7 mm of 0.5 mm voxels gives 0.5 mm,
    0.25 mm gives 0.5 mm (no refining), 1 mm of the 2 mm slices 2 mm; 1.2 mm gives 1.0 mm, within a
    fifth, unsaid."""
    lab = np.ones((8, 8, 4), np.uint8)
    _, info = downsample(Volume(lab, (0.5, 0.5, 2.0)), config(voxel_size=target), "x.nii")
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("downsample: voxel_size")]
    assert len(warned) == int(said)
    if said:
        got = " x ".join(f"{f * s:g}" for f, s in zip(info["factor"], (0.5, 0.5, 2.0)))
        assert f"gives voxels of {got} mm" in warned[0]


def test_a_factor_beside_a_voxel_size_is_said_to_be_unused(tmp_path, caplog):
    from dicer.cli import main

    np.save(tmp_path / "l.npy", np.ones((6, 6, 6), np.uint8))
    for sets, said in ((["downsample.factor=3", "downsample.voxel_size=2"], 1), (["downsample.voxel_size=2"], 0)):
        caplog.clear()
        args = ["downsample", str(tmp_path / "l.npy"), "-o", str(tmp_path / "d.nii.gz"), "-q"]
        assert main(args + [a for s in sets for a in ("--set", s)]) == 0
        warned = [r for r in caplog.records if "replaces downsample.factor" in r.getMessage()]
        assert len(warned) == said


def test_priority_and_fallback():
    lab = np.zeros((4, 4), np.uint8)
    lab[:, :2] = 1
    lab[:, 2:] = 2
    assert vote(lab, (4, 4), 2, 0.25).tolist() == [[2]]
    assert vote(lab, (4, 4), 2, 0.25, priority=[1, 2]).tolist() == [[1]]
    # no class reaches 0.6: plurality wins, ties go to the priority order, background last
    lab2 = np.array([[0, 0, 1, 2]] * 4, np.uint8)
    assert vote(lab2, (4, 4), 2, 0.6).tolist() == [[0]]
    lab3 = np.array([[0, 1, 1, 2]] * 4, np.uint8)
    assert vote(lab3, (4, 4), 2, 0.6).tolist() == [[1]]
    lab4 = np.array([[0, 0, 1, 1]] * 4, np.uint8)
    assert vote(lab4, (4, 4), 2, 0.6).tolist() == [[1]]


def test_priority_from_config():
    lab = np.zeros((8, 8), np.uint8)
    lab[:, :4] = 1
    lab[:, 4:] = 2
    lab = np.tile(lab, (2, 2))
    cfg = config(segment={"priority": ["soft_tissue"]}, factor=[8, 8], morphology=False)
    out, _ = downsample(Volume(lab, (1, 1)), cfg, "x")
    assert (out.array == 1).all()


@settings(max_examples=40, deadline=None)
@given(arrays(np.uint8, st.tuples(st.integers(1, 9), st.integers(1, 9)), elements=st.integers(0, 2)),
       st.integers(1, 4), st.integers(1, 4), st.sampled_from([0.0, 0.25, 0.5, 1.0]))
def test_vote_matches_blockwise_rule(lab, fx, fy, frac):
    out = vote(lab, (fx, fy), 2, frac)
    nx, ny = -(-lab.shape[0] // fx), -(-lab.shape[1] // fy)
    assert out.shape == (nx, ny)
    pad = np.zeros((nx * fx, ny * fy), np.uint8)
    pad[:lab.shape[0], :lab.shape[1]] = lab
    for i in range(nx):
        for j in range(ny):
            blk = pad[i * fx:(i + 1) * fx, j * fy:(j + 1) * fy]
            counts = np.bincount(blk.ravel(), minlength=3)
            cands = [c for c in (2, 1) if counts[c] > 0 and counts[c] >= frac * blk.size]
            expected = cands[0] if cands else max([2, 1, 0], key=lambda c: (counts[c], -[2, 1, 0].index(c)))
            assert out[i, j] == expected


def test_morphology_runs_again_after_reduction():
    lab = np.zeros((24, 24, 24), np.uint8)
    lab[:, :, :12] = 1
    lab[20:22, 20:22, 20:22] = 1          # a speck that becomes one isolated coarse voxel
    vol = Volume(lab, (1, 1, 1))
    out, _ = downsample(vol, config(factor=2), "x")
    assert out.array[10, 10, 10] == 0 and np.count_nonzero(out.array) == 12 * 12 * 6
    out, _ = downsample(vol, config(factor=2, morphology=False), "x")
    assert out.array[10, 10, 10] == 1


def test_2d_and_anisotropic_factor():
    lab = np.zeros((12, 10), np.uint8)
    lab[2:10, 2:8] = 1
    out, info = downsample(Volume(lab, (0.5, 1.0)), config(factor=[2, 1], morphology=False), "s.png")
    assert out.array.shape == (6, 10) and out.spacing == (1.0, 1.0)
    assert np.array_equal(out.array, lab[::2])


@pytest.mark.parametrize("ds, arr, words", [
    ({"factor": [2, 2]}, np.zeros((4, 4, 4), np.uint8), ["lab.nii", "downsample.factor", "3D"]),
    ({"voxel_size": [1.0, 2.0, 3.0]}, np.zeros((4, 4), np.uint8), ["lab.nii", "downsample.voxel_size", "2D"]),
    ({"factor": 2}, np.full((4, 4, 4), 5, np.uint8), ["lab.nii", "5 .. 5", "2 material"]),
    ({"factor": 2}, np.full((4, 4, 4), 0.5, np.float32), ["lab.nii", "non-integer"]),
])
def test_errors(ds, arr, words):
    with pytest.raises(DicerError) as err:
        downsample(Volume(arr, (1.0,) * arr.ndim), config(**ds), "lab.nii")
    for w in words:
        assert w in str(err.value)


def test_volume_change_reported_and_a_lost_plate_warned_of(tmp_path, caplog):
    """An isolated 3-voxel bone plate does not survive factor 2 with the opening after the vote:
    info gives every material's volume change, and the command warns of it."""
    from dicer.cli import main
    from dicer.io.images import write_image

    lab = np.zeros((32, 32, 32), np.uint8)
    lab[2:30, 2:30, 2:30] = 1
    lab[6:26, 6:26, 14:17] = 2  # 3 voxels thick
    _, info = downsample(Volume(lab, (1.0, 1.0, 1.0)), config(factor=2), "plate.nii")
    assert info["volume_change_percent"]["bone"] == -100.0
    assert abs(info["volume_change_percent"]["soft_tissue"]) < 25
    _, info = downsample(Volume(lab, (1.0, 1.0, 1.0)), config(factor=2, morphology=False), "plate.nii")
    assert info["volume_change_percent"]["bone"] == pytest.approx(100 * (10 * 10 * 2 * 8 - 1200) / 1200, abs=0.01)  # 2 coarse layers
    write_image(Volume(lab, (1.0, 1.0, 1.0)), tmp_path / "l.nii.gz")
    assert main(["downsample", str(tmp_path / "l.nii.gz"), "-o", str(tmp_path / "d.nii.gz"),
                 "--set", "downsample.factor=2", "-q"]) == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and '{"bone": "-100.0 %"}' in warned[0] and "downsample.morphology=false" in warned[0]
    assert "first in segment.priority" in warned[0] and "are removed" in warned[0]
    # the plurality vote without morphology (a label volume's defaults): the warning names them, and
    # no longer advises the setting already in force
    caplog.clear()
    assert main(["downsample", str(tmp_path / "l.nii.gz"), "-o", str(tmp_path / "d.nii.gz"), "--set",
                 "downsample.factor=4", "--set", "downsample.vote=plurality", "--set", "downsample.morphology=false",
                 "-q"]) == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "the most frequent class takes a block" in warned[0], warned
    assert "keeps only the blocks it fills" in warned[0] and "morphology=false" not in warned[0]


def test_a_grid_beyond_the_image_is_reported_and_growth_into_it_warned_of(tmp_path, caplog):
    """24 voxels at factor 5: the fifth coarse layer covers 4 voxels and 1 mm beyond the image.
    Material at the far face grows into it (a cut model: +13 % for a full cube); background
    there does not, and a factor that divides the shape reaches nowhere."""
    from dicer.cli import main
    from dicer.io.images import write_image

    full = np.ones((24, 24, 24), np.uint8)
    out, info = downsample(Volume(full, (1.0, 1.0, 1.0)), config(factor=5), "cube.nii")
    assert info["beyond_image_mm"] == [1.0, 1.0, 1.0] and info["material_beyond_image"] == [True] * 3
    assert out.array.sum() * 125 == 25 ** 3  # the model is a 25 mm cube
    inner = np.zeros((24, 24, 24), np.uint8)
    inner[4:18, 4:18, 4:18] = 1
    _, info = downsample(Volume(inner, (1.0, 1.0, 1.0)), config(factor=5), "ball.nii")
    assert info["material_beyond_image"] == [False] * 3
    _, info = downsample(Volume(full, (1.0, 1.0, 0.5)), config(factor=[4, 6, 3]), "cube.nii")
    assert info["beyond_image_mm"] == [0.0, 0.0, 0.0] and info["material_beyond_image"] == [False] * 3
    write_image(Volume(full, (1.0, 1.0, 1.0)), tmp_path / "cube.nii.gz")
    caplog.set_level("WARNING", logger="dicer")
    assert main(["downsample", str(tmp_path / "cube.nii.gz"), "-o", str(tmp_path / "d.nii.gz"),
                 "--set", "downsample.factor=[5, 4, 5]", "-q"]) == 0
    warned = [r.getMessage() for r in caplog.records if "beyond the image" in r.getMessage()]
    assert len(warned) == 1
    assert "x by 1 mm (24 voxels, factor 5), z by 1 mm" in warned[0] and "y by" not in warned[0]
    assert "(x: 2, 3, 4, 6; z: 2, 3, 4, 6)" in warned[0]
    caplog.clear()
    write_image(Volume(inner, (1.0, 1.0, 1.0)), tmp_path / "inner.nii.gz")
    assert main(["downsample", str(tmp_path / "inner.nii.gz"), "-o", str(tmp_path / "e.nii.gz"),
                 "--set", "downsample.factor=5", "-q"]) == 0
    assert not [r for r in caplog.records if "beyond the image" in r.getMessage()]


def _block_atlas() -> np.ndarray:
    """An atlas of 40 parcels (values 2, 5, 8, ...) made of aligned 4 x 4 x 4 blocks, 6^3 blocks."""
    i, j, k = np.indices((6, 6, 6))
    index = (i * 7 + j * 13 + k * 29) % 40 * 3 + 2
    return np.kron(index, np.ones((4, 4, 4), int)).astype(np.uint16)


@settings(max_examples=80, deadline=None)
@given(st.integers(1, 300).flatmap(lambda k: st.tuples(
           st.just(k), arrays(np.uint16, st.tuples(*[st.integers(1, 7)] * 3), elements=st.integers(0, k)),
           st.permutations(list(range(1, k + 1))))),
       st.tuples(*[st.integers(1, 3)] * 3), st.sampled_from([0.0, 0.2, 0.5, 1.0]), st.booleans())
def test_vote_of_many_classes_matches_blockwise_rule(drawn, factor, frac, plurality):
    # up to 300 classes in any priority: each coarse voxel follows the rule on its block. By
    # priority: the first class filling frac; by plurality: when the classes together fill
    # frac, the most frequent, ties to the first in the priority on even blocks (i + j + k)
    # and to the last on odd ones. Else the block's most frequent value.
    k, lab, prio = drawn
    out = vote(lab, factor, k, frac, priority=prio, plurality=plurality)
    order = prio + [0]
    pad = np.zeros([-(-n // f) * f for n, f in zip(lab.shape, factor)], np.uint16)
    pad[tuple(slice(0, n) for n in lab.shape)] = lab
    for idx in np.ndindex(*out.shape):
        blk = pad[tuple(slice(i * f, (i + 1) * f) for i, f in zip(idx, factor))]
        counts = np.bincount(blk.ravel(), minlength=k + 1)
        present = [c for c in prio if counts[c] > 0]
        if plurality:
            first = sum(idx) % 2 == 0
            tie = (lambda c: -prio.index(c)) if first else prio.index
            cands = [max(present, key=lambda c: (counts[c], tie(c)))] if present and \
                counts[1:].sum() >= frac * blk.size else []
        else:
            cands = [c for c in present if counts[c] >= frac * blk.size]
        expected = cands[0] if cands else max(order, key=lambda c: (counts[c], -order.index(c)))
        assert out[idx] == expected


def test_renumbering_an_atlas_does_not_move_volume_between_its_parcels():
    # 300 random parcels at factor 2: the priority vote gave the high numbers the low ones' volume
    rng = np.random.default_rng(5)
    n = 24
    seeds = rng.uniform(0, n, (300, 3))
    grid = np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), -1).reshape(-1, 3)
    nearest = np.argmin(((grid[:, None, :] - seeds[None]) ** 2).sum(-1), axis=1).reshape(n, n, n)
    atlas = (nearest + 1).astype(np.uint16)
    ratios = {}
    for name, lab in (("as numbered", atlas), ("reversed", 301 - atlas)):
        coarse = vote(lab, (2, 2, 2), 300, 0.25, plurality=True)
        fine = np.bincount(lab.ravel(), minlength=301)
        kept = np.bincount(coarse.ravel(), minlength=301) * 8
        parcel = np.arange(1, 301) if name == "as numbered" else 301 - np.arange(1, 301)
        ratios[name] = kept[parcel] / fine[parcel]  # by parcel, whatever its number
    for r in ratios.values():
        assert 0.9 < r[:75].mean() < 1.1 and 0.9 < r[-75:].mean() < 1.1  # no end of the numbering favoured
    priority = vote(atlas, (2, 2, 2), 300, 0.25)
    low = np.bincount(priority.ravel(), minlength=301)[1:76] * 8 / np.bincount(atlas.ravel(), minlength=301)[1:76]
    assert low.mean() < 0.8  # what the priority vote does to the low numbers


def test_label_volumes_made_elsewhere_are_downsampled_without_the_scans_morphology(tmp_path, caplog):
    """Factor 2 of an atlas of aligned 4-voxel parcels: every coarse voxel lies in one parcel.
    The segment section's opening and closing (for a scan's few classes) removed most parcels
    and regrew their neighbours into them; for 'dicer run --labels' null now means off, and
    the materials lost are named in full."""
    from dicer.cli import main
    from dicer.config import for_label_volume, load_config
    from dicer.io.images import read_labels, write_image

    assert load_config()["downsample"]["morphology"] is None
    assert for_label_volume(load_config())["downsample"]["morphology"] is False
    assert for_label_volume(load_config())["downsample"]["vote"] == "plurality"
    assert for_label_volume(load_config(sets=["downsample.vote=priority"]))["downsample"]["vote"] == "priority"
    assert for_label_volume(load_config(sets=["downsample.morphology=true"]))["downsample"]["morphology"] is True
    atlas = _block_atlas()
    write_image(Volume(atlas, (1.0, 1.0, 1.0)), tmp_path / "atlas.nii.gz")
    assert main(["run", "--labels", str(tmp_path / "atlas.nii.gz"), "-o", str(tmp_path / "out"), "-q",
                 "--set", "downsample.factor=2"]) == 0
    fine = read_labels(tmp_path / "out" / "labels.nii.gz").array
    coarse = read_labels(tmp_path / "out" / "labels_ds.nii.gz").array
    assert np.array_equal(coarse, fine[::2, ::2, ::2]) and np.unique(coarse).size == 40
    # 'dicer downsample' given the materials file of a mapped label volume: as the run does
    assert main(["downsample", str(tmp_path / "out" / "labels.nii.gz"), "-o", str(tmp_path / "same.nii.gz"),
                 "--materials", str(tmp_path / "out" / "materials.json"), "--set", "downsample.factor=2",
                 "-q"]) == 0
    assert (tmp_path / "same.nii.gz").read_bytes() == (tmp_path / "out" / "labels_ds.nii.gz").read_bytes()
    caplog.clear()
    # with the scan's morphology: most parcels go, and each is named
    assert main(["downsample", str(tmp_path / "out" / "labels.nii.gz"), "-o", str(tmp_path / "d.nii.gz"),
                 "--materials", str(tmp_path / "out" / "materials.json"), "--set", "downsample.factor=2",
                 "--set", "downsample.morphology=true", "--set", "downsample.vote=priority", "-q"]) == 0
    left = np.unique(read_labels(tmp_path / "d.nii.gz").array)
    lost = [r.getMessage() for r in caplog.records if "have no voxels left" in r.getMessage()]
    assert left.size == 23 and len(lost) == 1  # measured: 17 of 40 parcels lost
    assert lost[0].startswith("downsample: 17 material(s) have no voxels left")
