"""Faults while writing: a full disk, SIGTERM, temporary files of killed runs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.atomic import atomic_path, remove_stale_temporaries
from dicer.io.images import write_labels

ROOT = Path(__file__).resolve().parents[1]


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_temporaries_of_dead_processes_are_removed(tmp_path):
    target = tmp_path / "model.inp"
    dead = tmp_path / f".model.inp.{_dead_pid()}.abcdef.tmp.inp"
    alive = tmp_path / f".model.inp.{os.getppid()}.ghijkl.tmp.inp"
    other = tmp_path / f".other.inp.{_dead_pid()}.mnopqr.tmp.inp"
    for f in (dead, alive, other):
        f.write_text("partial")
    with atomic_path(target) as tmp:
        tmp.write_text("*HEADING\n")
    assert target.read_text() == "*HEADING\n"
    assert not dead.exists() and alive.exists() and other.exists()
    assert remove_stale_temporaries(tmp_path / "other.inp") == [other]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alive.name, "model.inp"])


def test_an_os_error_while_writing_is_one_error_and_leaves_the_target(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(DicerError, match="a.txt: cannot write the file"):
        with atomic_path(target) as tmp:
            tmp.write_text("new")
            raise OSError(5, "Input/output error")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


@pytest.fixture
def small_disk(tmp_path):
    """A 256 KiB tmpfs (root only); skipped where it cannot be mounted."""
    mount = tmp_path / "disk"
    mount.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root): " + proc.stderr.decode()[:80])
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)


def test_full_disk_keeps_the_good_file(small_disk):
    rng = np.random.default_rng(3)
    good = small_disk / "labels.nii.gz"
    write_labels(Volume(np.ones((4, 4, 4), np.uint8), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), good)
    before = good.read_bytes()
    noise = rng.integers(0, 250, (96, 96, 96)).astype(np.uint8)  # does not compress below 256 KiB
    with pytest.raises(DicerError, match="labels.nii.gz: .*(disk|does not hold)"):
        write_labels(Volume(noise, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), good)
    assert good.read_bytes() == before
    assert [p.name for p in small_disk.iterdir()] == ["labels.nii.gz"]


def test_full_disk_through_the_command(small_disk, tmp_path):
    rng = np.random.default_rng(4)
    labels = tmp_path / "labels.npy"
    np.save(labels, rng.integers(1, 3, (40, 40, 40)).astype(np.uint8))
    out = small_disk / "mesh.vtu"
    proc = subprocess.run([sys.executable, "-m", "dicer", "mesh", str(labels), "-o", str(out)], capture_output=True,
                          text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "mesh.vtu" in errors[0] and "Traceback" not in proc.stderr
    assert list(small_disk.iterdir()) == []


def _terminate_while_writing(args: list[str], folder: Path, pattern: str, seconds: float,
                             kept: str = "no output of the unfinished step was kept") -> str:
    """Start ``dicer ARGS``, send SIGTERM once a temporary file ``pattern`` shows in
    ``folder``, check the one error line (``kept`` after the signal's name) and exit status
    143; returns its stderr."""
    proc = subprocess.Popen([sys.executable, "-m", "dicer", *args], stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    deadline = time.monotonic() + seconds
    while not list(folder.glob(pattern)):
        assert proc.poll() is None, "the command ended before it began writing"
        assert time.monotonic() < deadline
        time.sleep(0.005)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=seconds)
    assert proc.returncode == 143, err
    assert [line for line in err.splitlines() if line.startswith("error:")] == [
        f"error: terminated (SIGTERM, e.g. a cluster time limit); {kept}"]
    return err


def test_sigterm_keeps_no_partial_output(tmp_path):
    labels = tmp_path / "labels.npy"
    np.save(labels, np.ones((150, 150, 150), np.uint8))
    out = tmp_path / "mesh.vtu"
    # signal while the mesh is being written: its temporary file exists from the start of
    # the write to the rename after the read-back check
    _terminate_while_writing(["mesh", str(labels), "-o", str(out)], tmp_path, ".mesh.vtu.*.tmp*", 120)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels.npy"]


def test_a_failed_run_leaves_the_old_results_and_keeps_its_stage_files(tmp_path):
    from dicer.cli import main

    image = tmp_path / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(image), "-q"]) == 0
    out = tmp_path / "out"
    args = ["run", str(image), "-o", str(out), "-q", "--set", "downsample.factor=4"]
    assert main(args) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert "model.inp" in before and not (tmp_path / ".out.partial").exists()
    assert main(args + ["--set", "smooth.min_scaled_jacobian=0.99", "--set", "smooth.max_backoff_rounds=0"]) == 2
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    failed = tmp_path / "out.failed"
    assert {"labels_fixed.nii.gz", "mesh.vtu", "merged.vtu", "fix.json"} <= {p.name for p in failed.iterdir()}
    assert not (failed / "smoothed.vtu").exists() and not (tmp_path / ".out.partial").exists()
    # a finished run replaces every result of the earlier one
    assert main(args) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_failed_run_names_its_stage_and_the_kept_files(tmp_path, capsys):
    from dicer.cli import main

    image = tmp_path / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(image), "-q"]) == 0
    out = tmp_path / "new"
    assert main(["run", str(image), "-o", str(out), "-q", "--set", "downsample.factor=4",
                 "--set", "smooth.min_scaled_jacobian=0.99", "--set", "smooth.max_backoff_rounds=0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and str(tmp_path / "new.failed") in err[0]
    assert "stopped at the smooth stage" in err[0] and ".partial" not in err[0]
    assert not out.exists()


def test_full_disk_image_write_is_one_line_naming_the_target(small_disk, capfd):
    """The NIfTI writer prints its short write straight to stderr and fails in the read-back:
    the error says the disk is full and names the target, not the temporary file."""
    from dicer.io.images import write_image

    rng = np.random.default_rng(5)
    out = small_disk / "ct.nii"
    with pytest.raises(DicerError) as info:
        write_image(Volume(rng.normal(size=(48, 48, 48)).astype(np.float32), (1.0, 1.0, 1.0)), out)
    assert str(info.value).startswith(f"{out}: the disk is full") and ".tmp" not in str(info.value)
    assert capfd.readouterr().err == ""  # nothing of ITK's own
    assert list(small_disk.iterdir()) == []


def test_a_command_keeps_all_its_old_outputs_when_a_later_one_fails(small_disk, tmp_path):
    """quality writes the report after the HTML: a full disk at the second write leaves
    neither new (the first was held back until both were written)."""
    from dicer.cli import main

    labels = tmp_path / "labels.npy"
    np.save(labels, np.ones((6, 6, 6), np.uint8))
    mesh = tmp_path / "m.vtu"
    assert main(["mesh", str(labels), "-o", str(mesh), "-q"]) == 0
    html, report = tmp_path / "q.html", small_disk / "q.json"
    html.write_text("old")
    try:  # fill the disk to the last block
        with open(small_disk / "filler", "wb", buffering=0) as f:
            while True:
                f.write(b"x" * 4096)
    except OSError:
        pass
    assert main(["quality", str(mesh), "-o", str(report), "--html", str(html), "-q"]) == 2
    assert html.read_text() == "old" and not report.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk", "labels.npy", "m.vtu", "q.html"]


def test_a_signal_right_after_the_temporary_file_is_made_leaves_none(tmp_path, monkeypatch):
    import dicer.io.atomic as atomic

    real = os.close

    def interrupted(fd):
        real(fd)
        raise KeyboardInterrupt  # as a SIGTERM handler raises between two steps

    monkeypatch.setattr(atomic.os, "close", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("never")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


def test_all_or_nothing_removes_the_folders_it_made(tmp_path):
    from dicer.io.atomic import all_or_nothing, write_bytes_atomic

    with pytest.raises(DicerError):
        with all_or_nothing():
            write_bytes_atomic(tmp_path / "new" / "deeper" / "a.json", "{}")
            raise DicerError("a later step failed")
    assert list(tmp_path.iterdir()) == []
    with all_or_nothing():
        write_bytes_atomic(tmp_path / "new" / "a.json", "{}")
        assert not (tmp_path / "new" / "a.json").exists()  # renamed at the end of the block
    assert (tmp_path / "new" / "a.json").read_text() == "{}"


def test_a_sigterm_whose_exception_was_lost_still_stops_before_any_rename(tmp_path, capsys):
    """CPython can drop the exception a signal handler raises inside C code (a module being
    compiled on import); the handler's note makes the next rename raise it again."""
    from dicer.cli import Terminated, main
    from dicer.io import atomic

    labels = tmp_path / "labels.npy"
    np.save(labels, np.ones((6, 6, 6), np.uint8))
    atomic.stop_requested.append(Terminated)  # as _terminate leaves it when its raise is lost
    assert main(["mesh", str(labels), "-o", str(tmp_path / "m.vtu"), "-q"]) == 143
    assert "terminated (SIGTERM" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels.npy"] and atomic.stop_requested == []


def _head_run(tmp_path):
    from dicer.cli import main

    image = tmp_path / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(image), "-q"]) == 0
    return main, ["run", str(image), "-q", "--set", "downsample.factor=4"]


