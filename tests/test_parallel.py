"""Chunk work side by side (dicer.parallel): same results and the same first error as one thread."""

import io
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import dicer.parallel as parallel
from dicer.export.textfmt import Float, Int, Sci, row_ids, write_chunks
from dicer.export.textparse import FormatError, layout_of, parse_records
from dicer.parallel import ordered_map


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_ordered_map_keeps_order_whatever_finishes_first(workers):
    def slow_first(i):
        time.sleep(0.02 if i % 3 == 0 else 0.0)  # early items finish last
        return i * i

    assert list(ordered_map(slow_first, range(25), workers)) == [i * i for i in range(25)]


def test_ordered_map_raises_the_first_failing_item_in_order():
    def fail(i):
        if i in (7, 3, 12):
            time.sleep(0.05 if i == 3 else 0.0)  # item 3 fails last in time, first in order
            raise ValueError(i)
        return i

    got = []
    with pytest.raises(ValueError) as exc:
        for v in ordered_map(fail, range(20), 2):
            got.append(v)
    assert exc.value.args == (3,)
    assert got == [0, 1, 2]


def test_ordered_map_holds_few_items_in_flight():
    running, most = [0], [0]
    lock = threading.Lock()

    def work(i):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.005)
        with lock:
            running[0] -= 1
        return i

    started = []

    def items():
        for i in range(40):
            started.append(i)
            yield i

    for v in ordered_map(work, items(), 2):
        assert len(started) - v <= 2 * 2 + 1  # the consumer is never far behind the producer
    assert most[0] <= 2


def test_one_core_runs_in_the_callers_thread(monkeypatch):
    monkeypatch.setattr(parallel, "cores", lambda: 1)
    threads = set(ordered_map(lambda i: threading.get_ident(), range(5)))
    assert threads == {threading.get_ident()}


def test_a_single_item_runs_in_the_callers_thread_without_a_pool(monkeypatch):
    # an atlas's deck has thousands of one-piece blocks: no threads for them
    monkeypatch.setattr(parallel, "cores", lambda: pytest.fail("looked at the cores"))
    assert list(ordered_map(lambda i: (i, threading.get_ident()), [7])) == [(7, threading.get_ident())]
    assert list(ordered_map(lambda i: i, iter([]))) == []
    with pytest.raises(ZeroDivisionError):
        list(ordered_map(lambda i: 1 / i, [0]))
    monkeypatch.setattr(parallel, "cores", lambda: 2)
    assert list(ordered_map(lambda i: i * i, iter(range(6)))) == [0, 1, 4, 9, 16, 25]  # two and more: as before


def _deck(points, chunk):
    stream = io.BytesIO()
    fmt = Sci(9)
    write_chunks(stream, points.shape[0], lambda a, b: [Int(row_ids(a, b), 8, b"\n")]
                 + [Float(points[a:b, j], fmt, b",") for j in range(3)], chunk=chunk)
    return stream.getvalue()


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 400), chunk=st.integers(1, 64), seed=st.integers(0, 2**16))
def test_text_chunks_written_and_read_side_by_side_match_one_thread(n, chunk, seed):
    points = np.random.default_rng(seed).normal(scale=100.0, size=(n, 3))
    with pytest.MonkeyPatch.context() as m:
        m.setattr(parallel, "cores", lambda: 1)
        one = _deck(points, chunk)
        text = one[1:] + b"\n"  # records "<id>,x,y,z\n"
        body, layout = np.frombuffer(text, np.uint8), layout_of(text[: text.index(b"\n") + 1])
        ints1, reals1 = parse_records(body, layout, chunk=chunk)
    two = _deck(points, chunk)
    assert two == one
    ints2, reals2 = parse_records(body, layout, chunk=chunk)
    assert np.array_equal(ints1, ints2) and np.array_equal(reals1, reals2)
    want = np.array([[float(v) for v in line.split(b",")[1:]] for line in one.split(b"\n")[1:]])
    assert np.array_equal(reals2, want) and np.array_equal(ints2[:, 0], np.arange(1, n + 1))
    seen = []
    assert parse_records(body, layout, chunk=chunk,
                         sink=lambda start, i, r: seen.append((start, i[:, 0].copy()))) == n
    seen.sort(key=lambda s: s[0])
    assert np.array_equal(np.concatenate([ids for _, ids in seen]), np.arange(1, n + 1))


