"""The cohort sheet: rows read with their line numbers, and every way a sheet goes wrong
named by its line before a job runs (dicer.sheet; the workflow's dry runs in hostile.py)."""

from pathlib import Path

import pytest
import yaml

from dicer.errors import DicerError
from dicer.sheet import beside_sheet, read_sheet

SCHEMA = yaml.safe_load((Path(__file__).resolve().parents[1] / "workflow" / "schemas" / "patients.schema.yaml")
                        .read_text())
HEAD = "patient\timage\toverrides\n"


def _read(tmp_path, text: str | bytes):
    sheet = tmp_path / "patients.tsv"
    sheet.write_bytes(text if isinstance(text, bytes) else text.encode())
    return read_sheet(sheet, SCHEMA)


def test_rows_keep_their_line_numbers_across_blank_rows(tmp_path):
    rows = _read(tmp_path, HEAD + "A\ta.nii.gz\t\n\n\t\t\nB\tb.nii.gz\tfix.type_c=false; downsample.factor=2\n")
    assert [(n, r["patient"]) for n, r in rows] == [(2, "A"), (5, "B")]
    assert rows[1][1] == {"patient": "B", "image": "b.nii.gz", "overrides": "fix.type_c=false; downsample.factor=2"}
    # spreadsheet exports: a byte-order mark, CRLF, quoted cells with doubled quotes, short rows
    rows = _read(tmp_path, b"\xef\xbb\xbfpatient\timage\toverrides\r\n\"A\"\t\"my \"\"scan\"\".nii.gz\"\r\nB\tb.nii.gz\r\n")
    assert [r for _, r in rows] == [{"patient": "A", "image": 'my "scan".nii.gz', "overrides": ""},
                                    {"patient": "B", "image": "b.nii.gz", "overrides": ""}]


