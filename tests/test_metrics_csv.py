"""`dicer quality --csv`: per-element metrics in automesh's columns, read back exactly."""

import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dicer.cli import main
from dicer.errors import DicerError
from dicer.export.textfmt import write_chunks
from dicer.io.meshes import write_mesh
from dicer.io.metrics_csv import HEADER, _fields_of, parse_metrics_csv, read_metrics_csv, write_metrics_csv
from dicer.mesh.metrics import edge_ratio, element_volumes, scaled_jacobian, skew
from dicer.mesh.voxel import voxel_mesh


@pytest.fixture
def mesh():
    labels = np.zeros((4, 3, 2), np.uint8)
    labels[:3, :, :] = 1
    labels[3, 1:, 1] = 2
    return voxel_mesh(labels, spacing=(2.0, 3.0, 4.0), origin=(-10.0, 5.0, 0.5))



def _lines(values: np.ndarray) -> bytes:
    """The value lines of a metrics CSV of ``values`` (M, 4), as the writer writes them."""
    stream = io.BytesIO()
    write_chunks(stream, values.shape[0], _fields_of(values), compact=True)
    return stream.getvalue()

def test_header_and_values_of_boxes(tmp_path, mesh):
    path = tmp_path / "m.csv"
    write_metrics_csv(mesh, path)
    text = path.read_text()
    assert text.splitlines()[0] == "maximum edge ratio,minimum scaled jacobian,maximum skew,element volume"
    rows = text.splitlines()[1:]
    assert len(rows) == mesh.n_cells == 20
    # every element a 2 x 3 x 4 mm box: edge ratio 2, scaled Jacobian 1, skew 0, 24 mm^3
    assert set(rows) == {"2.000000e+00,1.000000e+00,0.000000e+00,2.400000e+01"}
    assert np.array_equal(read_metrics_csv(path), np.tile([2.0, 1.0, 0.0, 24.0], (20, 1)))


def test_values_follow_the_metrics_module(tmp_path, mesh):
    rng = np.random.default_rng(2)
    mesh.points = mesh.points + rng.uniform(-0.3, 0.3, mesh.points.shape)
    path = tmp_path / "m.csv"
    write_metrics_csv(mesh, path)
    got = read_metrics_csv(path)
    want = np.column_stack([edge_ratio(mesh.points, mesh.cells), scaled_jacobian(mesh.points, mesh.cells),
                            skew(mesh.points, mesh.cells), element_volumes(mesh.points, mesh.cells)])
    assert got.shape == (20, 4)
    assert np.all(np.abs(got - want) <= 5.000001e-7 * np.abs(want))
    assert np.all(got[:, 2] > 0)  # moved nodes: skewed


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(min_value=-1e90, max_value=1e90, allow_nan=False).filter(lambda x: x == 0 or
                                                                                  abs(x) > 1e-90),
                min_size=4, max_size=40).filter(lambda v: len(v) % 4 == 0))
def test_print_and_parse_round_trip(values):
    v = np.array(values).reshape(-1, 4)
    data = HEADER + _lines(v)
    back = parse_metrics_csv(data)
    assert back.shape == v.shape
    assert np.all(np.abs(back - v) <= 5.000001e-7 * np.abs(v))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(min_value=0, max_value=1e90).filter(lambda x: x == 0 or x > 1e-90),
                min_size=4, max_size=80).filter(lambda v: len(v) % 4 == 0))
def test_the_fixed_width_parse_of_non_negative_lines_equals_the_general_one(values):
    """Lines of four non-negative values are parsed as columns of fixed width: the same
    values bit for bit as the parse that searches for the separators."""
    import dicer.io.metrics_csv as mc

    v = np.array(values).reshape(-1, 4)
    body = np.frombuffer(_lines(v), np.uint8)
    fast = mc._parse_non_negative(body)
    assert fast is not None
    assert fast.tobytes() == _general_parse(mc, body).tobytes()
    # a negative value changes the line's width: the fixed-width parse declines it
    negative = np.frombuffer(_lines(v * np.array([1, -1, 1, 1]) + np.array([0, -1, 0, 0])), np.uint8)
    assert mc._parse_non_negative(negative) is None


