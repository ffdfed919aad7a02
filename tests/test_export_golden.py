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
from dicer.config import load_config
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
    "3d_o1.inp": "24d9fa98a3efe7f236c23efe49d4be86b731517c54981202a30bdedb25a3d6bd",
    "3d_o1.vtu": "372ca48e87097622ef689cd1dfdceac032e85fb1a8a59e2c92fb9ce6f0e454b4",
    "3d_o1.out": "cc7e3062190f0d5fa713e2802d061280ffcc6eeb17ab54bde8ae2630c9c71695",
    "3d_o1.neu": "cc7e3062190f0d5fa713e2802d061280ffcc6eeb17ab54bde8ae2630c9c71695",
    "3d_o1.k": "9fde3d34f93cdc932e80dd0f87d247037f27979d4072f7c1561b00c1bde1f5a6",
    "3d_o1.msh": "2f2a263c457e388e0654c0d048138096aa8c7a75f3251e5e72e4bf1f57d49e53",
    "3d_o1.exo": "2cdffacf54a16102abcdfbbb85be5faae3e0e40c3152550d37d35330bc575289",
    "3d_o1.feb": "e548586b7e478364f224088d095e8e67ed2b41a72fbd9c4ff894b2f8ea9e9af5",
    "3d_o1_mirror.inp": "df71c754f114b8fc0752e0a8451df8c234db4c059b5f80526c8ec5f17659af25",
    "3d_o1_mirror.vtu": "4748666570075d74bbb9dc9c17970fca7ab36af5816c3c19eb3df9aa35b32edb",
    "3d_o1_mirror.out": "6a979e3c6b65581669dbf03403a69e8e976f90b8fdeaeab45d96f9424b395759",
    "3d_o1_mirror.k": "d5521f01c01365bdb8030304b07b7a212d99b59352c80e255e4702d54393a3cb",
    "3d_o1_mirror.msh": "57dd0cfe5ed39d231c62a2e4978309d215ac96cc7fc717f3b25a12956ed3a79f",
    "3d_o1_mirror.exo": "3ace8f8336ee02c159aa40022da922463168ce1b618cbe9fc81637874ff85988",
    "3d_o1_mirror.feb": "47a896bf3afb89043a309e7c34b9af1d1ff92f7f72cfe38919407d3fbb04ce0c",
    "3d_o2.inp": "3ecb8b7dc0d574ac75eb000d5a6a571eb7f4e4fa8a5c3a3c34ad4458cb9d802c",
    "3d_o2.vtu": "7e9576b9a855c7889592b9acc32cfc449dcca45cabc774fe1800731d40870e98",
    "3d_o2.out": "3c87b9a09f23b2ce136fe246335ccf100b3e5c50bb635dc2fa48d0a6c9c4a725",
    "3d_o2.msh": "4bfcdd801498fd533798d20d4739d72203a77cc64a5455d287526e1b669efa69",
    "3d_o2.exo": "e8b66778a9c68b4ce8fe57ad3451998ff6b7c6831294f31b1c3b987f925684a6",
    "3d_o2.feb": "5edeeaa295a80202929c0176c61362298f53a71c7e96285f1cba13564eb1a32f",
    "2d_o1.inp": "e9e2073d8c14753aca9a6f5d5dbf6a874f6af82335d0e0acb917a453a0c420f8",
    "2d_o1.vtu": "65c857c674ccdcc50367886d5fb93171a5d2cd144963ee89d95693e51f9afc48",
    "2d_o1.out": "77bf5c4dd7fcbefaf74b598d115b50d43676cd776ac1332f5946130cd9d3aca0",
    "2d_o1.msh": "1bb08b1703c061531d8233eff2650eb2e8104541ab8b8a0c149f00c161ad5780",
    "2d_o1.exo": "9435cba6f0a0261344bb8d9f595565b4a58e9c20fdd95386b34170d85f50586e",
    "2d_o2.inp": "46568e57a0eadc8a4631cb365ce1bb865f9d76d572a17a30ac46ed1c9705543b",
    "2d_o2.vtu": "6b8340ec1ffde409dda2e3fc10405405b45e3a85411fd28c9a0d8a6a02e745cd",
    "2d_o2.out": "a00807e60cc58b9ecb44fd62502f14f06901293d888b9a4c0b744e2d86e615e1",
    "2d_o2.msh": "1e731fe075a3239c005bedd684de8ba4ad7be3bf63c18dda5e6e52283d068839",
    "2d_o2.exo": "b45bdd51abe277b6a3c07485bd07153af68e3d84e4fcf1932ff56575d44eb73a",
    "stl_3d_o1/bone.stl": "bad895442df03d22e2f6ecbf252b78c3096d16ffaf35ac443fbd010f507e3cb8",
    "stl_3d_o1/soft.stl": "3f20a762fc638166fb0e70a4f5cf1dea8c9eca2cabaaaecf8c92bf3e05fc45aa",
    "stl_3d_o1_mirror/bone.stl": "bc89d88107250a795573dc7fb58663c142ecd3226bd60b77abcc77dcf5907e65",
    "stl_3d_o1_mirror/soft.stl": "131d6de663571021a843cb11449ecf52c06197016b202e45e156b7e36e528200",
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
    mesh.points[:, :dim] += rng.uniform(-0.05, 0.05, (mesh.n_points, dim))
    return mesh


def _config(export: dict) -> dict:
    return load_config(settings={"materials": [{"name": "bone", "youngs_modulus": 17000.0, "poissons_ratio": 0.3},
                                               {"name": "soft", "youngs_modulus": 1.5, "density": 1.1e-9}],
                                 "export": export})


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
