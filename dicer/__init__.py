"""dicer: all-hexahedral finite-element models from CT and MR scans (Canton & Gilchrist's DICER)."""

__version__ = "0.1.0"

LIBRARIES = ("numpy", "scipy", "scikit-image", "meshio", "netCDF4", "PyYAML", "SimpleITK", "pydicom",
             "jsonschema", "matplotlib", "snakemake", "threadpoolctl")
"""The distributions dicer runs on (pyproject.toml's dependencies): their versions decide a
model's last bits (numpy's and scipy's arithmetic, the readers, the pictures; threadpoolctl
holds numpy's BLAS to one thread, dicer.parallel.one_blas_thread)."""


def library_versions() -> dict[str, str]:
    """The installed versions of Python and of :data:`LIBRARIES`, from their metadata (none is
    imported); a missing one is ``"not installed"``.

    Returns
    -------
    dict of str to str
        ``{"python": "3.11.7", "numpy": "2.4.6", ...}``, in the order of :data:`LIBRARIES`.
    """
    import platform
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out
