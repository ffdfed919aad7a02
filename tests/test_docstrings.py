"""The public API's docstrings are in one dialect, numpydoc (as scikit-image's): a summary
line, then a ``Parameters`` section naming every parameter and a ``Returns`` (or ``Yields``)
section when the callable gives something back.

Public: the names in a module's ``__all__``, or, without one, the functions and classes
the module defines whose names do not start with an underscore.
"""

import ast
import importlib
import inspect
import textwrap

import pytest
from numpydoc.docscrape import NumpyDocString

MODULES = [
    "dicer.errors",
    "dicer.mesh",
    "dicer.mesh.model",
    "dicer.mesh.faces",
    "dicer.mesh.metrics",
    "dicer.mesh.voxel",
    "dicer.mesh.coarsen",
    "dicer.mesh.merge",
    "dicer.mesh.frame",
    "dicer.mesh.subvoxel",
    "dicer.mesh.templates",
    "dicer.mesh.quadratic",
    "dicer.segment",
    "dicer.segment.morphology",
    "dicer.connectivity",
    "dicer.downsample",
    "dicer.labels",
    "dicer.crop",
    "dicer.image",
    "dicer.quality",
    "dicer.cohort",
    "dicer.phantoms",
    "dicer.config",
    "dicer.resources",
    "dicer.export",
    "dicer.export.model",
    "dicer.export.provenance",
    "dicer.export.registry",
    "dicer.export.format",
    "dicer.export.readers",
    "dicer.export.textfmt",
    "dicer.export.textparse",
    "dicer.export.abaqus",
    "dicer.export.exodus",
    "dicer.export.febio",
    "dicer.export.gmsh",
    "dicer.export.lsdyna",
    "dicer.export.patran",
    "dicer.export.stl",
    "dicer.export.vtu",
    "dicer.validation.__main__",
    "dicer.validation.analytic",
    "dicer.validation.calculix",
    "dicer.validation.cases",
    "dicer.validation.figures",
    "dicer.validation.geometry",
    "dicer.validation.models",
    "dicer.validation.study",
]


def _public(module):
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n, obj in vars(module).items()
                 if not n.startswith("_") and (inspect.isfunction(obj) or inspect.isclass(obj))
                 and obj.__module__ == module.__name__]
    return [(n, getattr(module, n)) for n in names
            if inspect.isfunction(getattr(module, n)) or inspect.isclass(getattr(module, n))]


def _callables():
    for name in MODULES:
        module = importlib.import_module(name)
        for attr, obj in _public(module):
            yield pytest.param(obj, id=f"{name}.{attr}")


def _gives_something(func) -> bool:
    """True when ``func`` returns a value or yields (its own body, not nested functions)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    body = tree.body[0]
    stack = list(body.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda)):
            continue
        if isinstance(node, (ast.Yield, ast.YieldFrom)):
            return True
        if isinstance(node, ast.Return) and node.value is not None and not (
                isinstance(node.value, ast.Constant) and node.value.value is None):
            return True
        stack.extend(ast.iter_child_nodes(node))
    return False


def _documented(section) -> set[str]:
    names = set()
    for param in section:
        for name in param.name.split(","):
            names.add(name.strip().lstrip("*"))
    return names


@pytest.mark.parametrize("obj", list(_callables()))
def test_public_callable_has_a_numpydoc_docstring(obj):
    doc = inspect.getdoc(obj)
    assert doc, "no docstring"
    parsed = NumpyDocString(doc)  # raises on a malformed section
    assert parsed["Summary"], "no one-line summary"
    func = obj.__init__ if inspect.isclass(obj) else obj
    if inspect.isclass(obj) and not inspect.isfunction(func):  # the constructor of a builtin base
        return
    wanted = [p for p in inspect.signature(func).parameters if p not in ("self", "cls")]
    if wanted:
        documented = _documented(parsed["Parameters"]) | _documented(parsed["Other Parameters"])
        missing = [p for p in wanted if p not in documented]
        assert not missing, f"Parameters section lacks {missing}"
    if not inspect.isclass(obj) and _gives_something(inspect.unwrap(obj)):
        assert parsed["Returns"] or parsed["Yields"], "no Returns section"


def _methods():
    for name in MODULES:
        module = importlib.import_module(name)
        for attr, obj in _public(module):
            if not inspect.isclass(obj) or obj.__module__ != module.__name__:
                continue
            for meth, member in vars(obj).items():
                if meth.startswith("_"):
                    continue
                func = member.fget if isinstance(member, property) else getattr(member, "__func__", member)
                if inspect.isfunction(func):
                    yield pytest.param(func, id=f"{name}.{attr}.{meth}")


@pytest.mark.parametrize("func", list(_methods()))
def test_public_method_has_a_docstring(func):
    doc = inspect.getdoc(func)
    assert doc and NumpyDocString(doc)["Summary"], "no docstring"
