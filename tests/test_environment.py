"""environment.yml: a conda environment for the workflow's rules with pyproject.toml's dependencies
(conda itself is not installed here: the file's structure and names are checked)."""

import re
import tomllib
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def _name(spec: str) -> tuple[str, str]:
    match = re.match(r"^\s*([A-Za-z0-9_.-]+)\s*(.*)$", spec)
    return match.group(1).lower().replace("_", "-"), match.group(2).replace(" ", "")


def test_environment_lists_pyprojects_dependencies_without_dicer_itself():
    env = yaml.safe_load((REPO / "environment.yml").read_text())
    assert set(env) == {"name", "channels", "dependencies"} and env["channels"][0] == "conda-forge"
    conda = {}
    for item in env["dependencies"]:
        assert isinstance(item, str), f"no pip section (a path such as -e . breaks Snakemake's conda deployment): {item}"
        name, bound = _name(item)
        conda[name] = bound
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    pip = dict(_name(spec) for spec in project["dependencies"])
    # every runtime dependency with the same lower bound (conda-forge uses the lower-case names)
    assert {n: conda.get(n) for n in pip} == pip
    assert conda["python"] == project["requires-python"]
    # beyond them only what installs dicer from its source: pip and pyproject's build system
    build = {_name(spec)[0] for spec in tomllib.loads((REPO / "pyproject.toml").read_text())["build-system"]["requires"]}
    assert set(conda) - set(pip) - {"python"} == {"pip"} | build
    assert "dicer" not in conda
    # the SLURM plugin: listed, commented out (optional)
    slurm = project["optional-dependencies"]["slurm"][0]
    assert f"# - {slurm}" in (REPO / "environment.yml").read_text()


def test_rules_use_the_environment_and_its_post_deploy_script_installs_dicer():
    common = (REPO / "workflow" / "rules" / "common.smk").read_text()
    assert 'CONDA_ENV = "../../environment.yml"' in common
    assert (REPO / "workflow" / "rules" / "../../environment.yml").resolve() == REPO / "environment.yml"
    assert "DICER_SOURCE=" in common
    script = (REPO / "environment.post-deploy.sh").read_text()
    assert 'pip install --no-deps --no-build-isolation --quiet -e "$DICER_SOURCE"' in script
    for rules in (REPO / "workflow" / "rules").glob("*.smk"):
        text = rules.read_text()
        assert text.count("\nrule ") == text.count("        CONDA_ENV"), rules.name


def _pins() -> dict[str, str]:
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pins[name.lower().replace("_", "-")] = version.strip()
    return pins


def test_constraints_pin_every_dependency_at_or_above_its_lower_bound():
    from packaging.version import Version

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    pins = _pins()
    specs = list(project["dependencies"]) + [s for extra in project["optional-dependencies"].values() for s in extra]
    for spec in specs:
        name, bound = _name(spec)
        assert name in pins, f"{name} has no pin in constraints.txt"
        if bound.startswith(">="):
            assert Version(pins[name]) >= Version(bound[2:]), (name, pins[name], bound)
        elif bound.startswith("=="):
            assert pins[name] == bound[2:], (name, pins[name], bound)
    assert "dicer" not in pins


def test_the_libraries_reported_are_pyprojects_dependencies_at_their_pins():
    """quality.json's ``library_versions`` and ``dicer --version`` name pyproject's runtime
    dependencies; the setup (make setup: pip install -c constraints.txt) installs them at the
    pinned versions, so the same input gives the same bytes on a machine set up later."""
    import subprocess
    import sys

    from dicer import LIBRARIES, library_versions

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = [_name(spec)[0] for spec in project["dependencies"]]
    assert [n.lower().replace("_", "-") for n in LIBRARIES] == runtime
    versions = library_versions()
    pins = _pins()
    assert list(versions) == ["python", *LIBRARIES]
    assert {n: versions[n] for n in LIBRARIES} == {n: pins[n.lower().replace("_", "-")] for n in LIBRARIES}
    out = subprocess.run([sys.executable, "-m", "dicer", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout == "dicer " + __import__("dicer").__version__ + " (" + ", ".join(
        f"{k} {v}" for k, v in versions.items()) + ")\n" and out.stderr == ""
