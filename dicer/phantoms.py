"""Synthetic CT-like phantoms in Hounsfield units, with their true label volumes.

Labels follow the default configuration: 0 background, 1 soft tissue, 2 bone, so the
default manual thresholds (-140 HU soft tissue, 226 HU bone) recover them from a
noise-free phantom exactly. Every builder is vectorised: 1D coordinate arrays are
broadcast against each other instead of building full ``mgrid`` arrays, so the 256^3
shell needs a few bytes per voxel.

Voxel centres sit at ``(i + 0.5) * spacing`` mm from the volume corner (origin 0).
"""

from __future__ import annotations

import math

import numpy as np

from dicer.errors import DicerError
from dicer.image import Volume

AIR, SOFT, BONE = 0, 1, 2

#: phantom name -> one-line description
PHANTOMS = {
    "head": "air around an ellipsoidal head: scalp, a skull of varying thickness (thin temporal bone of "
            "2-3 voxels), brain, a frontal air sinus, and a separate thin headrest arc behind the head "
            "(not part of the labels)",
    "long_bone": "a bowed long bone (cortical tube with marrow, wider thin-walled ends) in a cylinder of "
                 "muscle cut by both end planes",
    "shell": "two-material ball: bone inside radius 0.30 n, soft tissue out to 0.45 n, 1 mm voxels "
             "(n = 256 gives about 6.4 M voxels)",
    "sphere": "single-material bone ball of radius 0.3 n with an off-lattice centre, 1 mm voxels",
    "block": "a rectangular bone block with an air margin, 1 mm voxels",
}

#: default size (voxels along the longest axis) and Gaussian noise (HU) per phantom
DEFAULT_SIZE = {"head": 96, "long_bone": 96, "shell": 256, "sphere": 48, "block": 32}
DEFAULT_NOISE = 30.0
_MIN_SIZE = {"head": 32, "long_bone": 32, "shell": 8, "sphere": 8, "block": 8}

# Hounsfield units of the tissues
HU_AIR = -1000.0
HU_SCALP = 40.0
HU_BRAIN = 30.0
HU_MUSCLE = 50.0
HU_MARROW = 20.0
HU_BONE = 1000.0
HU_CORTEX = 1200.0
HU_HEADREST = 300.0


def _centres(n: int, spacing: float, dtype=np.float64) -> np.ndarray:
    """Voxel-centre coordinates (mm) along one axis, shape (n,)."""
    return ((np.arange(n, dtype=np.float64) + 0.5) * spacing).astype(dtype)


def _ball(shape, centre, radius) -> np.ndarray:
    """Boolean ball ``|x - centre| <= radius`` in voxel units (voxel i has centre i + 0.5).

    Compares ``dz^2 <= radius^2 - dx^2 - dy^2`` by broadcasting, so the only 3D
    temporary is the boolean result; exact in float64.
    """
    d2 = [(np.arange(n, dtype=np.float64) + 0.5 - c) ** 2 for n, c in zip(shape, centre)]
    if len(shape) == 2:
        return d2[1][None, :] <= radius**2 - d2[0][:, None]
    limit = radius**2 - d2[0][:, None] - d2[1][None, :]
    return d2[2][None, None, :] <= limit[:, :, None]


def _check_size(name: str, size) -> int:
    n = DEFAULT_SIZE[name] if size is None else int(size)
    if n < _MIN_SIZE[name]:
        raise DicerError(f"phantom {name!r}: size {n} is too small; use at least {_MIN_SIZE[name]} voxels")
    if n > MAX_SIZE:
        # checked before any array is made: the phantom's float arrays need about 16 bytes a voxel
        raise DicerError(f"phantom {name!r}: size {n} is too large (up to {n ** 3 * 16 / 2 ** 30:,.0f} GB of "
                         f"memory); use at most {MAX_SIZE} voxels")
    return n


MAX_SIZE = 1024
"""Largest phantom size (voxels along the longest axis): about 16 GB of arrays at 1024."""


# --- exact label builders ----------------------------------------------------------------