@pytest.mark.parametrize("text, said", [
    # an unclosed quote swallowed the rows after it: B and C vanished without a word
    (HEAD + 'A\t"a.nii.gz\t\nB\tb.nii.gz\t\nC\tc.nii.gz\t\n',
     r"line 2: a quote \(\"\) opens a cell that no quote on that line closes"),
    (HEAD + "A\ta.nii.gz\t\n" + 'B\tb.nii.gz\t"fix.type_c=false\n' + "C\tc.nii.gz\t\n" * 3000,
     r"line 3: a quote"),  # past csv's field limit
    # cells past the last column were dropped: an override lost
    ("patient\timage\tlabels\nA\t\ta.nii.gz\tdownsample.factor=2\n", r"line 2: 4 cells where the header names 3"),
    (HEAD + "A\ta.nii.gz\tfix.type_c=false\tdownsample.factor=2\n", r"line 2: 4 cells where the header names 3"),
    # the workflow's settings per patient were checked, then ignored
    (HEAD + "A\ta.nii.gz\tworkflow.exports=[inp,feb]\n",
     r"line 2: patient 'A': override 'workflow.exports': the workflow settings are the whole cohort's"),
    # overrides glued with a comma: the second became part of the first's value ("2,segment.keep=largest")
    (HEAD + "A\ta.nii.gz\tdownsample.factor=2,segment.keep=largest\n",
     r"line 2: patient 'A': overrides are separated by ';', not ',' \(before 'segment.keep'\); write KEY=VALUE;KEY=VALUE"),
    (HEAD + "A\ta.nii.gz\tdownsample.factor=2,smooth={pillow: true}\n",
     r"line 2: patient 'A': overrides are separated by ';', not ',' \(before 'smooth'\)"),
    (HEAD + "A\ta.nii.gz\tdownsample.factor=2,segmnt.keep=1\n",
     r"line 2: patient 'A': overrides are separated by ';', not ',' \(before 'segmnt.keep'\)"),
    (HEAD + "A\ta.nii.gz\tlabels.map={1: x, y=2},smooth.pillow=true\n",
     r"line 2: patient 'A': overrides are separated by ';', not ',' \(before 'smooth.pillow'\)"),
    (HEAD + "A\ta.nii.gz\tdownsample.factor=2;downsample.factor=1\n",
     r"line 2: patient 'A': override 'downsample.factor' is given twice"),
    # a section and one of its keys, spelled differently: the key's value won unsaid
    (HEAD + "A\ta.nii.gz\tdownsample={factor: 2};downsample.factor=3\n",
     r"line 2: patient 'A': override 'downsample' and 'downsample.factor' both set downsample.factor; keep one"),
    (HEAD + "A\ta.nii.gz\tsmooth.coefficients.A=0.5;smooth.coefficients={A: 0.8, B: 0.8}\n",
     r"override 'smooth.coefficients' and 'smooth.coefficients.A' both set smooth.coefficients.A"),
    # the workflow's own names: Snakemake's ChildIOException, or a failure after every stage ran
    (HEAD + "cohort.html\ta.nii.gz\t\n", r"line 2: patient code 'cohort.html' is a name the workflow gives its own"),
    (HEAD + "Phantoms\ta.nii.gz\t\n", r"line 2: patient code 'Phantoms' is a name"),
    (HEAD + "cohort.log\ta.nii.gz\t\n", r"line 2: patient code 'cohort.log'"),
    (HEAD + "P1\ta.nii.gz\t\n\np1\tb.nii.gz\t\n",
     r"line 4: patient 'p1' and 'P1' \(line 2\) differ only in case"),
    (HEAD + "P1\ta.nii.gz\t\nP1\tb.nii.gz\t\n", r"line 3: patient 'P1' appears twice"),
    ("", r"the sheet is empty; write a header line"),
    (HEAD, r"the sheet lists no patient"),
    ("patient\tlabels\tlabels\nA\ta\tb\n", r"line 1: column 'labels' appears twice in the header"),
    ("patient\tscan\nA\ta.nii.gz\n", r"line 1: unknown column 'scan'"),
    ("patient,image,overrides\nA,a.nii.gz,\n",
     r"line 1: unknown column 'patient,image,overrides' \(the sheet's columns are separated by tabs, not commas\)"),
    (HEAD + "A/B\ta.nii.gz\t\n", r"line 2: column 'patient': 'A/B' is not a patient code: use letters, digits"),
    (HEAD + "P1\u200b\ta.nii.gz\t\n", r"line 2: column 'patient': 'P1.*' is not a patient code: .* invisible"),
    (HEAD + "A\t\t\n", r"line 2: patient 'A': give either an image or a labels file"),
    # overrides no stage of the patient reads were accepted and changed nothing
    (HEAD + "A\ta.nii.gz\tlabels.drop=[2]\n",
     r"line 2: patient 'A': override 'labels.drop' is read only for a label volume .* would change nothing"),
    ("patient\timage\tlabels\toverrides\nA\t\tl.nii.gz\tsegment.thresholds=[0, 300]\n",
     r"line 2: patient 'A': override 'segment.thresholds' sets the threshold search, which this row's label"),
    ("patient\timage\tlabels\toverrides\nA\t\tl.nii.gz\tsmooth.surface_from_image=true\n",
     r"line 2: patient 'A': override 'smooth.surface_from_image' acts on the scan .* label volume has none"),
    ("patient\timage\tlabels\toverrides\nA\t\tl.nii.gz\tsmooth.fit_to_scan=true\n",
     r"line 2: patient 'A': override 'smooth.fit_to_scan' acts on the scan .* label volume has none"),
    # a section given whole: its keys checked alike
    ("patient\timage\tlabels\toverrides\nA\t\tl.nii.gz\tsmooth={pillow: true, fit_to_scan: false}\n",
     r"line 2: patient 'A': override 'smooth' sets 'smooth.fit_to_scan', which acts on the scan .* label volume "
     r"has none, so it would change nothing: remove it"),
    ("patient\timage\tlabels\toverrides\nA\t\tl.nii.gz\tsegment={morphology: false, thresholds: [0, 300]}\n",
     r"line 2: patient 'A': override 'segment' sets 'segment.thresholds', which sets the threshold search"),
])
def test_bad_sheets_are_refused_naming_the_line(tmp_path, text, said):
    with pytest.raises(DicerError, match=said):
        _read(tmp_path, text)


def test_a_section_and_a_key_it_does_not_set_are_both_taken(tmp_path):
    text = HEAD + "A\ta.nii.gz\tsmooth={coefficient: 0.8};smooth.pillow=true;smooth.coefficients.A=0.5\n"
    assert _read(tmp_path, text)[0][1]["overrides"].count("=") == 3