def test_parse_reports_the_first_bad_record_when_several_chunks_are_bad():
    record = b"       1, 1.00000000e+00, 2.50000000e-01,-3.00000000e+00\n"
    n, chunk = 5000, 64
    buf = bytearray(record * n)
    for row, col in ((4321, 12), (1234, 30), (77, 5)):  # chunks 67, 19 and 1
        buf[row * len(record) + col] = ord("x")
    with pytest.raises(FormatError) as exc:
        parse_records(np.frombuffer(bytes(buf), np.uint8), layout_of(record), chunk=chunk)
    assert exc.value.offset == 77 * len(record) + 5

    def sink(start, ints, reals):
        if start <= 3000 < start + ints.shape[0]:
            raise FormatError((3000 - start) * len(record), "sink")
    buf[77 * len(record) + 5] = record[5]
    buf[1234 * len(record) + 30] = record[30]
    with pytest.raises(FormatError) as exc:  # the sink's error at record 3000 comes before the byte at 4321
        parse_records(np.frombuffer(bytes(buf), np.uint8), layout_of(record), chunk=chunk, sink=sink)
    assert exc.value.offset == 3000 * len(record)


def test_a_stop_signal_ends_the_work_between_items_in_any_thread(monkeypatch):
    """After SIGTERM (its handler leaves the exception in atomic.stop_requested) chunked work
    stops before its next item, also in a thread other than the main one, which the
    handler's own raise does not reach (a table written beside a report)."""
    from concurrent.futures import ThreadPoolExecutor

    from dicer.io import atomic

    class Stop(Exception):
        pass

    done = []

    def consume(workers):
        for v in ordered_map(lambda i: i, range(100), workers):
            done.append(v)
            if v == 9:
                atomic.stop_requested.append(Stop)

    for workers in (1, 2):
        done.clear()
        try:
            with ThreadPoolExecutor(1) as other, pytest.raises(Stop):
                other.submit(consume, workers).result()
        finally:
            atomic.stop_requested.clear()
        assert done == list(range(10))


def test_sigterm_while_the_metrics_table_is_written_beside_the_report(tmp_path):
    from test_faults import _terminate_while_writing

    from dicer.io.meshes import write_mesh
    from dicer.mesh.voxel import voxel_mesh

    vtu = tmp_path / "m.vtu"
    write_mesh(voxel_mesh(np.ones((120, 120, 120), np.uint8)), vtu)
    _terminate_while_writing(["quality", str(vtu), "-o", str(tmp_path / "q.json"), "--csv", str(tmp_path / "t.csv")],
                             tmp_path, ".t.csv.*.tmp*", 120)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.vtu"]


def test_cores_follow_a_slurm_task_and_a_cgroup_quota(monkeypatch, tmp_path):
    import dicer.parallel as par

    monkeypatch.setattr(par.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    monkeypatch.setattr(par, "Path", lambda name: tmp_path / "cpu.max")  # no cgroup file
    monkeypatch.delenv("SLURM_CPUS_PER_TASK", raising=False)
    assert par.cores() == 4
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "1")
    assert par.cores() == 1
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "x")  # not a count: ignored
    assert par.cores() == 4
    (tmp_path / "cpu.max").write_text("150000 100000\n")  # 1.5 CPUs of quota
    assert par.cores() == 2
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert par.cores() == 4


def test_meanwhile_returns_the_result_or_raises_on_the_callers_thread():
    started = threading.Event()

    def work(x):
        started.set()
        time.sleep(0.05)
        return x * 2

    result = parallel.meanwhile(work, 21)
    assert started.wait(5)  # running before anyone waits
    assert result() == 42 and result() == 42

    def fail():
        raise ValueError("bad input")

    failed = parallel.meanwhile(fail)
    with pytest.raises(ValueError, match="bad input"):
        failed()