def test_the_quality_report_beside_the_exports_leaves_the_same_files(tmp_path, monkeypatch):
    import dicer.cli as cli

    main, args = _head_run(tmp_path)
    results = {}
    for beside in (False, True):
        monkeypatch.setattr(cli, "_side_by_side", lambda source, elements, order=1, faces=None, beside=beside: beside)
        out = tmp_path / f"out_{beside}"
        assert main(args + ["-o", str(out)]) == 0
        results[beside] = {p.name: p.read_bytes() for p in out.iterdir()}
    assert len(results[True]) >= 15 and {"model.inp", "model.vtu", "quality.json", "report.html"} <= set(results[True])
    assert results[True] == results[False]


def test_a_failure_beside_the_exports_names_the_quality_stage(tmp_path, monkeypatch, capsys):
    import dicer.cli as cli

    main, args = _head_run(tmp_path)
    monkeypatch.setattr(cli, "_side_by_side", lambda source, elements, order=1, faces=None: True)

    def broken(mesh_path, out, *a, **k):
        time.sleep(0.5)  # still running when the exports end
        raise DicerError(f"{mesh_path}: broken on purpose")

    monkeypatch.setattr(cli, "do_quality", broken)
    out = tmp_path / "out"
    assert main(args + ["-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken on purpose" in err[0] and "stopped at the quality stage" in err[0]
    failed = tmp_path / "out.failed"
    assert {"model.inp", "model.vtu", "smoothed.vtu"} <= {p.name for p in failed.iterdir()}
    assert not out.exists() and not list(failed.glob(".*tmp*"))


def test_sigterm_while_the_report_is_made_beside_the_exports(tmp_path):
    from dicer.cli import main

    image = tmp_path / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(image), "-q"]) == 0
    out = tmp_path / "out"
    staging = tmp_path / ".out.partial"
    # once the exports began, the report beside them
    err = _terminate_while_writing(["run", str(image), "-o", str(out), "--set", "downsample.factor=2"], staging,
                                   ".model.inp.*.tmp*", 300,
                                   f"{out} is unchanged; the finished stage files are in {tmp_path / 'out.failed'}")
    assert "dicer run: the quality report is made beside the exports" in err
    assert not out.exists() and not staging.exists()
    failed = tmp_path / "out.failed"
    assert not list(failed.glob(".*tmp*")) and not (failed / "model.inp").exists()


