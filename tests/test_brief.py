"""Log lines of atlases with many labels: the first few figures, the rest counted; report files keep all."""

import json

import numpy as np

from dicer.brief import LIMIT, brief_json, brief_names
from dicer.cli import main


def test_mappings_and_lists_are_cut_to_the_limit_and_counted():
    volumes = {f"label_{k}": k * 10 for k in range(1, 31)}
    text = json.loads(brief_json(volumes))
    assert list(text)[:LIMIT] == [f"label_{k}" for k in range(1, LIMIT + 1)]
    assert text["..."] == f"{30 - LIMIT} more" and len(text) == LIMIT + 1
    nested = json.loads(brief_json({"bytes": 5, "materials": volumes, "sweeps": list(range(20))}, whole_top=True))
    assert nested["bytes"] == 5 and len(nested["materials"]) == LIMIT + 1
    assert nested["sweeps"][-1] == f"... {20 - LIMIT} more" and len(nested["sweeps"]) == LIMIT + 1
    top = json.loads(brief_json({str(k): k for k in range(12)}, limit=3, sort_keys=True))
    assert list(top) == ["0", "1", "10", "..."]  # sorted as strings, as json.dumps(sort_keys=True)
    small = {"a": 1, "b": [1, 2]}
    assert brief_json(small) == json.dumps(small)  # nothing to cut: the same text
    assert brief_names(["a", "b", "c"], limit=2) == "a, b and 1 more"
    assert brief_names(["a", "b"], limit=2) == "a, b"


def test_an_atlas_s_log_lines_stay_short_and_its_files_keep_every_label(tmp_path, caplog):
    labels = np.zeros((12, 12, 12), np.uint16)
    # 50 labels: 10 slabs along x, each cut into 5 bars of 2 voxels along y
    labels[1:11, 1:11, 1:11] = 1 + np.arange(10)[:, None, None] * 10 + np.arange(10)[None, :, None] // 2
    np.save(tmp_path / "atlas.npy", labels)
    caplog.set_level("INFO", logger="dicer")
    assert main(["labels", str(tmp_path / "atlas.npy"), "-o", str(tmp_path / "l.nii.gz"),
                 "--materials", str(tmp_path / "m.json")]) == 0
    materials = json.loads((tmp_path / "m.json").read_text())["materials"]
    assert len(materials) == 50
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("labels:")]
    assert len(lines) >= 2 and max(len(line) for line in lines) < 800
    assert any("and 42 more: default properties" in line for line in lines)
