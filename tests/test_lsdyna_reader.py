"""The strict LS-DYNA reader: fast (cards a block at a time, node sets together) and the same
dict as the former column-by-column reader; corrupted files refused naming the line."""

from __future__ import annotations

import re
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dicer.config import load_config
from dicer.errors import DicerError
from dicer.export import export_mesh
from dicer.export import lsdyna
from dicer.export.lsdyna import _read_lsdyna, read_lsdyna
from dicer.export.readers import Lines
from dicer.export.textparse import FormatError, layout_of_columns, parse_column, parse_records
from dicer.mesh.voxel import voxel_mesh


# --- the former reader (reference) ------------------------------------------------------------


def _former_read_lsdyna(path) -> dict:
    """The LS-DYNA reader as it was before the cards were parsed a block at once (column by column,
    set by set): the reference the fast reader must agree with."""
    lines = Lines(path)
    n = len(lines)
    is_key = lines.arr[lines.starts[lines.lengths > 0]] == ord("*")
    key_rows = np.flatnonzero(lines.lengths > 0)[is_key]
    comment = np.zeros(n, bool)
    nonempty = np.flatnonzero(lines.lengths > 0)
    comment[nonempty[lines.arr[lines.starts[nonempty]] == ord("$")]] = True
    keys = [lines.text(i).strip().upper() for i in key_rows]
    if not keys or keys[0] != "*KEYWORD" or keys[-1] != "*END":
        raise DicerError("an LS-DYNA keyword file starts with *KEYWORD and ends with *END")
    bounds = list(key_rows) + [n]
    out = {"parts": {}, "materials": {}, "node_sets": {}, "segment_sets": {}, "title": ""}
    points = cells = pids = None
    for i, key in enumerate(keys):
        rows = np.arange(bounds[i] + 1, bounds[i + 1])
        rows = rows[~comment[rows]]
        if key == "*TITLE":
            out["title"] = lines.text(rows[0]) if rows.size else ""
        elif key == "*NODE":
            lines.lengths_are(rows, 56, "*NODE")
            ids = lines.ints(rows, 0, 8, "*NODE id")
            if not np.array_equal(ids, np.arange(1, rows.size + 1)):
                raise DicerError("*NODE ids must run 1..N in order")
            points = np.column_stack([lines.floats(rows, 8 + 16 * j, 16, "*NODE coordinate") for j in range(3)])
        elif key == "*PART":
            if rows.size != 2:
                raise DicerError("*PART needs a title card and one data card")
            vals = [lines.ints(rows[1:], 10 * k, 10, "*PART")[0] for k in range(3)]
            pid, secid, mid = (int(v) for v in vals)
            out["parts"][pid] = {"title": lines.text(rows[0]).strip(), "secid": secid, "mid": mid}
        elif key == "*SECTION_SOLID":
            if rows.size != 1:
                raise DicerError("*SECTION_SOLID needs one data card")
            out.setdefault("sections", {})[int(lines.ints(rows, 0, 10, "*SECTION_SOLID")[0])] = int(
                lines.ints(rows, 10, 10, "*SECTION_SOLID ELFORM")[0])
        elif key == "*MAT_ELASTIC":
            if rows.size != 1:
                raise DicerError("*MAT_ELASTIC needs one data card")
            mid = int(lines.ints(rows, 0, 10, "*MAT_ELASTIC")[0])
            out["materials"][mid] = tuple(float(lines.floats(rows, 10 * k, 10, "*MAT_ELASTIC")[0]) for k in (1, 2, 3))
        elif key == "*ELEMENT_SOLID":
            lines.lengths_are(rows, 80, "*ELEMENT_SOLID")
            ids = lines.ints(rows, 0, 8, "*ELEMENT_SOLID id")
            if not np.array_equal(ids, np.arange(1, rows.size + 1)):
                raise DicerError("*ELEMENT_SOLID ids must run 1..M in order")
            pids = lines.ints(rows, 8, 8, "*ELEMENT_SOLID part").astype(np.int32)
            cells = np.column_stack([lines.ints(rows, 16 + 8 * j, 8, "*ELEMENT_SOLID node") for j in range(8)])
        elif key == "*SET_NODE_LIST_TITLE":
            if rows.size < 2:
                raise DicerError("*SET_NODE_LIST_TITLE needs a title and a data card")
            name = lines.text(rows[0]).strip()
            data = rows[2:]
            if data.size and np.any(lines.lengths[data] % 10):
                raise DicerError(f"node set {name}: cards must be whole 10-column fields")
            full = data[lines.lengths[data] == 80]
            ids = [lines.ints(full, 10 * k, 10, "node set")[:, None] for k in range(8)]
            ids = np.concatenate(ids, axis=1).ravel() if full.size else np.zeros(0, np.int64)
            tail = data[lines.lengths[data] < 80]
            if tail.size > 1 or (tail.size == 1 and tail[0] != data[-1]):
                raise DicerError(f"node set {name}: only the last card may be short")
            if tail.size:
                k = int(lines.lengths[tail[0]]) // 10
                ids = np.concatenate([ids] + [lines.ints(tail, 10 * j, 10, "node set") for j in range(k)])
            out["node_sets"][name] = ids - 1
        elif key == "*SET_SEGMENT_TITLE":
            if rows.size < 3:
                raise DicerError("*SET_SEGMENT_TITLE needs a title, a SID card and a segment card")
            name, data = lines.text(rows[0]).strip(), rows[2:]
            if np.any(lines.lengths[data] != 40):
                raise DicerError(f"segment set {name}: a segment card is four 10-column node ids")
            out["segment_sets"][name] = np.column_stack([lines.ints(data, 10 * k, 10, "segment node")
                                                         for k in range(4)]) - 1
        elif key in ("*KEYWORD", "*END"):
            if rows.size:
                raise DicerError(f"{key} takes no data cards")
        else:
            raise DicerError(f"unexpected keyword {key}")
    if points is None or cells is None:
        raise DicerError("no *NODE or *ELEMENT_SOLID block")
    if cells.min() < 1 or cells.max() > points.shape[0]:
        raise DicerError("elements refer to nodes that do not exist")
    out.update(points=points, cells=cells - 1, material=pids)
    return out