def test_a_sheet_that_is_a_folder_or_missing(tmp_path):
    with pytest.raises(DicerError, match="is a folder; set workflow.patients to the cohort sheet"):
        read_sheet(tmp_path, SCHEMA)
    with pytest.raises(DicerError, match="cohort sheet not found"):
        read_sheet(tmp_path / "none.tsv", SCHEMA)


def test_paths_are_the_working_folders_and_the_sheets_folder_is_named_when_it_differs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "study" / "scans").mkdir(parents=True)
    (tmp_path / "study" / "scans" / "P1.nii.gz").write_bytes(b"beside")
    sheet = Path("study") / "patients.tsv"
    assert beside_sheet("scans/P1.nii.gz", sheet) == Path("study/scans/P1.nii.gz")  # not found here: a hint
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "P1.nii.gz").write_bytes(b"here")
    assert beside_sheet("scans/P1.nii.gz", sheet) == Path("study/scans/P1.nii.gz")  # another file: a warning
    assert beside_sheet("scans/P1.nii.gz", "patients.tsv") is None  # the sheet in the working folder
    assert beside_sheet(str(tmp_path / "scans" / "P1.nii.gz"), sheet) is None
    assert beside_sheet("scans/P2.nii.gz", sheet) is None


def test_a_scans_files_are_its_own_and_its_headers_data_file(tmp_path):
    """The workflow watched every file whose name shares the scan's stem: another scan or a note
    beside it (ct.v2.nii.gz, ct.v1.notes.txt) re-ran the patient's whole chain."""
    from dicer.sheet import scan_files

    for name in ("ct.v1.nii.gz", "ct.v2.nii.gz", "ct.v1.notes.txt", "head.mhd", "head.raw", "head.zraw", "knee.nhdr",
                 "knee_voxels.raw.gz", "knee.raw", "old.hdr", "old.img", "one.mha"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "head.mhd").write_text("NDims = 3\nElementType = MET_SHORT\nElementDataFile = head.raw\n")
    (tmp_path / "knee.nhdr").write_text("NRRD0004\ntype: short\ndata file: knee_voxels.raw.gz\n")
    (tmp_path / "one.mha").write_text("NDims = 3\nElementDataFile = LOCAL\n")
    names = lambda path: [f.name for f in scan_files(tmp_path / path)]  # noqa: E731
    assert names("ct.v1.nii.gz") == ["ct.v1.nii.gz"]
    assert names("head.mhd") == ["head.mhd", "head.raw"]
    assert names("knee.nhdr") == ["knee.nhdr", "knee_voxels.raw.gz"]
    assert names("old.hdr") == ["old.hdr", "old.img"]
    assert names("one.mha") == ["one.mha"]
    (tmp_path / "dicom").mkdir()
    for i in (2, 1):
        (tmp_path / "dicom" / f"{i}.dcm").write_bytes(b"x")
    assert names("dicom") == ["1.dcm", "2.dcm"]
    assert names("missing.nii.gz") == []
    # a data file named with a space, or by its absolute path elsewhere
    (tmp_path / "my scan.raw").write_bytes(b"x")
    (tmp_path / "head.mhd").write_text("NDims = 3\nElementDataFile = my scan.raw\n")
    assert names("head.mhd") == ["head.mhd", "my scan.raw"]
    (tmp_path / "far").mkdir()
    (tmp_path / "far" / "v.raw").write_bytes(b"x")
    (tmp_path / "knee.nhdr").write_text(f"NRRD0004\ndata file: {tmp_path / 'far' / 'v.raw'}\n")
    assert scan_files(tmp_path / "knee.nhdr") == [tmp_path / "far" / "v.raw", tmp_path / "knee.nhdr"]
    (tmp_path / "head.mhd").write_bytes(b"NDims = 3\r\nElementDataFile = head.raw\r\n")  # Windows line ends
    assert names("head.mhd") == ["head.mhd", "head.raw"]