def shell_labels(n: int = 256) -> Volume:
    """Two-material ball: bone (2) for r <= 0.30 n, soft tissue (1) for 0.30 n < r <= 0.45 n.

    Parameters
    ----------
    n : int
        Voxels per axis; 1 mm voxels, centre at the volume centre (a voxel corner).

    Returns
    -------
    Volume
        uint8 labels of shape (n, n, n); about 4/3 pi (0.45 n)^3 non-background voxels
        (6.4 M for n = 256).
    """
    shape, centre = (n, n, n), (n / 2,) * 3
    labels = _ball(shape, centre, 0.45 * n).view(np.uint8)  # bool -> 0/1 without a copy
    labels += _ball(shape, centre, 0.30 * n)  # inner ball is inside the outer one: 2
    return Volume(labels, (1.0, 1.0, 1.0))


#: off-lattice offset (voxels) of the sphere phantom's centre from the volume centre
SPHERE_OFFSET = (0.31, 0.17, 0.23)


def sphere_labels(n: int = 48, label: int = BONE) -> Volume:
    """Single-material ball of radius 0.3 n centred at n/2 + ``SPHERE_OFFSET`` (voxel units).

    Parameters
    ----------
    n : int, optional
        Voxels per axis.
    label : int, optional
        Label of the ball.

    Returns
    -------
    Volume
        uint8 labels of shape (n, n, n): ``label`` inside, 0 outside; 1 mm voxels.
    """
    centre = tuple(n / 2 + o for o in SPHERE_OFFSET)
    labels = _ball((n, n, n), centre, 0.3 * n).astype(np.uint8) * np.uint8(label)
    return Volume(labels, (1.0, 1.0, 1.0))


