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
    "3d_o1.inp": "7e58c59ae5b5af6e1de81511e06b6c1a2080f4ac2f3a10942e36da066b230516",
    "3d_o1.vtu": "372ca48e87097622ef689cd1dfdceac032e85fb1a8a59e2c92fb9ce6f0e454b4",
    "3d_o1.out": "cc7e3062190f0d5fa713e2802d061280ffcc6eeb17ab54bde8ae2630c9c71695",
    "3d_o1.neu": "cc7e3062190f0d5fa713e2802d061280ffcc6eeb17ab54bde8ae2630c9c71695",
    "3d_o1.k": "8deb09af7ed4504cf0a298545520249393295f92a4e5f916556691ab537cc495",
    "3d_o1.msh": "2f2a263c457e388e0654c0d048138096aa8c7a75f3251e5e72e4bf1f57d49e53",
    "3d_o1.exo": "7fafe700e54fca9fff1965df3112cd670535993f17302fcfeb521d9a2a046e32",
    "3d_o1.feb": "5fa5cad2faab41bb5623445f77e79fa31c4322c5766c70255145a449386dffcd",
    "3d_o1_mirror.inp": "6e4ee7359900a0273f248c2f3726cd37df9fbc8ae0d297e096d9363caf5f08e7",
    "3d_o1_mirror.vtu": "4748666570075d74bbb9dc9c17970fca7ab36af5816c3c19eb3df9aa35b32edb",
    "3d_o1_mirror.out": "6a979e3c6b65581669dbf03403a69e8e976f90b8fdeaeab45d96f9424b395759",
    "3d_o1_mirror.k": "ce207fb3592153bc9c2962343d4e2751b4792817a89ab229ab158fe6b0cbf7f3",
    "3d_o1_mirror.msh": "57dd0cfe5ed39d231c62a2e4978309d215ac96cc7fc717f3b25a12956ed3a79f",
    "3d_o1_mirror.exo": "e0f94cfed8e595042f3e261aa415e09e7d5618a2aca8472bb50b2132eb067a49",
    "3d_o1_mirror.feb": "39de1d62d6d932e18e0a8668027e21dd55e5ea0e8e14206366d5b3f8c22d8520",
    "3d_o2.inp": "e0ef78c9df023a5e0b59e037de6284c68ac59718cf0833020d82dc0206927148",
    "3d_o2.vtu": "7e9576b9a855c7889592b9acc32cfc449dcca45cabc774fe1800731d40870e98",
    "3d_o2.out": "3c87b9a09f23b2ce136fe246335ccf100b3e5c50bb635dc2fa48d0a6c9c4a725",
    "3d_o2.msh": "4bfcdd801498fd533798d20d4739d72203a77cc64a5455d287526e1b669efa69",
    "3d_o2.exo": "8c2031b9dedc38c77f485a9132d759496e26f55de692de843419cbdcafcf4bd2",
    "3d_o2.feb": "9c6bb264a4dc30630b69a53702a3da35e13d8b8746b6c65603ac8c266dfa8315",
    "2d_o1.inp": "4fd5a9f6243df49eb376b37ec9f7298083f05ec7ae75f093c447c565579dfa1e",
    "2d_o1.vtu": "65c857c674ccdcc50367886d5fb93171a5d2cd144963ee89d95693e51f9afc48",
    "2d_o1.out": "77bf5c4dd7fcbefaf74b598d115b50d43676cd776ac1332f5946130cd9d3aca0",
    "2d_o1.msh": "1bb08b1703c061531d8233eff2650eb2e8104541ab8b8a0c149f00c161ad5780",
    "2d_o1.exo": "d755055fc978b245694ae557cc597d506e51e4295ae96dfb3b5a29dd37152570",
    "2d_o2.inp": "48092c702ad4c782e8368f09bab071a8f4d311593773c92b16bd66e85f3273c1",
    "2d_o2.vtu": "6b8340ec1ffde409dda2e3fc10405405b45e3a85411fd28c9a0d8a6a02e745cd",
    "2d_o2.out": "a00807e60cc58b9ecb44fd62502f14f06901293d888b9a4c0b744e2d86e615e1",
    "2d_o2.msh": "1e731fe075a3239c005bedd684de8ba4ad7be3bf63c18dda5e6e52283d068839",
    "2d_o2.exo": "1eee4defc2a9ac690b883266b1bee503d90a962fadbbaf68974c9aae358ecb76",
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