# --- helpers ----------------------------------------------------------------------------------


def _config(n_materials: int) -> dict:
    rng = np.random.default_rng(n_materials)
    materials = [{"name": f"mat{k}", "youngs_modulus": float(rng.uniform(0.5, 2e4)),
                  "poissons_ratio": float(rng.uniform(0.0, 0.49)), "density": float(rng.uniform(1e-10, 3e-9))}
                 for k in range(1, n_materials + 1)]
    return load_config(settings={"materials": materials})


def _labels(shape, n_materials: int, seed: int) -> np.ndarray:
    lab = np.random.default_rng(seed).integers(0, n_materials + 1, size=shape).astype(np.uint8)
    lab.flat[0] = 1
    return lab


def _write(path: Path, labels: np.ndarray, n_materials: int, spacing=(0.5, 0.75, 1.25),
           origin=(-3.0, 10.0, -0.125), scale: float = 1.0, seed: int = 0) -> Path:
    """An LS-DYNA file of a voxel mesh (negative coordinates, smoothed-looking noise)."""
    mesh = voxel_mesh(labels, spacing=spacing, origin=origin)
    noise = np.random.default_rng(seed).normal(scale=0.2 * min(spacing), size=mesh.points.shape)
    mesh.points = (mesh.points + noise) * scale
    mesh.spacing, mesh.origin = np.multiply(mesh.spacing, scale), np.multiply(mesh.origin, scale)  # the same model
    export_mesh(mesh, path, _config(n_materials))  # its own read-back check passes too
    return path


def _same(a, b) -> bool:
    """Equal dicts: keys in order, arrays of one dtype, shape and bytes, scalars of one type."""
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and a.flags.c_contiguous == b.flags.c_contiguous and a.tobytes() == b.tobytes())
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, tuple):
        return isinstance(b, tuple) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def _assert_same(path: Path) -> dict:
    """The fast reader, its line-by-line path and the former reader give one dict."""
    got = _read_lsdyna(path)
    assert _same(got, _former_read_lsdyna(path))
    assert _same(lsdyna._parse(Lines(path), {}), got)
    return got


