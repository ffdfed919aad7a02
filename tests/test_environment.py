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
