"""dicer.pages: the commands' arrays in ordinary memory pages unless the user asks numpy otherwise."""

import pytest

from dicer.pages import _switch, ordinary_pages

switch = _switch()
pytestmark = pytest.mark.skipif(switch is None, reason="this numpy has no huge-page switch")


def current() -> bool:
    previous = switch(False)
    switch(previous)
    return bool(previous)


def test_ordinary_pages_inside_the_block_and_numpy_choice_restored_after(monkeypatch):
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    before = switch(True)
    try:
        with ordinary_pages(unless_set=True):
            assert current() is False
        assert current() is True
        with pytest.raises(RuntimeError), ordinary_pages():
            raise RuntimeError("a failing command")
        assert current() is True
    finally:
        switch(before)


def test_the_users_setting_stands(monkeypatch):
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
    before = switch(True)
    try:
        with ordinary_pages(unless_set=True):
            assert current() is True
        with ordinary_pages():  # the voxel mesher's own block ignores it
            assert current() is False
    finally:
        switch(before)


_SECOND_ARRAY_FAULTS = """
import resource, sys
from dicer.pages import reuse_freed_memory
applied = reuse_freed_memory() if sys.argv[1] == "reuse" else False
import numpy as np
a = np.ones(1 << 23)  # 64 MiB, above glibc's largest mmap threshold
del a
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
b = np.ones(1 << 23)
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _second_array_faults(mode: str, **env) -> tuple[str, int]:
    import os
    import subprocess
    import sys

    clean = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    clean["NUMPY_MADVISE_HUGEPAGE"] = "0"  # 4 KiB pages: one fault each
    out = subprocess.run([sys.executable, "-c", _SECOND_ARRAY_FAULTS, mode], env={**clean, **env},
                         capture_output=True, text=True, check=True).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not __import__("platform").libc_ver()[0] == "glibc", reason="glibc's malloc only")
def test_freed_arrays_memory_is_reused_by_the_next_array():
    applied, faults = _second_array_faults("reuse")
    assert applied == "True"
    assert faults < 500  # the freed 64 MiB served again: no fresh pages
    _, fresh = _second_array_faults("plain")
    assert fresh > 10_000  # glibc's default: 16,384 fresh pages, each faulted in
    applied, faults = _second_array_faults("reuse", MALLOC_ARENA_MAX="4")  # the user's own tuning stands
    assert applied == "False" and faults > 10_000


def test_map_readonly_gives_the_whole_file_and_refuses_writes(tmp_path):
    import numpy as np

    from dicer.pages import map_readonly

    data = np.random.default_rng(0).integers(0, 256, 3 * 4096 + 17, dtype=np.uint8).tobytes()
    path = tmp_path / "f.bin"
    path.write_bytes(data)
    with open(path, "rb") as f:
        mapped = map_readonly(f.fileno())
    assert len(mapped) == len(data) and mapped[:] == data
    with pytest.raises(TypeError):
        mapped[0] = 1
    mapped.close()


def test_large_jobs_are_told_by_their_inputs_size(tmp_path):
    import numpy as np

    from dicer.pages import LARGE_JOB, large_job

    small, large = tmp_path / "small.vtu", tmp_path / "large.vtu"
    with open(small, "wb") as f:
        f.truncate(76 * (LARGE_JOB - 1))  # sparse: no disk used
    with open(large, "wb") as f:
        f.truncate(76 * LARGE_JOB)
    assert not large_job([small]) and large_job([large]) and large_job([tmp_path / "c.yaml", large])
    # a label volume by its header's voxels, not its (compressed) bytes
    np.lib.format.open_memmap(tmp_path / "big.npy", "w+", np.uint8, (400, 400, 400))
    np.lib.format.open_memmap(tmp_path / "one.npy", "w+", np.uint8, (256, 256, 256))
    assert large_job([tmp_path / "big.npy"]) and not large_job([tmp_path / "one.npy"])
    (tmp_path / "empty.npy").write_bytes(b"")
    (tmp_path / "bad.nii.gz").write_bytes(b"not an image")
    assert not large_job([tmp_path / "missing.vtu", tmp_path, tmp_path / "empty.npy", tmp_path / "bad.nii.gz"])