def block_labels(n: int = 32, margin: int | None = None, label: int = BONE) -> Volume:
    """Rectangular block in a volume of shape (n, round(0.75 n), round(0.5 n)).

    Parameters
    ----------
    n : int, optional
        Voxels along x.
    margin : int, optional
        Background voxels on every side of the block (default max(1, n // 8); 0 fills
        the volume).
    label : int, optional
        Label of the block.

    Returns
    -------
    Volume
        uint8 labels, ``label`` in the block; 1 mm voxels.
    """
    shape = (n, int(round(0.75 * n)), int(round(0.5 * n)))
    m = max(1, n // 8) if margin is None else int(margin)
    labels = np.zeros(shape, np.uint8)
    labels[m : shape[0] - m, m : shape[1] - m, m : shape[2] - m] = label
    return Volume(labels, (1.0, 1.0, 1.0))


def _head(n: int, sinus: bool = True):
    """Head geometry: (labels uint8, HU float32, spacing). ``n`` voxels along y."""
    fov = np.array([180.0, 224.0, 184.0])  # mm, x (left-right), y (back-front), z (feet-head)
    s = round(fov[1] / n, 3)  # a short decimal survives NIfTI's float32 header unchanged
    spacing = np.array([s, s, round(1.25 * s, 3)])  # thicker slices, as in clinical CT
    shape = tuple(int(np.floor(f / sp + 0.5)) for f, sp in zip(fov, spacing))
    ext = np.array(shape) * spacing
    c = np.array([ext[0] / 2, ext[1] / 2 + 6.0, ext[2] / 2])  # head moved forward: room for the headrest
    A = np.array([72.0, 92.0, 80.0])  # scalp semi-axes (mm)
    B = A - 6.0  # skull outer surface: 6 mm of scalp
    f32 = np.float32
    x, y, z = (_centres(k, sp, f32) - f32(cc) for k, sp, cc in zip(shape, spacing, c))
    X, Y, Z = x[:, None, None], y[None, :, None], z[None, None, :]

    # normalised radius of the skull ellipsoid (q <= 1 inside); along the ray from the
    # centre through a voxel, u = w / q are the direction cosines of the normalised w
    wx, wz = X / f32(B[0]), Z / f32(B[2])  # 1D, broadcast below
    q = np.sqrt(wx * wx + (Y / f32(B[1])) ** 2 + wz * wz)
    inv_q = np.reciprocal(np.maximum(q, f32(1e-6)))
    uz = wz * inv_q
    # skull thickness (mm): thin temporal bone at the sides (5.5 mm, 2-3 voxels at the
    # default size), 11 mm at the vertex, 6 mm at the base
    inner = np.square(wx * inv_q)
    del inv_q
    inner *= f32(-3.0)
    inner += f32(8.5)
    inner += f32(2.5) * uz
    # the ray meets the outer skull at |p - c| / q mm from the centre, so the inner
    # surface sits at q = 1 - thickness * q / |p - c|; in place to spare memory
    inner *= q
    inner /= np.maximum(np.sqrt(X * X + Y * Y + Z * Z), f32(1e-6))
    np.subtract(f32(1.0), inner, out=inner)

    scalp = (X / f32(A[0])) ** 2 + (Y / f32(A[1])) ** 2 + (Z / f32(A[2])) ** 2 <= f32(1.0)
    skull = (q <= f32(1.0)) & (q > inner)
    brain = q <= inner
    labels = scalp.astype(np.uint8)  # soft tissue everywhere inside the scalp ...
    labels[skull] = BONE  # ... except the skull
    hu = np.where(scalp, f32(HU_SCALP), f32(HU_AIR)).astype(f32)
    hu[brain] = HU_BRAIN
    del q, inner, skull, brain
    if sinus:
        # frontal sinus: an air pocket inside a bony bulge on the inner frontal skull
        sc = np.array([0.0, 0.80 * B[1], -0.25 * B[2]])
        bulge = ((X - f32(sc[0])) / f32(16)) ** 2 + ((Y - f32(sc[1])) / f32(10)) ** 2 \
            + ((Z - f32(sc[2])) / f32(12)) ** 2 <= f32(1)
        air = ((X - f32(sc[0])) / f32(10)) ** 2 + ((Y - f32(sc[1])) / f32(5)) ** 2 \
            + ((Z - f32(sc[2])) / f32(6)) ** 2 <= f32(1)
        labels[bulge] = BONE
        labels[air] = AIR
    bone = labels == BONE
    hu[bone] = f32(HU_BONE) + f32(150.0) * uz[bone]  # denser towards the vertex
    del uz, bone
    if sinus:
        hu[air] = HU_AIR

    # headrest: a thin cylindrical arc behind the head, parallel to z, below the crown;
    # the gap (>= 2.5 voxels) keeps it disconnected from the head even with 26-neighbours
    gap = max(8.0, 2.5 * s)
    t_rest = max(4.0, 1.5 * s)
    r_in = A[1] + gap  # the head's horizontal cross-sections lie within radius A[1]
    r_xy = np.sqrt(X * X + Y * Y)
    behind = -Y >= r_xy * f32(np.cos(np.radians(55.0)))  # within 55 degrees of straight back
    rest = (r_xy >= f32(r_in)) & (r_xy <= f32(r_in + t_rest)) & behind & (Z <= f32(0.3 * A[2]))
    hu[rest] = HU_HEADREST
    return labels, hu, tuple(float(v) for v in spacing)


def head_labels(n: int = 96, sinus: bool = True) -> Volume:
    """True labels of the head phantom (the headrest is background).

    Parameters
    ----------
    n : int
        Voxels along y (the longest axis); in-plane spacing 224 / n mm, slices 1.25x
        thicker (both rounded to 0.001 mm).
    sinus : bool
        Include the frontal air sinus (a background cavity enclosed by bone).

    Returns
    -------
    Volume
        uint8 labels of shape (round(180/s), n, round(184/(1.25 s))).
    """
    labels, _, spacing = _head(n, sinus)
    return Volume(labels, spacing)


def _long_bone(n: int):
    """Long-bone geometry: (labels uint8, HU float32, spacing). ``n`` voxels along z."""
    fov = np.array([120.0, 120.0, 240.0])
    s = round(fov[2] / n, 3)
    shape = tuple(int(np.floor(f / s + 0.5)) for f in fov)
    ext = np.array(shape) * s
    f32 = np.float32
    x, y, z = (_centres(k, s, f32) for k in shape)
    X, Y = x[:, None, None] - f32(ext[0] / 2), y[None, :, None] - f32(ext[1] / 2)
    muscle = (X / f32(52.0)) ** 2 + (Y / f32(46.0)) ** 2 <= f32(1.0)  # 2D cross-section, full length

    # the bone, described per slice (1D in z): a bow, a radius and a wall thickness
    z0, z1 = 0.1 * ext[2], 0.9 * ext[2]
    zz = z.astype(np.float64)
    # per slice by the C library (math): numpy's exp and sin run their own vector code on AVX-512
    # CPUs, which differs in the last bit, and a voxel on the edge would follow it
    ends = np.array([math.exp(-(((v - z0) / 25.0) ** 2)) + math.exp(-(((z1 - v) / 25.0) ** 2))
                     for v in zz])  # 1 at the ends
    bow = 4.0 * np.array([math.sin(math.pi * min(max((v - z0) / (z1 - z0), 0.0), 1.0)) for v in zz])
    r_out = 13.0 + 9.0 * ends  # wider epiphyses
    wall = 5.0 + 3.5 * (1.0 - np.minimum(ends, 1.0))  # 8.5 mm in the shaft, 5 mm at the ends
    in_bone_z = (zz >= z0) & (zz <= z1)
    in_marrow_z = (zz >= z0 + 5.0) & (zz <= z1 - 5.0)
    r2 = (X - bow.astype(f32)[None, None, :]) ** 2 + Y * Y  # (nx, ny, nz) float32
    bone = (r2 <= (r_out**2).astype(f32)) & in_bone_z
    marrow = (r2 <= ((r_out - wall) ** 2).astype(f32)) & in_marrow_z
    cortex = bone & ~marrow

    labels = np.broadcast_to(muscle, shape).astype(np.uint8)
    labels[cortex] = BONE
    labels[marrow] = SOFT
    hu = np.where(labels == SOFT, f32(HU_MUSCLE), f32(HU_AIR)).astype(f32)
    hu[marrow] = HU_MARROW
    hu[cortex] = HU_CORTEX
    return labels, hu, (s, s, s)


def long_bone_labels(n: int = 96) -> Volume:
    """True labels of the long-bone phantom: marrow and muscle 1, cortical bone 2.

    Parameters
    ----------
    n : int, optional
        Voxels along z.

    Returns
    -------
    Volume
        uint8 labels of shape (round(120/s), round(120/s), n), s = 240 / n mm (to 0.001 mm).
    """
    labels, _, spacing = _long_bone(n)
    return Volume(labels, spacing)


# --- public entry points ----------------------------------------------------------------


def _geometry(name: str, n: int):
    """(labels, HU or None, spacing) of a phantom; HU None means 'by label'."""
    if name == "head":
        return _head(n)
    if name == "long_bone":
        return _long_bone(n)
    builder = {"shell": shell_labels, "sphere": sphere_labels, "block": block_labels}[name]
    vol = builder(n)
    return vol.array, None, vol.spacing


def _check_name(name: str) -> None:
    if name not in PHANTOMS:
        raise DicerError(f"phantom {name!r} is unknown; choose one of {', '.join(sorted(PHANTOMS))}")


def phantom_labels(name: str, size: int | None = None) -> Volume:
    """The true label volume of a phantom (0 background, 1 soft tissue, 2 bone).

    Parameters
    ----------
    name : str
        A key of ``PHANTOMS``.
    size : int, optional
        As in :func:`make_phantom`.

    Returns
    -------
    Volume
        uint8 labels, same grid as ``make_phantom(name, size)``.
    """
    _check_name(name)
    labels, _, spacing = _geometry(name, _check_size(name, size))
    return Volume(labels, spacing)


def make_phantom(name: str, size: int | None = None, noise: float | None = None, seed: int = 0) -> Volume:
    """A synthetic CT image of a phantom in HU with Gaussian noise.

    Parameters
    ----------
    name : str
        A key of ``PHANTOMS``.
    size : int, optional
        Voxels along the longest axis (``DEFAULT_SIZE[name]`` if omitted).
    noise : float, optional
        Standard deviation of the noise in HU (``DEFAULT_NOISE`` if omitted; 0 for none).
    seed : int
        Seed of the numpy Generator: the same seed gives the same image.

    Returns
    -------
    Volume
        float32 HU of shape given by the phantom, rounded to whole HU as a scanner
        stores them (so ``write_image`` stores int16).
    """
    _check_name(name)
    sigma = DEFAULT_NOISE if noise is None else float(noise)
    if not np.isfinite(sigma) or sigma < 0:
        raise DicerError(f"phantom {name!r}: noise {sigma:g} HU is invalid; give a standard deviation >= 0")
    labels, hu, spacing = _geometry(name, _check_size(name, size))
    if hu is None:
        lut = np.array([HU_AIR, HU_SCALP, HU_BONE], np.float32)
        hu = lut[labels]
    if sigma > 0:
        rng = np.random.default_rng(seed)
        noise_field = rng.standard_normal(hu.shape, dtype=np.float32)
        noise_field *= np.float32(sigma)  # in place: one float32 temporary at 256^3
        hu += noise_field
        del noise_field
    np.rint(hu, out=hu)
    return Volume(hu, spacing)
