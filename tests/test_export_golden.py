"""Golden exports: every format's bytes for fixed small meshes stay the same (SHA-256 per file).

The decks carry no date or path (their heading hashes the source mesh and the settings),
so a change of these digests is a change of the files dicer writes. After a deliberate
change of a format, print the new table with ``python tests/test_export_golden.py``.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from dicer import __version__
from dicer.config import load_config, preset_settings
from dicer.export import export_mesh
from dicer.export.stl import write_surfaces
from dicer.mesh.voxel import voxel_mesh

# direction cosines with a reflection (the z axis reversed): mirrored corner order
MIRROR = (0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0)

# case -> (dim, export settings, suffixes, direction)
CASES = {
    "3d_o1": (3, {}, (".inp", ".vtu", ".out", ".neu", ".k", ".msh", ".exo", ".feb"), None),
    "3d_o1_mirror": (3, {"element_type": "C3D8R"}, (".inp", ".vtu", ".out", ".k", ".msh", ".exo", ".feb"), MIRROR),
    "3d_o2": (3, {"order": 2, "midside_nodes": "curved", "febio_material": "neo-Hookean"},
              (".inp", ".vtu", ".out", ".msh", ".exo", ".feb"), None),
    "2d_o1": (2, {"element_type": "CPE4", "thickness": 2.5}, (".inp", ".vtu", ".out", ".msh", ".exo"), None),
    "2d_o2": (2, {"order": 2, "digits": 13}, (".inp", ".vtu", ".out", ".msh", ".exo"), None),
}

GOLDEN_VERSION = "0.1.0"
GOLDEN = {
    "3d_o1.inp": "0053abb5af1c0c6ac9ffd3f7ba974e5d3a30af0d9c0ef4f574013a45adcfc9bb",
    "3d_o1.vtu": "842dd43ea112e8a2c696ae73ca63282920d63929595491f66e7825f8ba4a86fd",
    "3d_o1.out": "36dbc27386b68783299b5a7c0071ea38d10ac0e141c0300dd0b85e3163f8be0a",
    "3d_o1.neu": "36dbc27386b68783299b5a7c0071ea38d10ac0e141c0300dd0b85e3163f8be0a",
    "3d_o1.k": "25e873f4ce37e1c94a615975ea129eb7e924aea62ede5542b1cfcf1668443187",
    "3d_o1.msh": "058eaf9b037f7c723a24572de350f328d97003c2be791d8438ab6d6367ef6f74",
    "3d_o1.exo": "68b6a9ec35e9a429d553ad466b65e7c3b151e1a64c5b7d2e64ee2adc51983801",
    "3d_o1.feb": "fcc0e9e1ab15c5f3cb59d79ebd898fe046ddfb8b90b565f89038874557b145ee",
    "3d_o1_mirror.inp": "a52f7f1e279d33c7e935ee9e66f97567ede6d478d3f62ef090d0308b05908ec1",
    "3d_o1_mirror.vtu": "49a57d197963befb80b39486fe694d32275411ca9e8f126e225459fed96140ec",
    "3d_o1_mirror.out": "042986381baaa00e9513149e8261ac9d394a6ee4414e4d419f824de5ce745f35",
    "3d_o1_mirror.k": "03bc262e5596c080a1fdae7fd7ae716b3236102001eafb7fbadd6ae263fcb612",
    "3d_o1_mirror.msh": "4acaafe8144f1f2380a9e8eaffedebffc1a1249a2f3fe4b2b23a49421e146970",
    "3d_o1_mirror.exo": "db1fc4bffe8ac8ea1e6341365ea7153417673c2bf5787bda3ecfb4ffcad8b6ff",
    "3d_o1_mirror.feb": "e70438d8620566e54c50f5b9f01caeae9c9f4d8431beaa0ab3dfdd617c4af06a",
    "3d_o2.inp": "9dd33f7b3ccef4a2b94b52feafd9dc20d772d764070e8b4998f7d34db0bda1fc",
    "3d_o2.vtu": "9c4bfb3182137ea03e862688740d06f9c7da74d1f1f524d52976b24f0cbe5443",
    "3d_o2.out": "2f28cbf2d6448682c161e1cb99573bc33951f2811093add3d57ebacac9224ef7",
    "3d_o2.msh": "027254dd9932cdc7a77b8f6a4b3585736145a3a5c47f3c0cd8580db13a429b00",
    "3d_o2.exo": "2b124171248edee264cc524514d8a84c85874c75e3a72c636b4e5325f403a0e4",
    "3d_o2.feb": "49a0588e3dcf59995d76730ae47ce15855422f21f049899d206885c0872ac733",
    "2d_o1.inp": "4911ff1a50a4668e83949f4961f8f9b435fac11ef773115b68af2b76b20a7d21",
    "2d_o1.vtu": "d2002852e14997265e8e264a77132e9b7c4f8da97597bc4a879192b6d6045a42",
    "2d_o1.out": "b52cd1de7db08c82bb6b085065b328e509278bcde85471a926e89f7c9a074193",
    "2d_o1.msh": "2c418fff18034673e462b5939b87a6a6a12af4f880162b39d4817917f1561ade",
    "2d_o1.exo": "d48e6dae44da346a87d9c0d51e1a42e2e0d0245db8316f81ad162d6044b3bfcb",
    "2d_o2.inp": "98d2b4846ae738a964f0289c2fb887563953b9280fdc815661d164ea9c8dbb8e",
    "2d_o2.vtu": "792707b29a250c5c443355148f1e604e2c99ca70d8434e6c8ec5c8a25bbd0408",
    "2d_o2.out": "607e07db84941d2e6c30da5ba071cf1689a5993487c26bd97e4d9b29d595f329",
    "2d_o2.msh": "ebc00170dffed70205de4a24856d7499bab052d95a4a6cab9653bdbde4a1e5ad",
    "2d_o2.exo": "9bc25995c1dab595cf123745e63ee59ae3364f5faed86d346d73dc8077d6add7",
    "stl_3d_o1/bone.stl": "47283d2ec36d28ddc50f9aa6a0f9f806e738a9efb2b76276e88d3109a59a4271",
    "stl_3d_o1/soft.stl": "59fc140822196f38798ce6fd210ecc97fbb80235614b04307efb656c9cad9b82",
    "stl_3d_o1_mirror/bone.stl": "1058af3e2c2f59fd0d55b6ccc9d4c33306e9c948fbb56c386a85452097ce7556",
    "stl_3d_o1_mirror/soft.stl": "23eef2d49650ad0924975b8820ddfa1679ef8928a8fef0a31435ab275905ca7f",
}


def _mesh(dim: int, direction=None):
    """A two-material mesh with moved nodes (as after smoothing), the same on every run."""
    if dim == 3:
        lab = np.zeros((3, 4, 5), np.uint8)
        lab[:, :, :2] = 1
        lab[:, 1:3, 2:] = 2
        mesh = voxel_mesh(lab, spacing=(0.5, 0.75, 1.25), origin=(-1.0, 2.0, 0.5), direction=direction)
    else:
        lab = np.zeros((5, 6), np.uint8)
        lab[:, :3] = 1
        lab[1:4, 3:] = 2
        mesh = voxel_mesh(lab, spacing=(0.5, 0.75), origin=(-1.0, 2.0))
    rng = np.random.default_rng(7)
    shift = rng.uniform(-0.05, 0.05, (mesh.n_points, dim))
    on_plane = (mesh.lattice[:, :dim] == 0) | (mesh.lattice[:, :dim] == mesh.grid_shape[:dim])
    mesh.points[:, :dim] += np.where(on_plane, 0.0, shift)  # plane nodes stay in their planes, as smoothing keeps them
    return mesh


def _config(export: dict) -> dict:
    """The settings the digests were recorded at (the headings hash them): the explicit-dynamics
    preset's under the case's."""
    preset = preset_settings("explicit-dynamics")
    return load_config(settings={"materials": [{"name": "bone", "youngs_modulus": 17000.0, "poissons_ratio": 0.3},
                                               {"name": "soft", "youngs_modulus": 1.5, "density": 1.1e-9}],
                                 "smooth": preset["smooth"], "export": preset["export"] | export})


def _digests(tmp: Path, narrow: bool = False) -> dict[str, str]:
    """``narrow``: the meshes' connectivity read-only Int32, as ``dicer export`` reads it."""
    source = tmp / "source.bin"
    source.write_bytes(b"a fixed source mesh\n")
    out = {}
    for case, (dim, export, suffixes, direction) in CASES.items():
        mesh = _mesh(dim, direction)
        if narrow:
            mesh.cells = mesh.cells.astype(np.int32)
            mesh.cells.flags.writeable = False
        config = _config(export)
        for suffix in suffixes:
            path = tmp / f"{case}{suffix}"
            export_mesh(mesh, path, config, source=source)
            out[f"{case}{suffix}"] = hashlib.sha256(path.read_bytes()).hexdigest()
    for case, direction in (("3d_o1", None), ("3d_o1_mirror", MIRROR)):
        folder = tmp / f"stl_{case}"
        folder.mkdir()
        write_surfaces(_mesh(3, direction), folder, ["bone", "soft"])
        for f in sorted(folder.iterdir()):
            out[f"stl_{case}/{f.name}"] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


@pytest.mark.skipif(__version__ != GOLDEN_VERSION, reason="the headings name another dicer version")
def test_export_bytes_unchanged(tmp_path):
    pytest.importorskip("netCDF4")
    got = _digests(tmp_path)
    assert sorted(got) == sorted(GOLDEN)
    changed = [name for name in GOLDEN if got[name] != GOLDEN[name]]
    assert not changed, f"exported files changed: {changed}"


@pytest.mark.skipif(__version__ != GOLDEN_VERSION, reason="the headings name another dicer version")
def test_export_bytes_the_same_from_int32_connectivity(tmp_path):
    """`dicer export` keeps the stage file's Int32 connectivity (read_mesh mapped): every
    format writes the same bytes as from int64."""
    pytest.importorskip("netCDF4")
    got = _digests(tmp_path, narrow=True)
    changed = [name for name in GOLDEN if got[name] != GOLDEN[name]]
    assert not changed, f"exported files differ from int32 connectivity: {changed}"


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for name, digest in _digests(Path(tmp)).items():
            print(f'    "{name}": "{digest}",')
