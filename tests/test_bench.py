"""The benchmark's process runner and tables (speed itself is measured, never asserted)."""

import sys

from bench import PROCESS_JOBS, process_tables, run_process


def test_run_process_reports_time_memory_and_failure():
    ok = run_process([sys.executable, "-c", "x = bytearray(50 * 2**20); x[::4096] = b'1' * len(x[::4096])"])
    assert "error" not in ok and ok["seconds"] >= 0 and ok["cpu_seconds"] >= 0
    assert ok["peak_rss_mb"] >= 50  # the child's own peak, not the bench process's
    bad = run_process([sys.executable, "-c", "import sys; sys.exit('no such mesh')"])
    assert bad["error"].startswith("exit 1") and "no such mesh" in bad["error"]


def test_tables_give_ratios_to_automesh_and_scaling():
    rows = []
    for n, scale in ((64, 1.0), (128, 8.0)):
        for name, seconds in (("mesh", 2.0), ("automesh mesh", 4.0), ("run", 10.0), ("automesh smooth", 1.0),
                              ("automesh .inp", 1.0), ("automesh metrics", 1.0)):
            rows.append({"size": n, "case": name, "seconds": seconds * scale, "cpu_seconds": seconds * scale,
                         "peak_rss_mb": 100.0})
    text = process_tables(rows)
    assert "| mesh | 2.00 | 2.00 | 100 | 0.50 / 0.50 |" in text
    assert "run: 1.43 / 1.43" in text  # 10 s against 4 + 1 + 1 + 1
    assert "| mesh | 2.00 (100) | 16.00 (100) | 1.00 |" in text  # 8x the voxels, 8x the time


def test_every_dicer_job_is_a_dicer_command():
    from pathlib import Path

    from bench import _job_command

    for job in PROCESS_JOBS:
        cmd = _job_command(job, Path("/w"))
        assert cmd[0] == sys.executable
        assert ("dicer.cli" in cmd) != ("automesh" in job[0])


def test_the_atlas_has_its_parcels_inside_a_ball():
    import numpy as np

    from bench import atlas_labels

    n = 48
    lab = atlas_labels(n, parcels=60)
    values = np.unique(lab)
    assert values[0] == 0 and values[1:].tolist() == list(range(1, 61))  # every parcel holds voxels
    g = np.indices(lab.shape) + 0.5 - n / 2
    r = np.sqrt((g ** 2).sum(axis=0))
    assert not lab[r >= 0.45 * n].any() and lab[r < 0.44 * n].all()
    assert np.array_equal(lab, atlas_labels(n, parcels=60))  # seeded: the same labels every run
