import itertools
import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dicer.config import (
    config_hash,
    default_config,
    load_config,
    name_clash,
    parse_set,
    stage_settings,
    validate,
)
from dicer.errors import DicerError


def test_defaults_are_valid_and_complete():
    config = load_config()
    assert config == default_config()
    assert [m["name"] for m in config["materials"]] == ["soft_tissue", "bone"]
    assert config["segment"]["thresholds"] == [-140.0, 226.0]
    assert config["export"]["order"] == 1
    validate(config)


def test_file_then_settings_then_set(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("segment:\n  opening_radius: 3\nexport:\n  thickness: 2.5\n")
    config = load_config(path, sets=["segment.opening_radius=2"], settings={"export": {"thickness": 4.0}})
    assert config["segment"]["opening_radius"] == 2
    assert config["export"]["thickness"] == 4.0
    assert config["segment"]["closing_radius"] == 1  # default kept


def test_material_defaults_filled_per_item():
    config = load_config(sets=["materials=[{name: a}, {name: b, youngs_modulus: 5}]"])
    assert config["materials"][0]["youngs_modulus"] == 1000.0
    assert config["materials"][1]["youngs_modulus"] == 5
    assert config["materials"][1]["poissons_ratio"] == 0.3


@pytest.mark.parametrize(
    "item, words",
    [
        ("segment.foo=1", ["unknown key 'segment.foo'", "opening_radius"]),
        ("nonsense=1", ["unknown key 'nonsense'"]),
        ("segment.opening_radius=abc", ["segment.opening_radius", "integer"]),
        ("export.order=7", ["export.order"]),
        ("materials=[{name: a}, {name: a}]", ["unique", "a repeat"]),
        ("materials=[{name: Bone}, {name: bone}]", ["Bone and bone", "upper case"]),
        ("materials=[{name: a}, {name: a_b}, {name: b_c}, {name: c}]", ["a and b_c", "a_b and c", "a_b_c"]),
        ("materials=[{name: a}, {name: BOUNDARY}]", ["a_BOUNDARY"]),
        ("materials=[{name: Exterior_S2}]", ["Exterior_S2", "exterior face set"]),
        # its element set beside the surface EXTERIOR: CalculiX put a *DSLOAD EXTERIOR on nothing
        ("materials=[{name: exterior}]", ["exterior", "exterior face set"]),
        ("materials.0=1", ["materials"]),
        ("smooth.pillow_thickness=0.01", ["smooth.pillow_thickness", "0.05"]),
        # label 0's name: a material called so was meshed, stiff, under a name saying it was not there
        ("labels.map={2: wm, 24: background}", ["labels.map", "value 24 is named 'background'", "labels.drop: [24]"]),
        ("materials=[{name: Background}]", ["the name Background is label 0's", "rename"]),
        # clashes among labels.map's names blamed the label volume and key 'materials', at the labels stage
        ("labels.map={1: Bone, 2: bone, 3: marrow}", ["key 'labels.map'", "Bone and bone", "upper case"]),
        ("labels.map={1: a_b, 2: c, 3: a, 4: b_c}", ["key 'labels.map'", "a_b_c"]),
        ("labels.map={4: EXTERIOR}", ["key 'labels.map'", "exterior face set"]),
        ("quality.stretched_edge_ratio=0.5", ["quality.stretched_edge_ratio", "1"]),
    ],
)
def test_bad_keys_and_types_name_the_key(item, words):
    with pytest.raises(DicerError) as info:
        load_config(sets=[item])
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert word in message


def test_bad_config_file(tmp_path):
    with pytest.raises(DicerError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("segment: [unclosed\n")
    with pytest.raises(DicerError, match="not valid YAML"):
        load_config(bad)
    listy = tmp_path / "list.yaml"
    listy.write_text("- 1\n- 2\n")
    with pytest.raises(DicerError, match="mapping"):
        load_config(listy)


def test_parse_set_forms():
    assert parse_set("merge.passes=[1,1,1]") == {"merge": {"passes": [1, 1, 1]}}
    assert parse_set("smooth.coefficient=0.8") == {"smooth": {"coefficient": 0.8}}
    assert parse_set("segment.method=otsu") == {"segment": {"method": "otsu"}}
    for bad in ("novalue", "a..b=1", "=3"):
        with pytest.raises(DicerError):
            parse_set(bad)


@given(st.lists(st.sampled_from("abcxyz"), min_size=1, max_size=4), st.integers(-10**6, 10**6))
def test_parse_set_nests_dotted_keys(parts, value):
    out = parse_set(".".join(parts) + f"={value}")
    node = out
    for part in parts[:-1]:
        assert list(node) == [part]
        node = node[part]
    assert node == {parts[-1]: value}


def test_stage_settings_only_hold_their_sections():
    config = load_config()
    assert set(stage_settings(config, "export")) == {"materials", "export"}
    assert set(stage_settings(config, "mesh")) == {"materials", "mesh", "image"}  # names go into the mesh
    assert set(stage_settings(config, "mesh")["image"]) == {"spacing"}  # of a .npy volume
    assert set(stage_settings(config, "quality")) == {"materials", "quality", "image", "export"}  # the report names them
    # a 2D deck's plane stress or strain, and the order the element type is checked against
    assert set(stage_settings(config, "quality")["export"]) == {"order", "element_type"}
    changed = load_config(sets=["export.thickness=3"])
    assert stage_settings(changed, "segment") == stage_settings(config, "segment")
    assert stage_settings(changed, "export") != stage_settings(config, "export")
    # smooth reads the scan as segment read it: a crop changes its settings, not mesh's (the
    # workflow's smooth rule lined the uncropped scan up with the cropped mesh)
    cropped = load_config(sets=["image.crop={unit: voxels, min: [1, 1, 1], max: [9, 9, 9]}"])
    assert stage_settings(cropped, "smooth")["image"]["crop"]["min"] == [1, 1, 1]
    assert set(stage_settings(cropped, "smooth")["segment"]) == {"method", "thresholds"}
    assert stage_settings(cropped, "mesh") == stage_settings(config, "mesh")
    # the stages that read only the names do not change with a material's properties; the
    # exports and the quality report (its explicit time step) do
    stiffer = load_config(sets=["materials=[{name: soft_tissue}, {name: bone, youngs_modulus: 12000}]"])
    for stage in ("segment", "labels", "downsample", "fix", "mesh"):
        assert stage_settings(stiffer, stage) == stage_settings(config, stage)
    for stage in ("export", "quality"):
        assert stage_settings(stiffer, stage) != stage_settings(config, stage)


@pytest.mark.parametrize("sets", [["export.order=2", "export.element_type=C3D20R"],
                                  ["export.order=2", "export.element_type=CPS8"],
                                  ["export.element_type=CPE4"]])
def test_every_stage_takes_its_own_settings(sets):
    """What the workflow passes a rule (--settings, the stage's sections and keys) is a
    configuration the stage accepts: the quality rule had the element type without the order,
    and refused C3D20R as order 1 for every patient."""
    config = load_config(sets=sets)
    for stage in ("segment", "labels", "downsample", "fix", "mesh", "merge", "smooth", "export", "quality"):
        assert stage_settings(load_config(settings=stage_settings(config, stage)), stage) == \
            stage_settings(config, stage), stage


def test_the_shipped_config_writes_every_key_at_its_default():
    """config/config.yaml documents every key of the schema with its default (README), but
    workflow.skip_missing, which the demo cohort turns on; workflow.phantom_size was missing."""
    from pathlib import Path

    import yaml

    from dicer.config import default_config, schema

    shipped = yaml.safe_load((Path(__file__).parents[1] / "config" / "config.yaml").read_text(encoding="utf-8"))
    missing, differ = [], []

    def walk(node: dict, given: dict, default: dict, path: str) -> None:
        for key, sub in node.get("properties", {}).items():
            name = f"{path}{key}"
            if key not in given:
                missing.append(name)
            elif sub.get("type") == "object" and "properties" in sub and isinstance(given[key], dict):
                walk(sub, given[key], default[key], name + ".")
            elif given[key] != default[key]:
                differ.append(name)

    walk(schema(), shipped, default_config(), "")
    assert missing == [] and differ == ["workflow.skip_missing"]


def test_config_hash_is_stable_and_sensitive():
    a, b = load_config(), load_config()
    assert config_hash(a) == config_hash(b)
    assert len(config_hash(a)) == 16
    assert config_hash(a) != config_hash(load_config(sets=["export.thickness=3"]))
    # a number spelled 1 or 1.0 is one setting (the deck's heading was other bytes)
    assert config_hash(a) == config_hash(load_config(sets=["export.thickness=1"]))
    assert config_hash(load_config(sets=["materials=[{name: a, youngs_modulus: 1}]"])) == \
        config_hash(load_config(sets=["materials=[{name: a, youngs_modulus: 1.0}]"]))
    assert config_hash({"x": [1.5, True, 2.0]}) != config_hash({"x": [1.5, True, 2.5]})


def _set_names(names: list[str], sets) -> tuple[list[str], list[str]]:
    """The element set and node set names of an export of the materials, upper case."""
    upper = [n.upper() for n in names]
    elements = upper + ([f"EXTERIOR_S{s}" for s in range(1, 7)] if "exterior" in sets else [])
    nodes = ["X0", "X1", "Y0", "Y1", "Z0", "Z1", "EXTERIOR"]
    if "materials" in sets:
        nodes += [f"{a}_BOUNDARY" for a in upper]
    if "interfaces" in sets:
        nodes += [f"{a}_{b}" for a, b in itertools.combinations(upper, 2)]
    return elements, nodes


_WORDS = ["a", "b", "c", "a_b", "b_c", "a_b_c", "c_a", "BOUNDARY", "b_BOUNDARY", "A", "x_y", "y", "x", "Exterior_S3"]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from(_WORDS), min_size=1, max_size=6, unique=True),
       st.sets(st.sampled_from(["materials", "interfaces", "exterior"])))