def _lines(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True)


def _line_no(lines: list[bytes], prefix: bytes, after: int = 0) -> int:
    """0-based index of the first line from ``after`` on that starts with ``prefix``."""
    return next(i for i in range(after, len(lines)) if lines[i].startswith(prefix))


@lru_cache(maxsize=None)
def _model_k() -> bytes:
    """A file of three materials, 60 elements, 114 nodes, node sets of full and short cards."""
    with tempfile.TemporaryDirectory() as tmp:
        return _write(Path(tmp) / "m.k", _labels((3, 4, 5), 3, seed=1), 3).read_bytes()


@pytest.fixture
def model_k(tmp_path) -> Path:
    path = tmp_path / "m.k"
    path.write_bytes(_model_k())
    return path


def _bad(tmp_path: Path, lines: list[bytes], row: int, new: bytes) -> Path:
    bad = list(lines)
    bad[row] = new
    path = tmp_path / "bad.k"
    path.write_bytes(b"".join(bad))
    return path


# --- the same dict as the former reader ------------------------------------------------------


@pytest.mark.parametrize("shape, n_materials", [((2, 2, 2), 2), ((3, 4, 5), 3), ((6, 5, 7), 4)])
def test_fast_reader_gives_the_former_readers_dict(tmp_path, shape, n_materials):
    # small (columns of at most 64 cards went through numpy) and larger blocks (parse_column)
    path = _write(tmp_path / "m.k", _labels(shape, n_materials, seed=n_materials), n_materials)
    plain = lsdyna._cut_large_blocks(path)
    assert plain is not None and len(plain[1]) == 2  # dicer's own file: both large blocks cut out
    got = _assert_same(path)
    assert len(got["materials"]) == len(got["parts"]) == len(got["sections"]) == n_materials
    assert got["points"].min() < 0 and got["node_sets"]
    assert any(ids.size > 8 and ids.size % 8 for ids in got["node_sets"].values())  # full and short cards


@st.composite
def volumes(draw):
    """Random small label volumes, coordinates of any sign over many decades."""
    shape = tuple(draw(st.integers(1, 5)) for _ in range(3))
    k = draw(st.integers(1, 4))
    flat = draw(st.lists(st.integers(0, k), min_size=int(np.prod(shape)), max_size=int(np.prod(shape))))
    labels = np.array(flat, np.uint8).reshape(shape)
    if not labels.any():
        labels.flat[draw(st.integers(0, labels.size - 1))] = draw(st.integers(1, k))
    spacing = tuple(draw(st.floats(0.01, 5.0)) for _ in range(3))
    origin = tuple(draw(st.floats(-1e3, 1e3)) for _ in range(3))
    return labels, k, spacing, origin, 10.0 ** draw(st.integers(-40, 40)), draw(st.integers(0, 2**32 - 1))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=volumes())
def test_fast_reader_agrees_with_the_former_one_on_random_volumes(case):
    labels, k, spacing, origin, scale, seed = case
    with tempfile.TemporaryDirectory() as tmp:
        path = _write(Path(tmp) / "m.k", labels, k, spacing, origin, scale, seed)
        got = _assert_same(path)
    assert got["cells"].shape[0] == int(np.count_nonzero(labels))


def test_comment_lines_among_the_cards_read_column_by_column(tmp_path, model_k):
    lines = _lines(model_k)
    node, element = _line_no(lines, b"*NODE"), _line_no(lines, b"*ELEMENT_SOLID")
    nset = _line_no(lines, b"*SET_NODE_LIST_TITLE")
    # comments inside the node and element blocks and between a set's cards
    for row in sorted([node + 5, element + 7, nset + 5], reverse=True):
        lines.insert(row, b"$ a comment\n")
    path = tmp_path / "c.k"
    path.write_bytes(b"".join(lines))
    assert lsdyna._cut_large_blocks(path) is None
    got = _assert_same(path)
    assert _same(got, _read_lsdyna(model_k))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(at=st.floats(0.0, 1.0, exclude_max=True), how=st.sampled_from(["replace", "insert", "delete"]),
       byte=st.one_of(st.sampled_from(list(b"0123456789 -+.eE*$\n\rx")), st.integers(0, 255)))
