import numpy as np
import pytest

from dicer.config import load_config
from dicer.image import Volume
from dicer.mesh.voxel import voxel_mesh
from dicer.quality import quality_report, render_html


def test_report_counts_and_metrics():
    labels = np.zeros((4, 4, 4), np.uint8)
    labels[:2] = 1
    labels[2:, :2] = 2
    mesh = voxel_mesh(labels, spacing=(1.0, 1.0, 2.0))
    mesh.points[mesh.lattice[:, 0] == 4, 0] += 0.5  # stretch the x = 4 face: elements still valid
    report = quality_report(mesh, load_config(), labels=Volume(labels, (1.0, 1.0, 2.0)))
    assert report["elements"] == 48 and report["nodes"] == mesh.n_points
    soft, bone = report["materials"]["soft_tissue"], report["materials"]["bone"]
    assert soft["elements"] == 32 and bone["elements"] == 16
    assert soft["voxels"] == 32 and soft["volume_mm^3"] == pytest.approx(64.0)
    # 8 bone elements touch x = 4: each grows by half a voxel in x
    assert bone["volume_mm^3"] == pytest.approx(32.0 + 8 * 0.5 * 2.0)
    assert bone["volume_change_percent"] == pytest.approx(25.0)
    assert report["inverted_elements"] == 0 and report["poor_elements"] == 0
    assert report["scaled_jacobian"]["max"] == pytest.approx(1.0)
    assert report["edge_ratio"]["max"] == pytest.approx(2.0)
    assert report["element_volume_mm^3"]["total"] == pytest.approx(96.0 + 8.0)


def test_inverted_elements_are_counted_and_html_renders():
    labels = np.ones((2, 2, 2), np.uint8)
    mesh = voxel_mesh(labels)
    centre = np.flatnonzero((mesh.lattice == 1).all(axis=1))[0]
    mesh.points[centre] = [2.6, 2.6, 2.6]  # centre node pushed out through the far corner
    report = quality_report(mesh, load_config())
    assert report["inverted_elements"] >= 1
    assert report["poor_elements"] >= report["inverted_elements"]
    page = render_html(report)
    assert page.startswith("<!DOCTYPE html>") and "soft_tissue" in page


def test_html_shows_stage_reports_and_pictures():
    mesh = voxel_mesh(np.ones((2, 2, 2), np.uint8))
    report = quality_report(mesh, load_config())
    report["stages"] = {"fix": {"changed_voxels": 7, "type_a": {"bone": 3}}, "merge": {"elements_after": 1}}
    page = render_html(report, ["segmentation.png"])
    assert "<h2>Stage: fix</h2>" in page and "<h2>Stage: merge</h2>" in page
    assert "<td>7</td>" in page and "{&quot;bone&quot;: 3}" in page
    assert "<img src='segmentation.png'" in page