def test_name_clash_finds_exactly_the_repeated_set_names(names, sets):
    # a clash is reported exactly when two of the export's set names are equal
    distinct = all(len(set(group)) == len(group) for group in _set_names(names, sets))
    assert (name_clash(names, sets) is None) == distinct


def test_many_material_names_without_a_clash_are_quick():
    # 5000 names sharing prefixes and underscores, as atlas names do
    names = [f"{side}_{part}_{i}" for i in range(2500) for side, part in (("Left", "Gyrus"), ("Right", "Gyrus"))]
    assert name_clash(names) is None
    assert "Left_Gyrus_7" in name_clash(names + ["Left", "Gyrus_7_Right_Gyrus_7"])
    config = load_config(settings={"materials": [{"name": n} for n in names]})
    assert len(config["materials"]) == 5000


def test_yaml_keys_given_twice_are_an_error(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("smooth:\n  coefficient: 0.8\nsmooth:\n  tolerance: 0.001\n")
    with pytest.raises(DicerError, match=r"key 'smooth' is given twice \(lines 1 and 3\)"):
        load_config(path)
    with pytest.raises(DicerError, match="key 'a' is given twice"):
        load_config(sets=["smooth.coefficients={a: 1, a: 2}"])


def test_exponent_floats_without_a_dot_are_numbers(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("\ufeffsmooth:\n  tolerance: 1e-5\n")  # a byte-order mark is fine too
    assert load_config(path)["smooth"]["tolerance"] == 1e-5
    assert load_config(sets=["smooth.tolerance=2E-4"])["smooth"]["tolerance"] == 2e-4
    assert load_config(sets=["segment.method=otsu"])["segment"]["method"] == "otsu"


def test_the_workflow_reads_its_config_as_dicer_does(tmp_path):
    """Snakemake reads its config as YAML 1.1, where 1e-9 is a string ('1e-9' is not of type
    'number'), 041 octal 33 (a labels.map key went to another label) and a key given twice
    keeps its last; its --config items' nested values come as text."""
    import yaml

    from dicer.config import workflow_config

    text = ("materials:\n  - {name: bone, density: 1e-9, youngs_modulus: 2E+4}\nsmooth:\n  tolerance: 1e-5\n"
            "workflow:\n  results: out1e5\nlabels:\n  map: {041: bone, 010: bone}\n")
    (tmp_path / "a.yaml").write_text(text)
    parsed = yaml.safe_load(text)
    assert parsed["materials"][0]["density"] == "1e-9" and set(parsed["labels"]["map"]) == {33, 8}  # YAML 1.1
    read = workflow_config([tmp_path / "a.yaml"], {})
    assert read["materials"][0] == {"name": "bone", "density": 1e-9, "youngs_modulus": 2e4}
    assert read["smooth"]["tolerance"] == 1e-5 and read["workflow"]["results"] == "out1e5"
    assert set(read["labels"]["map"]) == {41, 10}
    assert load_config(settings=read)["materials"][0]["density"] == 1e-9
    # later files and then the items win; the items' texts read as --set reads a value
    (tmp_path / "b.yaml").write_text("smooth:\n  tolerance: 2e-5\n  pillow: true\n")
    items = {"smooth": {"coefficient": "0.5", "pillow": "false"}, "segment": {"method": "otsu", "keep": "[1, 2]"}}
    read = workflow_config([tmp_path / "a.yaml", tmp_path / "b.yaml"], items)
    assert read["smooth"] == {"tolerance": 2e-5, "pillow": False, "coefficient": 0.5}
    assert read["segment"] == {"method": "otsu", "keep": "[1, 2]"}  # structure is Snakemake's to parse
    (tmp_path / "c.yaml").write_text("smooth:\n  coefficient: 0.6\nsmooth:\n  pillow: true\n")
    with pytest.raises(DicerError, match=r"c.yaml: key 'smooth' is given twice \(lines 1 and 3\)"):
        workflow_config([tmp_path / "c.yaml"], {})
    # a text where the schema takes text stays as given (Snakemake took the quotes off): a results
    # folder "041", "out #1" or a date; a labels.map key of digits is a label, as --set reads it
    items = {"workflow": {"results": "041", "exports": ["inp", "exo"]}, "labels": {"map": {"041": "bone"}},
             "materials": [{"name": "yes", "density": "1e-9"}]}
    read = workflow_config([], items)
    assert read["workflow"] == {"results": "041", "exports": ["inp", "exo"]}
    assert read["labels"]["map"] == {41: "bone"} and read["materials"] == [{"name": "yes", "density": 1e-9}]
    for folder in ("out #1", "2024-01-05", "null"):
        assert workflow_config([], {"workflow": {"results": folder}})["workflow"]["results"] == folder
    # a JSON file (Snakemake reads JSON first): tabs are JSON's, not YAML's
    (tmp_path / "d.json").write_text(json.dumps({"smooth": {"coefficient": 0.5}}, indent="\t"))
    assert workflow_config([tmp_path / "d.json"], {}) == {"smooth": {"coefficient": 0.5}}
    (tmp_path / "e.json").write_text('{"smooth": {"coefficient": 0.5}, "smooth": {"pillow": true}}')
    with pytest.raises(DicerError, match=r"e.json: key 'smooth' is given twice in one section"):
        workflow_config([tmp_path / "e.json"], {})


def test_a_date_like_value_is_text_and_a_validated_tree_is_not_mistaken_for_another():
    """YAML 1.1 read 2024-01-05 as a date, which the error message could not print (a traceback);
    and the schema's remembered passes keyed a tuple like a list, a key True like "true"."""
    assert load_config(sets=["workflow.results=2024-01-05"])["workflow"]["results"] == "2024-01-05"
    with pytest.raises(DicerError, match="smooth.coefficient"):
        load_config(sets=["smooth.coefficient=2024-01-05"])
    validate({"image": {"spacing": [1.0, 1.0, 1.0]}})
    with pytest.raises(DicerError, match="image.spacing"):
        validate({"image": {"spacing": (1.0, 1.0, 1.0)}})


def test_an_element_type_of_another_order_is_refused_when_the_config_is_read():
    """It was refused at export, after every stage before it had run (and in the workflow, after
    a patient's whole chain)."""
    with pytest.raises(DicerError, match=r"key 'export.element_type': C3D20R has order 2 and export.order is 1; "
                                         r"set export.order: 2, or an element type of order 1 \(C3D8, C3D8R, C3D8I\)"):
        load_config(sets=["export.element_type=C3D20R"])
    assert load_config(sets=["export.element_type=C3D20R", "export.order=2"])["export"]["order"] == 2
    with pytest.raises(DicerError, match="CPS8 has order 2 and export.order is 1"):
        load_config(settings={"export": {"element_type": "CPS8"}})



def test_dicer_export_order_is_named_as_given(tmp_path, capsys):
    """dicer export --order 2 beside a config's C3D8 was said to come from --set."""
    from dicer.cli import main

    (tmp_path / "c.yaml").write_text("export:\n  element_type: C3D8\n")
    assert main(["export", str(tmp_path / "none.vtu"), "-o", str(tmp_path / "o.inp"), "--config",
                 str(tmp_path / "c.yaml"), "--order", "2"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "c.yaml with --order: key 'export.element_type': C3D8 has order 1 and export.order is 2; set export.order: "
        "1, or an element type of order 2 (C3D20, C3D20R)")


def test_label_values_read_as_decimal_and_once(tmp_path):
    # YAML 1.1 reads 010 as octal 8: labels.map would name label 8 and leave 10 unnamed
    path = tmp_path / "c.yaml"
    path.write_text("labels:\n  map: {010: bone, 9: marrow, 0x1F: skin}\n  drop: [012]\n")
    config = load_config(path)
    assert config["labels"]["map"] == {"10": "bone", "9": "marrow", "31": "skin"}
    assert config["labels"]["drop"] == [12]
    # one label value written two ways is one key given twice
    path.write_text("labels:\n  map: {8: bone, '8': marrow}\n")
    with pytest.raises(DicerError, match="key '8' is given twice"):
        load_config(path)
    # a string key with a leading zero would name the same label as another: refused
    path.write_text("labels:\n  map: {'08': bone, 9: marrow}\n")
    with pytest.raises(DicerError, match=r"key 'labels.map': \"08\" is not a label value to mesh: give a whole "
                                         r"number from 1, without leading zeros \(8, not 08\); 0 is the background"):
        load_config(path)
    # a key that is no whole number was cut to one: 2.7 named label 2, yes label 1
    for key, text in (("2.7", "2.7"), ("yes", "True")):
        path.write_text(f"labels:\n  map: {{{key}: cortex}}\n")
        with pytest.raises(DicerError, match=rf"key 'labels.map': \"{text}\" is not a label value to mesh"):
            load_config(path)
    # an atlas's lookup table with several names no solver takes: all named in one error
    path.write_text("labels:\n  map: {2: Left-Cortex, 4: '3rd-Ventricle', 5: ok_name, 7: 'a b'}\n")
    with pytest.raises(DicerError, match=r"key 'labels.map': 3 names are not a name: give a letter, .* "
                                         r"\(2: 'Left-Cortex', 4: '3rd-Ventricle', 7: 'a b'\)$"):
        load_config(path)
    # value 0 is the background: a map entry for it was ignored without a word
    path.write_text("labels:\n  map: {0: air, 1: soft}\n")
    with pytest.raises(DicerError, match=r"\"0\" is not a label value to mesh: .* 0 is the background, never meshed$"):
        load_config(path)
    # --set still overrides the file's entry for a value (a string key over an integer one)
    path.write_text("labels:\n  map: {8: bone}\n")
    assert load_config(path, sets=["labels.map.8=marrow"])["labels"]["map"] == {"8": "marrow"}


@pytest.mark.parametrize("name", ["direction", "scanner_coordinates", "grid_shape"])
def test_material_names_of_mesh_grid_fields_are_refused(name):
    with pytest.raises(DicerError, match=f"the name {name} is taken by the grid data"):
        load_config(settings={"materials": [{"name": name}]})


def test_config_that_is_not_utf8_names_the_byte(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"materials:\n  - {name: b\xe9}\n")
    with pytest.raises(DicerError, match=r"c.yaml: not UTF-8 text \(byte 24, line 2\)"):
        load_config(path)


def test_range_errors_state_the_allowed_range():
    with pytest.raises(DicerError, match=r"'smooth.interior_band': -2 is out of range; give a whole number >= 0$"):
        load_config(sets=["smooth.interior_band=-2"])
    with pytest.raises(DicerError, match=r"'smooth.coefficient': 1.5 is not allowed; give null or a number >= 0 and < 1"):
        load_config(sets=["smooth.coefficient=1.5"])


@pytest.mark.parametrize("crop, said", [
    ("{unit: voxel, min: [0,0,0], max: [5,5,5]}", 'unit: "voxel" is not one of voxels, mm'),
    ("{min: [0,0,0], max: [5,5,5]}", "'unit' is a required property"),
    ("{unit: mm, min: [0,0,0], max: [5,5,5], size: 1}", "Additional properties are not allowed ('size' was unexpected)"),
    ("{unit: mm, min: [0,a,0], max: [5,5,5]}", "min.1: 'a' is not of type 'number'"),
    ("[0, 5]", "list is not allowed; give null or an object"),
])
def test_an_error_inside_a_mapping_of_two_kinds_names_what_is_wrong_in_it(crop, said):
    # every one of these read "dict is not allowed; give null or a object"
    with pytest.raises(DicerError, match=re.escape(f"key 'image.crop': {said}")):
        load_config(sets=[f"image.crop={crop}"])


@pytest.mark.parametrize("nu, ok", [(0.4999999, True), (0.49999999, False), (0.4999999999999, False),
                                    (-0.9999999, True), (-0.99999999, False), (0.45, True)])
def test_poissons_ratio_that_a_deck_prints_as_a_limit_is_refused(nu, ok):
    from dicer.export.abaqus import _num
    from dicer.export.lsdyna import _e10

    settings = {"materials": [{"name": "rubber", "poissons_ratio": nu}]}
    if ok:  # and every deck prints it inside the limits
        load_config(settings=settings)
        assert all(-1 < float(text) < 0.5 for text in (_num(nu), _e10(nu)))
    else:
        with pytest.raises(DicerError, match=r"'materials.0.poissons_ratio': .* at the 7 significant digits a "
                                             "solver deck holds"):
            load_config(settings=settings)


def test_a_list_item_set_by_its_number_says_how_to_set_the_list():
    with pytest.raises(DicerError, match=r"key 'materials': a list is set whole, not item by item: give all of it"):
        load_config(sets=["materials.0.name=x"])


def test_smooth_settings_the_others_leave_unused_are_said():
    """image_sigma without a scan's surface, pillow_thickness without the layer, the fit's settings
    without the fit: ignored without a word (the smoothed mesh byte for byte the defaults')."""
    from dicer.config import unused_smooth_settings

    assert unused_smooth_settings(load_config()["smooth"]) == []
    sets = ["smooth.image_sigma=1", "smooth.pillow=false", "smooth.pillow_thickness=0.5",
            "smooth.surface_from_labels=false", "smooth.label_surface_radius=8", "smooth.label_samples=relaxed"]
    assert unused_smooth_settings(load_config(sets=sets)["smooth"]) == [
        "smooth.image_sigma=1 is not used: it smooths the scan for smooth.surface_from_image or smooth.fit_to_scan, "
        "which these settings leave unused",
        "smooth.pillow_thickness=0.5 is not used: it is the thickness of the layer smooth.pillow adds, which is off",
        "smooth.label_samples=\"relaxed\" is not used: it shapes the fit of smooth.surface_from_labels, which is off",
        "smooth.label_surface_radius=8 is not used: it shapes the fit of smooth.surface_from_labels, which is off"]
    # used: said of nothing (image_sigma smooths the scan for fit_to_scan, pillow_thickness the
    # layer: both on by default)
    used = ["smooth.image_sigma=1", "smooth.pillow_thickness=0.5"]
    assert unused_smooth_settings(load_config(sets=used)["smooth"]) == []
    # a fit_to_scan turned off reads no scan: image_sigma unused; relaxed samples are placed by it
    assert unused_smooth_settings(load_config(sets=["smooth.image_sigma=1", "smooth.fit_to_scan=false"])["smooth"])[
        0].startswith("smooth.image_sigma=1 is not used")
    assert unused_smooth_settings(load_config(sets=["smooth.image_sigma=1", "smooth.label_samples=relaxed"])["smooth"]) \
        == []


def test_unused_smooth_settings_are_said_by_the_commands_that_smooth_only(tmp_path, caplog):
    from dicer.cli import main

    caplog.clear()
    assert main(["export", str(tmp_path / "none.vtu"), "-o", str(tmp_path / "m.inp"), "--set",
                 "smooth.pillow_thickness=0.5"]) == 2
    assert not [r for r in caplog.records if "is not used" in r.getMessage()]
    assert main(["smooth", str(tmp_path / "none.vtu"), "-o", str(tmp_path / "s.vtu"), "--set", "smooth.pillow=false",
                 "--set", "smooth.pillow_thickness=0.5"]) == 2
    assert [r.getMessage() for r in caplog.records if "is not used" in r.getMessage()] == [
        "smooth: smooth.pillow_thickness=0.5 is not used: it is the thickness of the layer smooth.pillow adds, which "
        "is off"]



def test_materials_listed_without_their_properties_are_said_by_the_commands_that_write_them(tmp_path, caplog):
    """Listed by name alone, soft tissue took E 1000 MPa from the schema (the default config's
    is 1 MPa) without a word; a property left out takes the schema's default, and is said."""
    from dicer.cli import main
    from dicer.config import load_config, materials_left_to_defaults

    given = {"materials": [{"name": "soft_tissue", "youngs_modulus": 2.0}, {"name": "bone"},
                           {"name": "marrow", "youngs_modulus": 50.0, "poissons_ratio": 0.4, "density": 1e-9}]}
    assert materials_left_to_defaults(given) == [("soft_tissue", ["poissons_ratio", "density"]),
                                                 ("bone", ["youngs_modulus", "poissons_ratio", "density"])]
    assert materials_left_to_defaults({}) == [] and materials_left_to_defaults({"materials": given["materials"][2:]}) == []
    config = load_config(settings=given)
    assert config["materials"][0] == {"name": "soft_tissue", "youngs_modulus": 2.0, "poissons_ratio": 0.3,
                                      "density": 1e-9}
    said = "properties left out of materials: soft_tissue (poissons_ratio, density), bone (youngs_modulus, "
    caplog.clear()
    load_config(settings=given)  # a stage that reads the names only: not said
    assert not [r for r in caplog.records if said in r.getMessage()]
    sets = ["--set", "materials=[{name: soft_tissue, youngs_modulus: 2.0}, {name: bone}]"]
    assert main(["export", str(tmp_path / "none.vtu"), "-o", str(tmp_path / "m.inp"), *sets]) == 2  # no mesh
    assert [r.getMessage() for r in caplog.records if said in r.getMessage()] == [
        "config with --set: properties left out of materials: soft_tissue (poissons_ratio, density), bone "
        "(youngs_modulus, poissons_ratio, density); they take the defaults (E 1000 MPa, nu 0.3, density 1e-09 "
        "t/mm^3), not the default config's soft_tissue and bone properties: give each listed material its "
        "youngs_modulus, poissons_ratio and density"]
    caplog.clear()  # the quality report too: its explicit time step takes the properties
    assert main(["quality", str(tmp_path / "none.vtu"), "-o", str(tmp_path / "q.json"), *sets]) == 2
    assert len([r for r in caplog.records if said in r.getMessage()]) == 1
    # the workflow's labels rule gives the names alone (its materials.json holds no properties):
    # its log said every label patient's materials took 1000 MPa
    import numpy as np

    from dicer.image import Volume
    from dicer.io.images import write_image

    write_image(Volume(np.pad(np.ones((4, 4, 4), np.uint8), 1), (1.0, 1.0, 1.0)), tmp_path / "seg.nii.gz")
    for listed, warned in (([{"name": "soft_tissue"}, {"name": "bone"}], False),
                           ([{"name": "soft_tissue", "youngs_modulus": 2.0}, {"name": "bone"}], True)):
        caplog.clear()
        assert main(["labels", str(tmp_path / "seg.nii.gz"), "-o", str(tmp_path / "l.nii.gz"), "--materials",
                     str(tmp_path / "m.json"), "--settings", json.dumps({"materials": listed})]) == 0
        assert any("properties left out of materials" in r.getMessage() for r in caplog.records) == warned


def test_a_preset_is_laid_under_the_users_own_keys(tmp_path):
    """``preset: static-stress`` gives the packaged settings over the defaults (the same as the
    repository's config/static-stress.yaml); the file's own keys, settings and --set items win."""
    from pathlib import Path

    from dicer.config import preset_settings

    packaged = preset_settings("static-stress")
    assert packaged == {"smooth": {"pillow": True, "label_samples": "auto", "label_surface_radius": 7},
                        "export": {"order": 2, "midside_nodes": "curved"}}
    config = load_config(sets=["preset=static-stress"])
    repository = load_config(Path(__file__).parents[1] / "config" / "static-stress.yaml")
    assert config == {**repository, "preset": "static-stress"}
    assert config["smooth"]["pillow"] and config["export"]["order"] == 2
    path = tmp_path / "c.yaml"
    path.write_text("preset: static-stress\nsmooth:\n  pillow: false\n")
    config = load_config(path, sets=["export.order=1"], settings={"export": {"midside_nodes": "midpoint"}})
    assert (config["smooth"]["pillow"], config["smooth"]["label_samples"]) == (False, "auto")
    assert (config["export"]["order"], config["export"]["midside_nodes"]) == (1, "midpoint")
    # as the workflow reads its config: the settings alone
    assert load_config(settings={"preset": "static-stress"})["smooth"]["label_samples"] == "auto"
    assert load_config()["preset"] is None


def test_the_presets_are_the_packaged_files_and_each_is_a_valid_configuration():
    from importlib import resources

    from dicer.config import preset_settings, schema

    files = sorted(p.name[:-5] for p in resources.files("dicer").joinpath("presets").iterdir()
                   if p.name.endswith(".yaml"))
    assert files == sorted(schema()["properties"]["preset"]["enum"][1:]) and files
    for name in files:
        settings = preset_settings(name)
        assert settings and "preset" not in settings
        validate(load_config(settings=settings), name)


def test_an_unknown_preset_is_one_error_line_and_no_output(tmp_path, capsys):
    from dicer.cli import main

    np.save(tmp_path / "l.npy", np.ones((4, 4, 4), np.uint8))
    assert main(["run", "--labels", str(tmp_path / "l.npy"), "-o", str(tmp_path / "out"),
                 "--set", "preset=static_stress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: config with --set: key 'preset': \"static_stress\" is not one of null, static-stress, "
                   "explicit-dynamics"]
    assert not (tmp_path / "out").exists()


def test_the_static_stress_preset_relaxes_a_label_volume_and_places_a_scans_faces(tmp_path):
    """``label_samples: auto`` (the preset's): a label volume's staircase relaxed, as ``relaxed``;
    a scan's faces placed by it, as ``faces`` (relaxed through the scan's places the noise-free
    Kirsch plate read 5 % low): the same smoothed nodes as those settings, whole runs."""
    from dicer.cli import main
    from dicer.io.meshes import read_mesh

    assert main(["phantom", "sphere", "--size", "20", "-o", str(tmp_path / "ct.nii.gz"), "-q"]) == 0
    common = ["--set", "smooth.pillow=true", "--set", "smooth.label_surface_radius=7", "--set", "export.order=2",
              "--set", "export.midside_nodes=curved"]
    runs = {"ct preset": ["run", str(tmp_path / "ct.nii.gz"), "--set", "preset=static-stress"],
            "ct faces": ["run", str(tmp_path / "ct.nii.gz"), *common, "--set", "smooth.label_samples=faces"],
            "ct relaxed": ["run", str(tmp_path / "ct.nii.gz"), *common, "--set", "smooth.label_samples=relaxed"]}
    for name, args in runs.items():
        assert main([*args, "-o", str(tmp_path / name), "-q"]) == 0
    labels = str(tmp_path / "ct preset" / "labels_fixed.nii.gz")
    runs = {"labels preset": ["run", "--labels", labels, "--set", "preset=static-stress"],
            "labels relaxed": ["run", "--labels", labels, *common, "--set", "smooth.label_samples=relaxed"]}
    for name, args in runs.items():
        assert main([*args, "-o", str(tmp_path / name), "-q"]) == 0
    points = {name: read_mesh(tmp_path / name / "smoothed.vtu").points
              for name in ("ct preset", "ct faces", "ct relaxed", "labels preset", "labels relaxed")}
    assert np.array_equal(points["ct preset"], points["ct faces"])
    assert not np.array_equal(points["ct preset"], points["ct relaxed"])
    assert np.array_equal(points["labels preset"], points["labels relaxed"])
    smoothed = json.loads((tmp_path / "labels preset" / "smooth.json").read_text())
    assert "samples_relaxed" in json.dumps(smoothed)


def test_a_presets_keys_set_otherwise_by_the_configuration_are_said(tmp_path, caplog):
    """config/config.yaml writes every key at its default, so ``preset: explicit-dynamics`` added
    to it kept none of the preset's settings, silently: the keys that override it are named once."""
    from pathlib import Path

    from dicer.config import _say_once

    _say_once.cache_clear()
    shipped = Path(__file__).parents[1] / "config" / "config.yaml"
    caplog.set_level("WARNING", logger="dicer")
    for _ in range(2):
        config = load_config(shipped, sets=["preset=explicit-dynamics", "export.midside_nodes=midpoint"])
    assert (config["smooth"]["pillow"], config["export"]["midside_nodes"]) == (True, "midpoint")
    said = [r.getMessage() for r in caplog.records if "preset explicit-dynamics" in r.getMessage()]
    assert said == [f"{shipped} with --set: preset explicit-dynamics sets smooth.pillow: false, smooth.label_samples: "
                    "\"faces\", smooth.label_surface_radius: 5, export.midside_nodes: \"midpoint\"; "
                    "the configuration's own smooth.pillow: true, smooth.label_samples: \"auto\", "
                    "smooth.label_surface_radius: 7 override it: remove those keys to take the preset's"]
    # static-stress sets export.order besides the defaults: the shipped file's order 1 overrides it
    caplog.clear()
    assert load_config(shipped, sets=["preset=static-stress"])["export"]["order"] == 1
    assert [r.getMessage() for r in caplog.records if "preset static-stress" in r.getMessage()] == [
        f"{shipped} with --set: preset static-stress sets smooth.pillow: true, smooth.label_samples: \"auto\", "
        "smooth.label_surface_radius: 7, export.order: 2, export.midside_nodes: \"curved\"; the configuration's own "
        "export.order: 1 override it: remove those keys to take the preset's"]
    caplog.clear()
    caplog.set_level("INFO", logger="dicer")
    load_config(sets=["preset=static-stress"])
    assert [(r.levelname, r.getMessage()) for r in caplog.records if "preset" in r.getMessage()] == [
        ("INFO", "config with --set: preset static-stress sets smooth.pillow: true, smooth.label_samples: \"auto\", "
                 "smooth.label_surface_radius: 7, export.order: 2, export.midside_nodes: \"curved\"")]


@pytest.mark.parametrize("item", ["downsample.factor=99999999999999999999", "downsample.factor=[1e30,1,1]",
                                  "downsample.voxel_size=1e300"])
def test_downsampling_beyond_any_image_is_refused_by_the_schema(item):
    """Factors past int64 ended in an OverflowError traceback when the run estimated its memory."""
    with pytest.raises(DicerError, match=r"key 'downsample\.(factor|voxel_size)': .*<= 1000000"):
        load_config(None, [item])


def test_yaml_merge_keys_are_read_and_an_anchor_inside_itself_refused(tmp_path):
    """``<<: *soft`` is YAML (it was refused as 'not valid YAML ... quote strings'), a key after
    it overrides the merged one; 'a: &a [*a]' ended in a RecursionError traceback."""
    path = tmp_path / "c.yaml"
    path.write_text("materials:\n  - &soft {name: soft, youngs_modulus: 1, poissons_ratio: 0.3, density: 1.0e-9}\n"
                    "  - {<<: *soft, name: bone, youngs_modulus: 10}\n")
    materials = load_config(path)["materials"]
    assert [(m["name"], m["youngs_modulus"], m["poissons_ratio"]) for m in materials] == [("soft", 1, 0.3),
                                                                                        ("bone", 10, 0.3)]
    path.write_text("smooth: {coefficient: 0.5, coefficient: 0.6}\n")
    with pytest.raises(DicerError, match="key 'coefficient' is given twice"):
        load_config(path)
    path.write_text("smooth: &a {pillow: [*a]}\n")
    with pytest.raises(DicerError, match=r"c\.yaml: an anchor refers to itself .*; write the values out$"):
        load_config(path)


@pytest.mark.parametrize("item, said", [
    ("materials=[{name: a, youngs_modulus: 1.5e10}]", r"materials\.0\.youngs_modulus': 15000000000\.0 is out of range"),
    ("materials=[{name: a, density: 1900}]", r"materials\.0\.density': 1900 is out of range"),
    ("image.crop={unit: voxels, min: [0, 0, 0], max: [99999999999999999999, 30, 30]}", r"image\.crop': max\.0"),
])
def test_properties_in_other_units_and_crops_past_any_image_are_refused(item, said):
    """E in Pa and densities in kg/m^3 passed (E 1e308 made an explicit time step of 0.0 s and
    numpy's overflow warnings); a crop past int64 was printed as -9223372036854775808."""
    with pytest.raises(DicerError, match=said):
        load_config(None, [item])