@pytest.mark.parametrize("label_volume,sets,unread", [
    # a label volume at factor 1 is not downsampled: its morphology, vote and their order unread
    (True, ["segment.keep=largest", "downsample.min_fraction=0.6", "segment.priority=[bone]"],
     ["segment.keep", "downsample.min_fraction", "segment.priority"]),
    (True, ["downsample.factor=2", "segment.keep=largest", "segment.priority=[bone]"], ["segment.keep"]),
    (True, ["downsample.factor=2", "downsample.morphology=true", "segment.keep=largest"], []),
    (True, ["downsample={min_fraction: 0.6, factor: 1}"], ["downsample.min_fraction"]),
    # a scan at factor 1: the downsample stage changes nothing; the segment stage reads segment
    (False, ["downsample.min_fraction=0.6", "segment.keep=largest"], ["downsample.min_fraction"]),
    (False, ["downsample.voxel_size=2", "downsample.min_fraction=0.6"], []),
])
def test_settings_no_stage_reads_are_found(label_volume, sets, unread):
    """A floating part 'dropped' by segment.keep=largest on a label volume's row stayed in the
    model, and the override was accepted without a word (dicer run --labels too)."""
    from dicer.config import for_label_volume, load_config, parse_set
    from dicer.sheet import unread_settings

    config = {}
    for item in sets:
        config = {**config, **{k: {**config.get(k, {}), **v} for k, v in parse_set(item).items()}}
    loaded = load_config(settings=config)
    found = unread_settings(sets, for_label_volume(loaded) if label_volume else loaded, label_volume)
    assert [key for key, _ in found] == unread
    assert all("downsample" in why for _, why in found)  # names what would make it read


@pytest.mark.parametrize("sets, unread, said", [
    (["downsample.voxel_size=2", "downsample.factor=3"], ["downsample.factor"], "replaced by downsample.voxel_size"),
    (["smooth.coefficient=0.8", "smooth.coefficients={A: 0.3}"], ["smooth.coefficients.A"], "replaced by smooth.coefficient"),
    (["smooth.pillow=false", "smooth.pillow_thickness=0.4"], ["smooth.pillow_thickness"], "smooth.pillow is off"),
    (["merge.templates={levels: 1}"], ["merge.templates.levels"], "merge.method is planes"),
    (["merge.method=templates", "merge.passes=[0, 0, 0]"], ["merge.passes"], "merge.method is templates"),
    (["segment.thresholds=[-500, 100]"], ["segment.thresholds"], "segment.method is shape_connectivity"),
    (["segment.method=manual", "segment.ranges=[[-300, 0], [200, 900]]"], ["segment.ranges"], "segment.method is manual"),
    (["export.midside_nodes=curved"], ["export.midside_nodes"], "export.order is 1"),
    (["export.febio_material=neo-Hookean"], ["export.febio_material"], "workflow.exports names no feb"),
    (["smooth.pillow=true", "smooth.pillow_thickness=0.4", "export.order=2", "export.midside_nodes=curved",
      "segment.method=manual", "segment.thresholds=[-500, 100]"], [], ""),
])
def test_settings_another_setting_turns_off_are_found(sets, unread, said):
    """A patient's downsample.factor under the cohort's voxel_size, merge.passes under
    templates, curved mid-edge nodes at order 1 ... changed nothing, accepted without a word."""
    from dicer.config import deep_merge, load_config, parse_set
    from dicer.sheet import unread_settings

    config = {}
    for item in sets:
        config = deep_merge(config, parse_set(item))
    found = unread_settings(sets, load_config(settings=config), False)
    assert [key for key, _ in found] == unread
    assert all(said in why for _, why in found)


def test_priorities_naming_no_material_are_found_before_any_stage():
    """A patient's fix.priority=[metal] stopped the run at its fix stage, its segment and
    downsample stages done, naming a results file and not the sheet's line."""
    from dicer.config import load_config
    from dicer.sheet import unknown_priorities

    assert unknown_priorities(load_config()) is None
    assert unknown_priorities(load_config(settings={"fix": {"priority": ["metal", "bone"]}})) == (
        "fix.priority names 'metal', which the materials do not hold (they are soft_tissue, bone); list material names")
    assert unknown_priorities(load_config(settings={"segment": {"priority": ["Bone"]}})).startswith(
        "segment.priority names 'Bone'")
