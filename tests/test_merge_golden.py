"""Plane merging gives byte-identical meshes and reports on fixed volumes.

Each case merges a fixed label volume with fixed settings and compares SHA-256 digests of
the merged mesh's arrays (points, cells, material, lattice, spacing, origin, grid shape,
point and cell data) and of its report (without the timings) with values recorded from
the code. A change of any digest means the merge itself changed; a change of the input
digest means the volume changed (the connectivity stage or a phantom), not the merge.

Run this file as a script to print the current values, e.g. to record them again after
a deliberate change of the merge rules.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from scipy import ndimage

from dicer.connectivity import fix_connectivity
from dicer.mesh.merge import merge_planes
from dicer.mesh.voxel import voxel_mesh
from dicer.phantoms import phantom_labels


def _ball(n: int = 24) -> np.ndarray:
    """Two materials: a ball of material 1 around a core of material 2."""
    x = np.indices((n, n, n)) - (n - 1) / 2
    r = np.sqrt((x ** 2).sum(axis=0))
    labels = np.zeros((n, n, n), np.uint8)
    labels[r < 0.45 * n] = 1
    labels[r < 0.25 * n] = 2
    return labels


def _smooth_noise(seed: int, shape=(22, 20, 18), sigma: float = 2.5) -> np.ndarray:
    """Background and two materials from smoothed noise of a fixed seed, made well connected."""
    f = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(shape), sigma)
    labels = np.digitize(f, np.quantile(f, [0.35, 0.75])).astype(np.uint8)
    return fix_connectivity(labels)[0]


def _layered(seed: int) -> np.ndarray:
    """Three noise slices repeated 2, 1 and 3 times and stacked along axis ``seed % 3``:
    chamfers of two axes meet often in such volumes."""
    a = np.random.default_rng(seed).integers(0, 3, size=(14, 12, 3)).astype(np.uint8)
    return fix_connectivity(np.moveaxis(a.repeat([2, 1, 3], axis=2), 2, seed % 3))[0]


def _noise_2d(seed: int, shape=(40, 36), sigma: float = 0.0) -> np.ndarray:
    """2D background and two materials (smoothed when ``sigma`` > 0), made well connected."""
    f = np.random.default_rng(seed).standard_normal(shape)
    if sigma:
        f = ndimage.gaussian_filter(f, sigma)
    labels = np.digitize(f, np.quantile(f, [1 / 3, 2 / 3])).astype(np.uint8)
    return fix_connectivity(labels)[0]


# small volumes of tests/test_merge.py in which chamfers of two axes meet (shared corners)
_TWO_AXES_3D = np.array([[2, 2, 2, 2, 2], [1, 2, 2, 2, 1], [2, 2, 0, 1, 1], [0, 2, 2, 2, 2], [0, 1, 1, 2, 0]],
                        np.uint8)[:, :, None]
_JOINED_2D = np.array([[1, 2, 1], [1, 2, 0], [1, 1, 1], [2, 1, 0], [2, 2, 2]], np.uint8)
_JOINED_3D = np.array([[[2, 1], [2, 0], [2, 2]], [[2, 1], [2, 0], [2, 2]], [[2, 0], [2, 0], [0, 0]],
                       [[2, 2], [2, 0], [2, 0]]], np.uint8)

_VOLUMES = {
    "ball": _ball,
    "noise5": lambda: _smooth_noise(5),
    "noise1": lambda: _smooth_noise(1),
    "layered1": lambda: _layered(1),
    "noise2d": lambda: _noise_2d(2),
    "smooth2d": lambda: _noise_2d(3, sigma=1.5),
    "two_axes": lambda: _TWO_AXES_3D,
    "joined2d": lambda: _JOINED_2D,
    "joined3d": lambda: _JOINED_3D,
    "long_bone": lambda: phantom_labels("long_bone", 40).array,
}

# name: (volume, options of merge_planes; "data": the mesh gets point and cell data,
# non-unit spacing and an origin)
CASES = {
    "ball": ("ball", {"passes": (1, 1, 1)}),
    "ball_data": ("ball", {"passes": (1, 2, 1), "data": True}),
    "ball_plane": ("ball", {"passes": (2, 1, 1), "granularity": "plane"}),
    "ball_thin": ("ball", {"passes": (1, 1, 2), "min_thickness": 6.0}),
    "noise5": ("noise5", {"passes": (1, 1, 1)}),
    "noise5_3": ("noise5", {"passes": (2, 2, 2), "axes": (2, 0, 1)}),
    "noise1_fixed_rims": ("noise1", {"passes": (1, 2, 1), "rim_moves": False}),
    "noise1_thin_flat": ("noise1", {"passes": (2, 1, 1), "min_thickness": 2.5, "min_scaled_jacobian": 0.0}),
    "layered1": ("layered1", {"passes": (2, 2, 2)}),
    "layered1_no_jacobian": ("layered1", {"passes": (1, 1, 1), "min_scaled_jacobian": -1.0}),
    "noise2d": ("noise2d", {"passes": (2, 2)}),
    "smooth2d_plane": ("smooth2d", {"passes": (1, 3), "granularity": "plane", "axes": (1, 0, 2)}),
    "smooth2d_fixed_rims": ("smooth2d", {"passes": (2, 1), "rim_moves": False}),
    "two_axes": ("two_axes", {"passes": (1, 1, 1)}),
    "two_axes_fixed_rims": ("two_axes", {"passes": (1, 1, 1), "rim_moves": False}),
    "joined2d": ("joined2d", {"passes": (1, 2)}),
    "joined3d": ("joined3d", {"passes": (1, 1, 1)}),
    "long_bone": ("long_bone", {"passes": (2, 2, 2)}),
    "long_bone_thin": ("long_bone", {"passes": (1, 1, 1), "min_thickness": 4.0}),
    # at the default floor 0.3: the noise volume merges as at 0.2; the anisotropic ball to as many
    # elements (3,043), its rim nodes moved otherwise: lowest scaled Jacobian 0.385, at 0.2 0.292
    "noise5_defaults": ("noise5", {"passes": (1, 1, 1)}),
    "ball_data_defaults": ("ball", {"passes": (1, 2, 1), "data": True}),
}

# name: (input labels, merged mesh, report) SHA-256, first 16 hex digits
# (13 cases recorded again on 6 December 2026, when the checks began to count mirror images at
# the image's bounding planes: the ball and long-bone cases, off the planes, kept theirs)
GOLDEN = {
    "ball": ('6b31d01e77909ca2', '4f6ef75e300d34b6', '98182ba4c7c3e9d9'),
    "ball_data": ('6b31d01e77909ca2', '66a752cd5abbe55e', '0f73e0c04cd09511'),
    "ball_plane": ('6b31d01e77909ca2', '41222d9531427070', 'bc8a3e7e9f63b33c'),
    "ball_thin": ('6b31d01e77909ca2', 'd640d10fad944d46', 'b9e3370252acdc74'),
    "noise5": ('acb28eb5de7a8aac', '31e81da1265575fd', 'e17cd1cdc695ac8a'),
    "noise5_3": ('acb28eb5de7a8aac', '37a1b303dfe949b8', '4375e0e61eb03d28'),
    "noise1_fixed_rims": ('3395c052c03865be', 'aa5b5d8a2c061ef8', '503bdd84905a90c8'),
    "noise1_thin_flat": ('3395c052c03865be', '484fbc7e0848802f', '3a6e486b524d4f77'),
    "layered1": ('988d5ea2d3db0904', 'ee86c4e04bc355ce', 'f7d72b4f2a3be3cd'),
    "layered1_no_jacobian": ('988d5ea2d3db0904', 'ee86c4e04bc355ce', 'f63d8aabb1236cb8'),
    "noise2d": ('8aa86809aae50249', '93ff285da564f94b', 'd40950fd045a0343'),
    "smooth2d_plane": ('5ce974127b2b7537', '81d54d12972d3e61', '19a7454b031d0749'),
    "smooth2d_fixed_rims": ('5ce974127b2b7537', 'aa101019243ecb78', 'f436c46a9fae1c24'),
    "two_axes": ('fde31920e9ab65e5', '57a423e4a50b6e19', '61a4d711f252a9a5'),
    "two_axes_fixed_rims": ('fde31920e9ab65e5', '57a423e4a50b6e19', '2459a0845697d778'),
    "joined2d": ('5e190cadccdf7af0', 'dff6b0afd58f6b30', 'c5874e00cdb2045a'),
    "joined3d": ('f635632148d42633', 'cf20e348b1391a7e', '3f0e4419c60a54c6'),
    "long_bone": ('8068aa6bb3daa3df', 'd6f097e1604cb5a7', 'a5a62951938d9c01'),
    "long_bone_thin": ('8068aa6bb3daa3df', 'e76f4b467beb03bb', '6b422cc7a6ce567d'),
    "noise5_defaults": ('acb28eb5de7a8aac', '31e81da1265575fd', '266012d2246a6f2d'),
    "ball_data_defaults": ('6b31d01e77909ca2', '56e382ddc88bb58d', '7da3c2a94a137089'),
}


def _digest(parts) -> str:
    h = hashlib.sha256()
    for name, a in parts:
        a = np.ascontiguousarray(a)
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _mesh_digest(mesh) -> str:
    # the node numbers, whatever their index type (int32 while they fit, int64 when recorded)
    parts = [("points", mesh.points), ("cells", mesh.cells.astype(np.int64)), ("material", mesh.material),
             ("lattice", mesh.lattice), ("spacing", mesh.spacing), ("origin", mesh.origin),
             ("grid_shape", mesh.grid_shape)]
    parts += [(f"point_data.{k}", mesh.point_data[k]) for k in sorted(mesh.point_data)]
    parts += [(f"cell_data.{k}", mesh.cell_data[k]) for k in sorted(mesh.cell_data)]
    return _digest(parts)


def _without_seconds(value):
    if isinstance(value, dict):
        return {k: _without_seconds(v) for k, v in value.items() if k != "seconds"}
    if isinstance(value, list):
        return [_without_seconds(v) for v in value]
    return value


def _report_digest(report: dict) -> str:
    text = json.dumps(_without_seconds(report), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


RECORDED_FLOOR = 0.2
"""merge.min_scaled_jacobian of the cases but those named ``*_defaults``: the default when they
were recorded (0.3 since 5 December 2026), so each keeps testing its own path."""


def _run(name: str) -> tuple[str, str, str]:
    volume, options = CASES[name]
    options = dict(options) if name.endswith("_defaults") else {"min_scaled_jacobian": RECORDED_FLOOR, **options}
    labels = _VOLUMES[volume]()
    if options.pop("data", False):
        mesh = voxel_mesh(labels, spacing=(0.5, 0.7, 1.2), origin=(-3.0, 2.0, 10.5))
        rng = np.random.default_rng(7)
        mesh.point_data["temperature"] = rng.standard_normal(mesh.n_points)
        mesh.point_data["index"] = np.arange(mesh.n_points, dtype=np.int64)
        mesh.cell_data["density"] = rng.standard_normal((mesh.n_cells, 2)).astype(np.float32)
        mesh.cell_data["voxel"] = np.arange(mesh.n_cells, dtype=np.int32)
    else:
        mesh = voxel_mesh(labels)
    out, report = merge_planes(mesh, **options)
    return _digest([("labels", labels)]), _mesh_digest(out), _report_digest(report)


@pytest.mark.parametrize("name", sorted(CASES))
def test_merge_is_byte_identical_to_the_recorded_output(name):
    labels, mesh, report = _run(name)
    expected = GOLDEN[name]
    assert labels == expected[0], "the input volume changed (connectivity stage or phantom), not the merge"
    assert mesh == expected[1], "the merged mesh changed"
    assert report == expected[2], "the merge report changed"


@pytest.mark.parametrize("name", sorted(CASES))
def test_merge_in_small_pieces_on_threads_gives_the_recorded_output(name, monkeypatch):
    """Large meshes are worked in pieces of rows, several at a time on threads: pieces of 64
    values here make every piece loop of these small meshes run that way."""
    import dicer.mesh.merge as merge

    monkeypatch.setattr(merge, "CHUNK", 64)
    calls = []
    ordered_map = merge.ordered_map
    monkeypatch.setattr(merge, "ordered_map", lambda fn, items: calls.append(1) or ordered_map(fn, items))
    _, mesh, report = _run(name)
    assert len(calls) >= 3, "the piece loops did not run in pieces"
    assert (mesh, report) == GOLDEN[name][1:]


if __name__ == "__main__":  # print the table of recorded values
    for case in CASES:
        print(f'    "{case}": {_run(case)!r},')