def test_a_stage_file_written_beside_the_next_stage_names_its_stage_when_it_fails(tmp_path, monkeypatch, capsys):
    import dicer.cli as cli
    import dicer.io.meshes as meshes

    main, args = _head_run(tmp_path)
    monkeypatch.setattr(cli, "_side_by_side", lambda source, elements, order=1, faces=None: True)
    real = meshes.write_mesh

    def failing(mesh, path, *a, **k):
        if Path(path).name == "merged.vtu":
            time.sleep(0.5)  # the smooth stage runs meanwhile
            raise DicerError(f"{path}: the disk is full (No space left on device); free space or write elsewhere, "
                             "nothing was written")
        return real(mesh, path, *a, **k)

    monkeypatch.setattr(meshes, "write_mesh", failing)
    out = tmp_path / "out"
    assert main(args + ["-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "merged.vtu: the disk is full" in err[0] and "stopped at the merge stage" in err[0]
    failed = tmp_path / "out.failed"
    kept = {p.name for p in failed.iterdir()}
    assert {"mesh.vtu", "merge.json"} <= kept and "merged.vtu" not in kept and "model.inp" not in kept
    assert not out.exists() and not list(failed.glob(".*tmp*"))


def test_a_merge_whose_check_beside_the_smoothing_fails_is_named_before_the_smoothing(tmp_path, monkeypatch, capsys):
    # merge.min_scaled_jacobian=-1 let merging flatten corners; the merged file's check ran beside
    # the smoothing, whose error ("smoothing cannot keep element 5 ...") came first and named a
    # file the failed folder does not hold
    import dicer.cli as cli

    x, y, z = np.meshgrid(*[np.arange(48) + 0.5] * 3, indexing="ij")
    plates = np.zeros((48, 48, 48), np.uint8)
    # (offsets 30 and 10 until the merge counted mirror images at the image's planes: it now
    # refuses the flat corners those plates had at the planes)
    plates[np.abs((0.3 * x + 0.5 * y + 0.81 * z) / np.linalg.norm([0.3, 0.5, 0.81]) - 28) < 0.6] = 1
    plates[np.abs((0.7 * x - 0.4 * y + 0.2 * z) / np.linalg.norm([0.7, -0.4, 0.2]) - 12) < 1.0] = 2
    np.save(tmp_path / "plates.npy", plates)
    monkeypatch.setattr(cli, "_side_by_side", lambda source, elements, order=1, faces=None: True)
    out = tmp_path / "out"
    assert cli.main(["run", "--labels", str(tmp_path / "plates.npy"), "-o", str(out), "-q", "--set",
                     "merge.min_scaled_jacobian=-1", "--set", "merge.passes=[2,2,2]"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "merge.min_scaled_jacobian=-1 let merging make flat or inverted corners" in err[0]
    assert "stopped at the merge stage" in err[0] and "smoothing cannot" not in err[0]


def test_an_interrupt_that_left_an_exec_of_a_string_still_exits_130(tmp_path):
    # CPython ends a "python -m" process by SIGINT once a KeyboardInterrupt has left an
    # exec() of a string, even a caught one: a SIGINT that lands while an import makes a
    # namedtuple did so (about one run in 70 of 'dicer run' stopped after mesh.vtu)
    np.save(tmp_path / "labels.npy", np.ones((2, 2, 2), np.uint8))
    (tmp_path / "interrupted_probe.py").write_text(
        "import dicer.cli as cli\n"
        "def interrupted(args):\n"
        "    exec('raise KeyboardInterrupt')\n"
        "cli.cmd_mesh = interrupted\n"
        "raise SystemExit(cli.main(['mesh', 'labels.npy', '-o', 'mesh.vtu']))\n")
    proc = subprocess.run([sys.executable, "-m", "interrupted_probe"], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip() == "error: interrupted; no output was kept"
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".py" and p.name != "__pycache__") == [
        "labels.npy"]


def test_a_flush_that_fails_while_the_deck_is_checked_is_one_error_and_no_file(tmp_path, monkeypatch):
    """The export flushes its file on a thread while the check reads it: a full disk that
    shows only in the flush is the same one error, and no file is left."""
    import errno

    import dicer.io.atomic as atomic
    from dicer.config import load_config
    from dicer.export import export_mesh
    from dicer.mesh.voxel import voxel_mesh

    def full(path):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic, "_fsync", full)
    lab = np.ones((3, 3, 3), np.uint8)
    out = tmp_path / "m.inp"
    with pytest.raises(DicerError) as info:
        export_mesh(voxel_mesh(lab), out, load_config(settings={"materials": [{"name": "bone"}]}))
    assert str(info.value).startswith(f"{out}: the disk is full") and ".tmp" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("umask, mode", [(0o077, 0o600), (0o022, 0o644), (0o002, 0o664)])
def test_outputs_take_the_users_umask(tmp_path, umask, mode):
    """Every output was made 0644 whatever the umask: labels and decks of a private
    (umask 077) session came out readable by every user of the machine."""
    np.save(tmp_path / "l.npy", np.ones((3, 3, 3), np.uint8))
    out = tmp_path / "m.vtu"
    proc = subprocess.run([sys.executable, "-m", "dicer", "mesh", str(tmp_path / "l.npy"), "-o", str(out), "-q"],
                          preexec_fn=lambda: os.umask(umask), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert out.stat().st_mode & 0o777 == mode
