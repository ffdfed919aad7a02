"""The hostile-input re-run (tests/hostile.py) as a test: every case passes.

Slow (a few hundred whole dicer processes, several minutes): kept out of the default
suite; run it with ``pytest -m slow tests/test_hostile.py`` or ``python -m tests.hostile``.
"""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import hostile  # noqa: E402


@pytest.mark.slow
def test_every_hostile_case_passes(tmp_path):
    results = hostile.run_all(hostile.CASES, jobs=2, workdir=tmp_path)
    print(hostile.summary(results))
    ran = [r for r in results if r.status != "skip"]
    failed = [f"[{r.case.cls}] {r.case.name}: {'; '.join(r.reasons)}" for r in ran if r.status == "fail"]
    assert len(results) == len(hostile.CASES) >= 250
    assert len(ran) >= 300, [r.reasons for r in results if r.status == "skip"][:3]
    assert failed == [], "\n".join(failed)
    # every class is exercised (the full disk needs a tmpfs mount, the sheet Snakemake)
    assert {r.case.cls for r in ran} >= set(hostile.CLASSES) - {"1-full-disk", "6-cohort"}


def test_the_case_table_covers_every_class_and_command():
    """Cheap (no process): the table's shape, so a change that drops a class shows."""
    counts = {cls: sum(c.cls == cls for c in hostile.CASES) for cls in hostile.CLASSES}
    assert min(counts.values()) >= 10, counts
    assert len(hostile.CASES) >= 250
    names = [c.name for c in hostile.CASES]
    assert len(names) == len(set(names))  # each case once
    for command in hostile.COMMANDS:  # every command is run with bad input and in a good use
        assert any(n.startswith(f"{command}: ") and not c.good for n, c in zip(names, hostile.CASES)), command
        assert f"{command}: the good use" in names