def _general_parse(mc, body):
    original = mc._parse_non_negative
    try:
        mc._parse_non_negative = lambda b: None
        return mc._parse_lines(body, "csv", lambda: 0)
    finally:
        mc._parse_non_negative = original


def test_damaged_files_are_refused():
    good = HEADER + b"1.000000e+00,1.000000e+00,0.000000e+00,2.400000e+01\n"
    assert parse_metrics_csv(good).tolist() == [[1.0, 1.0, 0.0, 24.0]]
    for bad, what in [(good[:-1], "cut short"), (good.replace(b",0.0", b";0.0"), "4 comma"),
                      (good.replace(b"2.4", b"2,4"), "4 comma"), (good.replace(b"e+01", b"x+01"), "line 2"),
                      (b"a,b\n" + good[len(HEADER):], "header")]:
        with pytest.raises(DicerError, match=what):
            parse_metrics_csv(bad)


def test_cli_quality_csv(tmp_path, capsys, mesh):
    vtu = tmp_path / "mesh.vtu"
    write_mesh(mesh, vtu)
    for name in ("a", "b"):
        code = main(["quality", str(vtu), "-o", str(tmp_path / f"{name}.json"), "--csv", str(tmp_path / f"{name}.csv"),
                     "-q", "--set", "materials=[{name: a}, {name: b}]"])
        assert code == 0, capsys.readouterr().err
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()  # reruns: same bytes
    assert len((tmp_path / "a.csv").read_bytes().splitlines()) == mesh.n_cells + 1
    code = main(["quality", str(vtu), "-o", str(tmp_path / "c.json"), "--csv", str(tmp_path / "c.txt"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: ") and "c.txt" in err and ".csv" in err
    assert not (tmp_path / "c.json").exists() and not (tmp_path / "c.txt").exists()


def test_parse_in_blocks_of_lines(monkeypatch):
    """A file longer than a block parses to the same values, and an error in a later
    block names its line in the whole file."""
    import dicer.io.metrics_csv as mc

    rng = np.random.default_rng(1)
    values = np.abs(rng.normal(1, 0.5, (50, 4)))
    data = HEADER + _lines(values)
    whole = parse_metrics_csv(data)
    monkeypatch.setattr(mc, "_CHUNK", 100)  # about two lines per block
    assert parse_metrics_csv(data).tobytes() == whole.tobytes()
    lines = data.split(b"\n")
    lines[40] = lines[40].replace(b"e", b"x", 1)
    with pytest.raises(DicerError, match="line 41 holds"):
        parse_metrics_csv(b"\n".join(lines))
    monkeypatch.setattr(mc, "_CHUNK", 10)  # blocks shorter than one line
    assert parse_metrics_csv(data).tobytes() == whole.tobytes()


@pytest.mark.parametrize("fails", ["report", "table"])
def test_quality_csv_beside_the_report_is_all_or_nothing(tmp_path, capsys, mesh, monkeypatch, fails):
    """The table is written in a second thread beside the report: either failing leaves
    neither file, the old ones as they were, and no temporaries."""
    import dicer.cli as cli
    import dicer.io.metrics_csv as mc

    vtu = tmp_path / "mesh.vtu"
    write_mesh(mesh, vtu)
    (tmp_path / "q.json").write_text("old")
    (tmp_path / "q.csv").write_text("old")

    def boom(*args, **kwargs):
        raise cli.DicerError(f"{fails}: broken on purpose")

    if fails == "report":
        monkeypatch.setattr(cli, "_report_of", boom)
    else:
        monkeypatch.setattr(mc, "element_metrics", boom)
    code = main(["quality", str(vtu), "-o", str(tmp_path / "q.json"), "--csv", str(tmp_path / "q.csv"), "-q",
                 "--set", "materials=[{name: a}, {name: b}]"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and f"{fails}: broken on purpose" in err
    assert (tmp_path / "q.json").read_text() == "old" and (tmp_path / "q.csv").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.vtu", "q.csv", "q.json"]