def test_sets_built_meanwhile_are_the_sets_built_in_line():
    """An export model's surface sets are built on a thread while the writer starts: read
    from any thread they are the sets of the model built in line, and the first read waits."""
    from dicer.config import load_config
    from dicer.export.model import _surface_sets, neighbour_materials, prepare_model
    from dicer.mesh.voxel import voxel_mesh

    lab = np.zeros((6, 5, 4), np.uint8)
    lab[:, :, :2] = 1
    lab[1:5, 1:4, 2:] = 2
    mesh = voxel_mesh(lab)
    config = load_config(settings={"materials": [{"name": "a"}, {"name": "b"}]})
    model = prepare_model(mesh, config)
    node_sets, exterior, cavities, interfaces = _surface_sets(model, {"materials", "interfaces", "exterior"},
                                                              neighbour_materials(mesh), mesh.cells, mesh.points)
    seen = []
    readers = [threading.Thread(target=lambda: seen.append(dict(model.node_sets))) for _ in range(3)]
    for r in readers:
        r.start()
    for r in readers:
        r.join()
    want = {k: v for k, v in model.node_sets.items() if k not in node_sets} | node_sets
    for got in seen:
        assert list(got) == list(model.node_sets) and all(np.array_equal(got[k], want[k]) for k in want)
    assert list(model.node_sets)[:6] == ["X0", "X1", "Y0", "Y1", "Z0", "Z1"]  # planes first, as written
    solid = np.pad(lab > 0, 1)
    faces = sum(int(np.count_nonzero(np.diff(solid.astype(int), axis=a) != 0)) for a in range(3))
    assert np.array_equal(model.exterior, exterior) and exterior.shape[0] == faces == 132
    assert np.array_equal(model.cavities, cavities) and cavities.size == 0
    assert list(model.interfaces) == ["a_b"] and np.array_equal(model.interfaces["a_b"], interfaces["a_b"])


def test_import_meanwhile_loads_the_modules_and_leaves_errors_to_the_importer(tmp_path, monkeypatch):
    import sys
    import types

    gate = types.SimpleNamespace(release=threading.Event(), done=False)
    monkeypatch.setitem(sys.modules, "dicer_probe_gate", gate)
    (tmp_path / "dicer_probe_slow.py").write_text(
        "import dicer_probe_gate as gate\ngate.release.wait(10)\nVALUE = 7\ngate.done = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "dicer_probe_slow", raising=False)
    parallel.import_meanwhile("dicer_probe_slow", "dicer_probe_missing")
    assert not gate.done  # returned while the module is still loading
    gate.release.set()
    import dicer_probe_slow  # waits for the thread's import (the import lock), then has it

    assert gate.done and dicer_probe_slow.VALUE == 7
    assert "dicer_probe_missing" not in sys.modules
    with pytest.raises(ImportError):
        import dicer_probe_missing  # noqa: F401 -- the error comes from the caller's own import
    monkeypatch.delitem(sys.modules, "dicer_probe_slow")


_PROBE = """
import json, sys
from threadpoolctl import threadpool_info, threadpool_limits
import dicer.cli as cli

def threads():
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

seen = {}
cli.cmd_phantom = lambda args: seen.setdefault("inside", threads())
status = cli.main(["phantom", "sphere", "-o", sys.argv[1]])
with threadpool_limits(limits=2, user_api="blas"):  # as on a machine of two cores or more
    two = threads()
    cli.main(["phantom", "sphere", "-o", sys.argv[1]])
    seen["after"] = threads()
print(json.dumps({"status": status, "two": two, **seen}))
"""


def test_a_command_runs_numpys_matrix_products_in_one_thread(tmp_path):
    """OpenBLAS's threads spin beside dicer's own (the 20-node export's fold check: 31-38 s
    against 18-23 s with one on a busy 2-core machine): a command runs them in one, in a fresh
    process too (dicer.cli loads numpy only when a command runs), also where Snakemake set
    ``OMP_NUM_THREADS`` to a job's threads, and gives the library back its threads after."""
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", _PROBE, str(tmp_path / "p.nii.gz")], env=env, check=True,
                         capture_output=True, text=True).stdout
    seen = json.loads(out.splitlines()[-1])
    assert seen["status"] == 0 and seen["two"] and set(seen["two"]) == {2}
    assert seen["inside"] and set(seen["inside"]) == {1}
    assert seen["after"] == seen["two"]