def test_a_changed_byte_is_refused_or_read_as_the_former_reader_reads_it(at, how, byte):
    # the fast reader is at least as strict as the former one, and where it accepts a file
    # it gives the same dict
    data = bytearray(_model_k())
    i = int(at * len(data))
    if how == "replace":
        data[i] = byte
    elif how == "insert":
        data.insert(i, byte)
    else:
        del data[i]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.k"
        path.write_bytes(bytes(data))
        try:
            got = _read_lsdyna(path)
        except DicerError:
            return
        assert _same(got, _former_read_lsdyna(path))


# --- corrupted files: DicerError naming the line ------------------------------------------------


def test_truncated_files_are_refused(tmp_path, model_k):
    data = model_k.read_bytes()
    lines = _lines(model_k)
    element = _line_no(lines, b"*ELEMENT_SOLID")
    for name, cut, message in (
            ("mid.k", data[: len(data) // 2 + 5], r"the file ends in the middle of a line \(truncated\?\)"),
            ("lines.k", b"".join(lines[: element + 9]),
             r"an LS-DYNA keyword file starts with \*KEYWORD and ends with \*END "
             rf"\(this one ends after line {element + 9} without \*END: truncated\?\)"),
            ("empty.k", b"", r"the file ends in the middle of a line")):
        (tmp_path / name).write_bytes(cut)
        with pytest.raises(DicerError, match=rf"{re.escape(name)}: {message}"):
            read_lsdyna(tmp_path / name)


@pytest.mark.parametrize("block, card, column, what, columns", [
    (b"*NODE", 6, 30, r"\*NODE coordinate", "25-40"),
    (b"*NODE", 6, 3, r"\*NODE id", "1-8"),
    (b"*ELEMENT_SOLID", 4, 30, r"\*ELEMENT_SOLID node", "25-32"),
    (b"*ELEMENT_SOLID", 4, 12, r"\*ELEMENT_SOLID part", "9-16"),
    (b"*SET_NODE_LIST_TITLE", 1, 55, "node set", "51-60"),
])
def test_a_letter_in_a_number_names_the_line(tmp_path, model_k, block, card, column, what, columns):
    lines = _lines(model_k)
    head = _line_no(lines, block)
    row = head + 2 + card if block != b"*SET_NODE_LIST_TITLE" else head + 4 + card
    path = _bad(tmp_path, lines, row, lines[row][:column] + b"x" + lines[row][column + 1 :])
    kind = "a number" if "coordinate" in what else "an integer"
    with pytest.raises(DicerError, match=rf"bad\.k: line {row + 1}: {what}: '.*x.*' in columns {columns} is not "
                                         rf"{kind}"):
        read_lsdyna(path)


def test_a_card_one_column_short_names_the_line(tmp_path, model_k):
    lines = _lines(model_k)
    node, element = _line_no(lines, b"*NODE") + 2 + 9, _line_no(lines, b"*ELEMENT_SOLID") + 2 + 9
    with pytest.raises(DicerError, match=rf"bad\.k: line {node + 1}: \*NODE card has 55 columns, expected 56"):
        read_lsdyna(_bad(tmp_path, lines, node, lines[node][1:]))
    with pytest.raises(DicerError, match=rf"bad\.k: line {element + 1}: \*ELEMENT_SOLID card has 79 columns, "
                                         r"expected 80"):
        read_lsdyna(_bad(tmp_path, lines, element, lines[element][1:]))
    nset = _line_no(lines, b"*SET_NODE_LIST_TITLE") + 4  # the first data card of the first set, a full one
    assert len(lines[nset]) == 81 and lines[nset + 1][:1] != b"*"
    with pytest.raises(DicerError, match=rf"bad\.k: line {nset + 1}: node set \w+: cards must be whole "
                                         r"10-column fields"):
        read_lsdyna(_bad(tmp_path, lines, nset, lines[nset][1:]))
    with pytest.raises(DicerError, match=rf"bad\.k: line {nset + 1}: node set \w+: only the last card may be short"):
        read_lsdyna(_bad(tmp_path, lines, nset, lines[nset][10:]))
    with pytest.raises(DicerError, match=rf"bad\.k: line {nset + 1}: node set \w+: a card of more than 80 columns"):
        read_lsdyna(_bad(tmp_path, lines, nset, lines[nset][:10] + lines[nset]))


def test_a_wrong_id_names_the_line(tmp_path, model_k):
    lines = _lines(model_k)
    node = _line_no(lines, b"*NODE") + 2 + 6  # node 7
    with pytest.raises(DicerError, match=rf"bad\.k: line {node + 1}: \*NODE ids must run 1\.\.N in order "
                                         r"\(id 99 on card 7\)"):
        read_lsdyna(_bad(tmp_path, lines, node, b"      99" + lines[node][8:]))
    element = _line_no(lines, b"*ELEMENT_SOLID") + 2 + 4  # element 5
    with pytest.raises(DicerError, match=rf"bad\.k: line {element + 1}: \*ELEMENT_SOLID ids must run 1\.\.M in "
                                         r"order \(id 4 on card 5\)"):
        read_lsdyna(_bad(tmp_path, lines, element, b"       4" + lines[element][8:]))


def test_an_element_on_a_missing_node_names_the_line(tmp_path, model_k):
    lines = _lines(model_k)
    n_nodes = _read_lsdyna(model_k)["points"].shape[0]
    element = _line_no(lines, b"*ELEMENT_SOLID") + 2 + 8  # element 9
    for node in (n_nodes + 1, 0):
        path = _bad(tmp_path, lines, element, lines[element][:40] + f"{node:8d}".encode() + lines[element][48:])
        with pytest.raises(DicerError, match=rf"bad\.k: line {element + 1}: elements refer to nodes that do not "
                                             rf"exist \(element 9; the file has {n_nodes} nodes\)"):
            read_lsdyna(path)


# --- the fixed-column layout ------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(ints=st.lists(st.integers(0, 10**8 - 4), min_size=3, max_size=3),
       reals=st.lists(st.floats(-1e30, 1e30, allow_nan=False), min_size=2, max_size=2))
def test_layout_of_columns_parses_as_each_column_alone(ints, reals):
    from dicer.export.textfmt import Float, Int, format_rows

    n = 3
    values_i = np.array([ints] * n, np.int64) + np.arange(n)[:, None]
    values_f = np.array([reals] * n) * (1 + np.arange(n))[:, None]
    fields = [Int(values_i[:, 0], 8), Float(values_f[:, 0], lsdyna.E16), Int(values_i[:, 1], 9),
              Float(values_f[:, 1], lsdyna.E16), Int(values_i[:, 2], 10), b"\n"]
    buf = np.concatenate([b.ravel() for b in format_rows(fields, n)])
    widths = (8, 16, 9, 16, 10)
    layout = layout_of_columns(buf[:60].tobytes(), widths)
    assert layout.kinds == "ififi" and layout.length == 60
    got_i, got_f = parse_records(buf, layout)
    rows = buf.reshape(n, 60)
    edges = np.cumsum((0,) + widths)
    cols = [parse_column(rows[:, edges[j] : edges[j + 1]]) for j in range(5)]
    assert got_i.dtype == np.int64 and np.array_equal(got_i, np.column_stack([cols[0], cols[2], cols[4]]))
    assert np.array_equal(got_f.view(np.int64), np.column_stack([cols[1], cols[3]]).view(np.int64))


def test_layout_of_columns_refuses_what_does_not_fill_its_columns():
    with pytest.raises(FormatError, match="is not one number filling columns 9-16"):
        layout_of_columns(b"       1     1,2\n", (8, 8))
    with pytest.raises(FormatError, match="neither an integer") as exc:
        layout_of_columns(b"       1  12    \n", (8, 8))  # left-aligned
    assert exc.value.offset == 8
    with pytest.raises(FormatError, match="a record of 16 bytes where 17 belong"):
        layout_of_columns(b"       1       1", (8, 8))
