"""Configuration: schema defaults, YAML files, ``--set`` overrides, validation.

A configuration is a nested dict. Its schema (``dicer/schemas/config.schema.yaml``)
gives every key a default, so ``load_config()`` with no arguments is valid.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import inspect
import json
import logging
import math
import re
from collections import Counter
from importlib import resources
from pathlib import Path

import jsonschema
import yaml

from dicer.errors import DicerError

# The config sections each stage reads; the workflow passes exactly these to a rule
# through ``params:`` so that editing one section re-runs only the stages that read it.
STAGE_SECTIONS = {
    "segment": ("image", "materials", "segment"),
    "labels": ("image", "labels", "materials"),  # image.crop
    "downsample": ("materials", "segment", "downsample"),
    "fix": ("materials", "fix"),
    "mesh": ("materials", "mesh"),  # the names go into the mesh file
    "merge": ("merge",),
    "smooth": ("smooth",),
    "export": ("materials", "export"),
    "quality": ("materials", "quality"),  # the report names the materials; their properties: its time step
}

# The stages that read only the materials' names (and order): a change of a material's
# properties re-runs the exports and the quality report alone (the labels stage's
# materials.json then holds the names alone, the export takes the properties from its own
# settings by name, and the report's explicit time step follows them)
NAMES_ONLY = ("segment", "labels", "downsample", "fix", "mesh")

# Keys of other sections a stage reads too (the workflow passes them with the sections): the
# spacing of a .npy volume; smooth's scan, read as segment read it (spacing, slices, crop), and
# its manual thresholds
STAGE_KEYS = {
    "downsample": ("image.spacing",),
    "fix": ("image.spacing",),
    "mesh": ("image.spacing",),
    "smooth": ("image.spacing", "image.allow_irregular_slices", "image.crop", "segment.method", "segment.thresholds"),
    # a 2D model's plane stress or strain: its time step (the type is checked against the order)
    "quality": ("image.spacing", "export.order", "export.element_type"),
}


def schema() -> dict:
    """The configuration JSON Schema as a dict.

    Returns
    -------
    dict
        A fresh copy: callers may change it.
    """
    return copy.deepcopy(_schema())


@functools.lru_cache(maxsize=1)
def _schema() -> dict:
    # parsed once per process (with libyaml when present): every config load and each
    # Snakemake job's start-up reads it
    text = resources.files("dicer").joinpath("schemas/config.schema.yaml").read_text(encoding="utf-8")
    return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def _defaults(node: dict):
    if "default" in node:
        value = copy.deepcopy(node["default"])
        if isinstance(value, dict) and node.get("properties"):
            for key, sub in node["properties"].items():
                if key not in value and "default" in sub:
                    value[key] = _defaults(sub)
        return value
    if node.get("type") == "object" and "properties" in node:
        return {k: _defaults(s) for k, s in node["properties"].items() if "default" in s or s.get("type") == "object"}
    return None


def _fill(value, node: dict):
    """Fill schema defaults into ``value`` (dicts and list items), in place where possible."""
    if isinstance(value, dict):
        for key, sub in node.get("properties", {}).items():
            if key not in value:
                if "default" in sub:
                    value[key] = _defaults(sub)
                else:
                    continue
            value[key] = _fill(value[key], sub)
    elif isinstance(value, list) and isinstance(node.get("items"), dict):
        value = [_fill(v, node["items"]) for v in value]
    return value


def section_defaults(section: str) -> dict:
    """The defaults of one config section, from the schema (its only source).

    Parameters
    ----------
    section : str
        A top-level key of the config, e.g. ``"smooth"``.

    Returns
    -------
    dict
        Every key of the section that has a default, at that default (a fresh copy).
    """
    return _defaults(_schema()["properties"][section])


def material_defaults() -> dict:
    """The properties a ``materials`` entry takes when it leaves them out, from the schema.

    Returns
    -------
    dict
        Property name -> default (a fresh copy).
    """
    items = _schema()["properties"]["materials"]["items"]["properties"]
    return {k: copy.deepcopy(v["default"]) for k, v in items.items() if "default" in v}


def materials_left_to_defaults(user: dict) -> list[tuple[str, list[str]]]:
    """The ``materials`` entries a configuration lists without some of their properties.

    Parameters
    ----------
    user : dict
        A configuration as given (before :func:`load_config` fills in the defaults).

    Returns
    -------
    list of (str, list of str)
        Each such entry's name and the properties it leaves out, in list order.
    """
    given = user.get("materials")
    if not isinstance(given, list):
        return []
    properties = list(material_defaults())
    out = []
    for entry in given:
        if isinstance(entry, dict):
            missing = [key for key in properties if key not in entry]
            if missing:
                out.append((str(entry.get("name")), missing))
    return out


def _say_defaulted_properties(user: dict, source: str) -> None:
    """Warn of listed materials whose properties the schema's defaults fill in: the default
    soft tissue (E 1 MPa, nu 0.45) listed by name alone became 1000 times stiffer without a word."""
    from dicer.brief import brief_names

    left = materials_left_to_defaults(user)
    if not left:
        return
    default = material_defaults()
    which = brief_names(f"{name} ({', '.join(keys)})" for name, keys in left)
    logging.getLogger("dicer").warning(
        "%s: properties left out of materials: %s; they take the defaults (E %g MPa, nu %g, density %g t/mm^3), "
        "not the default config's soft_tissue and bone properties: give each listed material its youngs_modulus, "
        "poissons_ratio and density", source, which, default["youngs_modulus"], default["poissons_ratio"],
        default["density"])


def _say_overridden_preset_keys(name: str, preset: dict, user: dict, source: str) -> None:
    """Say which of the preset's keys it sets, and warn of those the configuration sets otherwise:
    a config file that writes every key at its default (config/config.yaml) keeps none of the
    preset's."""
    sets = [(section, key, value) for section, keys in preset.items() for key, value in keys.items()]
    overridden = [isinstance(user.get(section), dict) and key in user[section] and user[section][key] != value
                  for section, key, value in sets]
    differ = [f"{s}.{k}: {json.dumps(user[s][k])}" for (s, k, _), o in zip(sets, overridden) if o]
    taken = [f"{s}.{k}: {json.dumps(value)}" for (s, k, value), o in zip(sets, overridden) if not o]
    if taken:
        _say_once(logging.INFO, f"{source}: preset {name} sets {', '.join(taken)}")
    if differ:
        given = ", ".join(f"{section}.{key}: {json.dumps(value)}" for section, key, value in sets)
        _say_once(logging.WARNING, f"{source}: preset {name} sets {given}; the configuration's own {', '.join(differ)} "
                                   "override it: remove those keys to take the preset's")


@functools.lru_cache(maxsize=None)
def _say_once(level: int, message: str) -> None:
    """A message said once per process (the workflow loads its configuration once per patient)."""
    logging.getLogger("dicer").log(level, "%s", message)


def default_config() -> dict:
    """Every key at its schema default.

    Returns
    -------
    dict
    """
    return _fill({}, schema())


def deep_merge(base: dict, override: dict) -> dict:
    """A copy of ``base`` with ``override`` merged in (dicts merge, anything else replaces).

    Parameters
    ----------
    base, override : dict

    Returns
    -------
    dict
    """
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader with three fixes: a key given twice in one mapping is an error
    (not a silent last-one-wins; 8 and "8" are one key), integers are read as YAML 1.2
    reads them (010 is ten), and floats in exponent form without a dot (``1e-9``,
    ``2E+5``) are numbers as in YAML 1.2 (YAML 1.1 reads them as strings)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        # merge keys (``<<: *base``) first: their keys may be given again, which overrides them
        explicit = [pair for pair in node.value if pair[0].tag != "tag:yaml.org,2002:merge"]
        self.flatten_mapping(node)
        for key_node, _ in explicit:
            key = self.construct_object(key_node, deep=deep)
            # 8 and "8" are one key once the config is JSON (labels.map keys become strings)
            key = str(key) if isinstance(key, int) and not isinstance(key, bool) else key
            if key in seen:
                raise DuplicateKey(key, key_node.start_mark.line + 1, seen[key])
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


class DuplicateKey(Exception):
    """A key given twice in one mapping of a YAML file.

    Parameters
    ----------
    key : str
    line, first : int
        The lines of the second and the first occurrence.
    """
    def __init__(self, key, line, first):
        super().__init__(key)
        self.key, self.line, self.first = key, line, first


_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789"))


def workflow_config(files: list, items: dict) -> dict:
    """The configuration Snakemake was given, read as dicer reads it.

    Snakemake reads its config files as YAML 1.1: 041 is octal 33 (a labels.map key or a crop
    bound changed without a word), 1e-9 a string, and a key given twice keeps its last value;
    and its ``--config`` items' nested values as text. dicer reads 041 as 41 and 1e-9 as a
    number, and refuses a repeated key naming its lines, so a cohort and ``dicer run --config``
    give one model.

    Parameters
    ----------
    files : list of str or Path
        The config files in the order Snakemake merges them (the workflow's own, then
        ``--configfile``'s).
    items : dict
        Snakemake's ``--config`` items as it parsed them; each text in them is read as one YAML
        value, as ``--set`` reads it (``smooth={coefficient: 0.5}``: 0.5, not "0.5").

    Returns
    -------
    dict
        The files merged in order, then the items.

    Raises
    ------
    DicerError
        A file dicer cannot read (bad YAML, a key given twice, not a mapping).
    """
    merged: dict = {}
    for path in files:
        merged = deep_merge(merged, read_config_file(path))
    return deep_merge(merged, _texts_read(items, _schema()))


def _takes_text(node: dict) -> bool:
    """Whether a schema node accepts a string (a name, a path, a method): its text is kept."""
    kinds = node.get("type")
    if kinds == "string" or (isinstance(kinds, list) and "string" in kinds):
        return True
    if any(isinstance(v, str) for v in node.get("enum", ())):
        return True
    return any(_takes_text(branch) for key in ("oneOf", "anyOf") for branch in node.get(key, ()))


def _sub_node(node: dict, key=None) -> dict:
    """The schema node of a mapping's ``key`` (None: an array's items), through oneOf/anyOf."""
    for branch in [node, *node.get("oneOf", ()), *node.get("anyOf", ())]:
        if key is None and isinstance(branch.get("items"), dict):
            return branch["items"]
        if key is not None and key in branch.get("properties", {}):
            return branch["properties"][key]
        if key is not None and isinstance(branch.get("additionalProperties"), dict):
            return branch["additionalProperties"]
    return {}


def _texts_read(tree, node: dict):
    """``tree`` (Snakemake's --config items: their nested values as text) with each text where
    the schema takes no text read as one YAML value (``"0.5"``: 0.5; ``"041"``: 41), and each
    key of digits a number, as dicer reads a labels.map key (``041``: label 41). A text the
    schema takes (a results folder ``"041"``, ``"out #1"``) stays as given."""
    if isinstance(tree, dict):
        return {(int(k, 10) if isinstance(k, str) and k.isdigit() else k): _texts_read(v, _sub_node(node, k))
                for k, v in tree.items()}
    if isinstance(tree, list):
        return [_texts_read(v, _sub_node(node)) for v in tree]
    if isinstance(tree, str) and not _takes_text(node):
        try:
            value = _yaml(tree, "--config") if tree.strip() else None
        except DicerError:  # not one YAML value: the text itself, for the schema to name
            return tree
        return tree if isinstance(value, (dict, list)) else value
    return tree

# integers as YAML 1.2 reads them: 010 is ten (YAML 1.1: octal eight, so a labels.map key
# 010 named label 8), 1:30 is a string (YAML 1.1: sexagesimal 90); 0o17 and 0x1F stay
_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:int"]
    for first, resolvers in _Loader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver("tag:yaml.org,2002:int", re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"),
                              list("-+0123456789"))


def _construct_int(loader, node) -> int:
    text = loader.construct_scalar(node)
    if text.startswith(("0o", "0x")):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text, 10)


_Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)
# dates as YAML 1.2 reads them: text (YAML 1.1: a date, which no key takes and which the error
# message could not print: workflow.results=2024-01-05 ended in a traceback)
_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:timestamp"]
    for first, resolvers in _Loader.yaml_implicit_resolvers.items()}


def _yaml(text: str, source: str):
    """``text`` parsed with ``_Loader``; DicerError naming ``source`` on bad YAML."""
    try:
        tree = yaml.load(text, Loader=_Loader)  # noqa: S506  (_Loader is a SafeLoader)
        if _holds_itself(tree):
            raise DicerError(f"{source}: an anchor refers to itself (a section inside its own alias, "
                             "'a: &a [*a]'); write the values out")
        return tree
    except DuplicateKey as dup:
        raise DicerError(f"{source}: key '{dup.key}' is given twice (lines {dup.first} and {dup.line}) in one "
                         "section; keep one") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise DicerError(f"{source}: not valid YAML{where} ({getattr(exc, 'problem', None) or 'syntax'}); "
                         "fix the syntax (quote strings)") from None


def _holds_itself(tree, inside: tuple = ()) -> bool:
    """Whether a list or mapping of ``tree`` holds itself (a YAML alias inside its anchor)."""
    if not isinstance(tree, (dict, list)):
        return False
    if any(tree is outer for outer in inside):
        return True
    values = tree.values() if isinstance(tree, dict) else tree
    return any(_holds_itself(v, (*inside, tree)) for v in values)


def parse_set(item: str, source: str = "--set") -> dict:
    """A ``--set`` item as a nested dict: ``a.b.c=VALUE`` -> ``{"a": {"b": {"c": VALUE}}}``.

    Parameters
    ----------
    item : str
        VALUE is read as YAML (``[1,1,1]``, ``0.8``, ``otsu``).
    source : str, optional
        Named in error messages.

    Returns
    -------
    dict
        One key per part of the dotted name.

    Raises
    ------
    DicerError
        An item without ``=``, an empty key part, or a value that is not YAML.
    """
    if "=" not in item:
        raise DicerError(f"{source} {item!r}: expected KEY=VALUE, e.g. smooth.coefficient=0.8")
    key, _, text = item.partition("=")
    parts = key.strip().split(".")
    if not all(parts):
        raise DicerError(f"{source} {item!r}: empty key part; use dotted keys like export.order=2")
    value = _yaml(text, f"{source} {item!r}: value") if text.strip() else None
    out: dict = {}
    node = out
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def _json_config(text: str, path) -> dict | None:
    """A config file written as JSON (which YAML reads too, but not with tabs), or None when the
    text is not JSON; a key given twice is refused as in YAML."""
    def pairs(items):
        seen = {}
        for key, value in items:
            if key in seen:
                raise DicerError(f"{path}: key '{key}' is given twice in one section; keep one")
            seen[key] = value
        return seen

    try:
        return json.loads(text, object_pairs_hook=pairs)
    except json.JSONDecodeError:
        return None


def read_config_file(path: str | Path) -> dict:
    """Read a YAML configuration file (no defaults, no validation).

    Parameters
    ----------
    path : str or Path
        A YAML file.

    Returns
    -------
    dict
        Its sections; empty for an empty file.

    Raises
    ------
    DicerError
        A missing or unreadable file, bad YAML, a repeated key, or not a mapping.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DicerError(f"{path}: config file not found; check the path given to --config") from None
    except IsADirectoryError:
        raise DicerError(f"{path}: is a folder; give the config file (YAML) to --config") from None
    except OSError as exc:
        raise DicerError(f"{path}: cannot read config file ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DicerError(f"{path}: not UTF-8 text (byte {exc.start + 1}, line {line}); save the config file "
                         "as UTF-8") from None
    data = _json_config(text, path) if text.lstrip().startswith("{") else None
    if data is None:
        data = _yaml(text, str(path))
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DicerError(f"{path}: a config file must be a YAML mapping of sections (materials:, segment:, ...)")
    return data


def _key_path(error: jsonschema.ValidationError) -> str:
    return ".".join(str(p) for p in error.absolute_path) or "(top level)"


def _range(node: dict) -> str | None:
    """The allowed range of a numeric schema node, in words (None if it has no bounds)."""
    parts = []
    if "minimum" in node:
        parts.append(f">= {node['minimum']}")
    if "exclusiveMinimum" in node:
        parts.append(f"> {node['exclusiveMinimum']}")
    if "maximum" in node:
        parts.append(f"<= {node['maximum']}")
    if "exclusiveMaximum" in node:
        parts.append(f"< {node['exclusiveMaximum']}")
    if not parts:
        return None
    kind = "a whole number" if node.get("type") == "integer" else "a number"
    return f"{kind} {' and '.join(parts)}"


_JSON_TYPES = {"null": type(None), "boolean": bool, "object": dict, "array": list, "string": str}


def _of_type(value, kind) -> bool:
    """Whether ``value`` is of the JSON Schema type ``kind`` (a name; None for no type)."""
    if kind in ("number", "integer"):
        return isinstance(value, int if kind == "integer" else (int, float)) and not isinstance(value, bool)
    return kind in _JSON_TYPES and isinstance(value, _JSON_TYPES[kind])


def _explain(err: jsonschema.ValidationError) -> str:
    """A schema error in words that give the allowed values."""
    value = json.dumps(err.instance) if not isinstance(err.instance, (dict, list)) else type(err.instance).__name__
    if err.validator in ("oneOf", "anyOf") and err.context and isinstance(err.instance, (dict, list)):
        # a value of the type of one alternative only (a mapping for image.crop): what is
        # wrong inside it, not "a mapping is not allowed"
        fits = [i for i, sub in enumerate(err.validator_value) if _of_type(err.instance, sub.get("type"))]
        inner = [e for e in err.context if len(fits) == 1 and e.relative_schema_path[0] == fits[0]]
        if inner:
            best = jsonschema.exceptions.best_match(inner)
            where = ".".join(str(p) for p in best.relative_path)
            return (f"{where}: " if where else "") + _explain(best)
    if err.validator in ("oneOf", "anyOf"):
        allowed = []
        for sub in err.validator_value:
            if sub.get("type") == "null":
                allowed.append("null")
            elif "enum" in sub:
                allowed.append("one of " + ", ".join(map(str, sub["enum"])))
            elif _range(sub):
                allowed.append(_range(sub))
            elif "type" in sub:
                allowed.append(f"{'an' if sub['type'][0] in 'aeiou' else 'a'} {sub['type']}")
        if allowed:
            return f"{value} is not allowed; give {' or '.join(allowed)}"
    if err.validator in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum") and _range(err.schema):
        return f"{value} is out of range; give {_range(err.schema)}"
    if err.validator == "enum":
        named = ("null" if v is None else str(v) for v in err.validator_value)  # YAML's name for None
        return f"{value} is not one of {', '.join(named)}"
    if (err.validator == "type" and err.validator_value == "array" and isinstance(err.instance, dict)
            and all(str(k).isdigit() for k in err.instance)):
        # --set a.0.b=... makes a mapping of item numbers, not a list
        return ("a list is set whole, not item by item: give all of it, e.g. --set 'materials=[{name: a}, "
                "{name: b}]' (a YAML list)")
    if err.validator == "pattern" and err.validator_value in _PATTERNS:
        return f"{value} is not {_PATTERNS[err.validator_value]}"
    return err.message


_NAME = re.compile("^[A-Za-z][A-Za-z0-9_]{0,31}$")  # the schema's material name

#: the schema's patterns in words
_PATTERNS = {
    "^[1-9][0-9]*$": "a label value to mesh: give a whole number from 1, without leading zeros (8, not 08); "
                     "0 is the background, never meshed",
    "^[A-Za-z][A-Za-z0-9_]{0,31}$": "a name: give a letter, then at most 31 letters, digits or _",
}


def _numbers(value, where: str = ""):
    """(key path, float) of every float in a config (NaN and infinities included)."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, f"{where}.{k}" if where else str(k))
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from _numbers(v, f"{where}[{i}]")
    elif isinstance(value, float):
        yield where, value


@functools.lru_cache(maxsize=1)
def _validator() -> jsonschema.Draft202012Validator:
    # made once per process: every stage call checks its settings (stage_kwargs)
    return jsonschema.Draft202012Validator(_schema())


_VALID_TEXTS: set[bytes] = set()
"""Digests of configurations the schema passed: a command validates the same sections several
times (each stage_kwargs call), and an atlas's thousands of materials took seconds each."""


def _plain_json(tree) -> bool:
    """Whether ``tree`` is made of dicts with text keys, lists and scalars only."""
    if isinstance(tree, dict):
        return all(isinstance(k, str) and _plain_json(v) for k, v in tree.items())
    if isinstance(tree, list):
        return all(_plain_json(v) for v in tree)
    return tree is None or isinstance(tree, (str, int, float))


def _schema_errors(config: dict) -> list:
    """The schema's errors of ``config``, the shallowest first; none for a configuration that
    passed before (remembered by its canonical JSON)."""
    digest = None
    if _plain_json(config):  # other trees (tuples, keys that are not text) dump like plain ones
        try:
            digest = hashlib.sha256(json.dumps(config, sort_keys=True, allow_nan=True).encode()).digest()
        except (TypeError, ValueError):  # values JSON has not: not remembered
            digest = None
    if digest is not None and digest in _VALID_TEXTS:
        return []
    errors = sorted(_validator().iter_errors(config), key=lambda e: (len(list(e.absolute_path)), e.message))
    if not errors and digest is not None:
        if len(_VALID_TEXTS) >= 256:
            _VALID_TEXTS.clear()
        _VALID_TEXTS.add(digest)
    return errors


def validate(config: dict, source: str = "config") -> dict:
    """Validate a configuration against the schema.

    Parameters
    ----------
    config : dict
    source : str, optional
        Named in error messages.

    Returns
    -------
    dict
        ``config`` itself.

    Raises
    ------
    DicerError
        Naming the first bad key.
    """
    for where, value in _numbers(config):
        if not math.isfinite(value):
            raise DicerError(f"{source}: key '{where}': {value} is not a finite number; give a finite number "
                             "(see the allowed range in config/config.yaml)")
    mapping = config.get("labels", {}).get("map", {}) if isinstance(config.get("labels"), dict) else {}
    if isinstance(mapping, dict):  # an atlas's lookup table: every bad name at once, not one per run
        bad = [f"{k}: {v!r}" for k, v in mapping.items() if isinstance(v, str) and not _NAME.match(v)]
        if len(bad) > 1:
            shown = ", ".join(bad[:12]) + (f" and {len(bad) - 12} more" if len(bad) > 12 else "")
            raise DicerError(f"{source}: key 'labels.map': {len(bad)} names are not {_PATTERNS[_NAME.pattern]} "
                             f"({shown})")
    errors = _schema_errors(config)
    if errors:
        err = errors[0]
        if err.validator == "additionalProperties":
            extra = sorted(set(err.instance) - set(err.schema.get("properties", {})))
            where = _key_path(err)
            name = f"{where}.{extra[0]}" if where != "(top level)" else extra[0]
            known = ", ".join(sorted(err.schema.get("properties", {}))) or "none"
            raise DicerError(f"{source}: unknown key '{name}'; known keys here: {known}")
        raise DicerError(f"{source}: key '{_key_path(err)}': {_explain(err)}")
    for i, material in enumerate(config.get("materials", [])):
        nu = material.get("poissons_ratio")
        # decks print at least 7 significant digits (LS-DYNA's 10 columns); solvers divide
        # by 1 - 2 nu and 1 + nu, so a printed 0.5 or -1 stops them
        if isinstance(nu, (int, float)) and not -1 < float(f"{nu:.7g}") < 0.5:
            raise DicerError(f"{source}: key 'materials.{i}.poissons_ratio': {nu!r} is {float(f'{nu:.7g}'):g} "
                             "at the 7 significant digits a solver deck holds, where solvers divide by 1 - 2 nu "
                             "and 1 + nu; give a value from -0.9999999 to 0.4999999")
    names = [m["name"] for m in config.get("materials", [])]
    if len(set(names)) != len(names):
        twice = sorted(n for n, count in Counter(names).items() if count > 1)
        raise DicerError(f"{source}: key 'materials': class names must be unique; {', '.join(twice)} repeat")
    from dicer.mesh.model import GRID_FIELDS

    taken = sorted(set(names) & set(GRID_FIELDS))
    if taken:
        raise DicerError(f"{source}: key 'materials': the name {taken[0]} is taken by the grid data of dicer's "
                         "mesh files; rename the material")
    section = config.get("labels", {})
    # label 0's name in materials.json, segmentation.json and the stage reports: a material of
    # that name would be meshed (and stiff) under a name that says it is not there
    background = sorted((int(k), v) for k, v in section.get("map", {}).items() if str(v).lower() == "background")
    if background:
        value, name = background[0]
        raise DicerError(f"{source}: key 'labels.map': value {value} is named {name!r}, the name of label 0, which "
                         f"is never meshed; to leave value {value} out of the model use labels.drop: [{value}], "
                         "else give it another name")
    named = [n for n in names if n.lower() == "background"]
    if named:
        raise DicerError(f"{source}: key 'materials': the name {named[0]} is label 0's, which is never meshed; "
                         "rename the material (to leave a label out of the model use labels.drop)")
    both = sorted(set(section.get("drop", [])) & {int(k) for k in section.get("map", {})})
    if both:
        raise DicerError(f"{source}: key 'labels': label value {both[0]} is both in labels.map and in "
                         "labels.drop; keep it in one of them")
    clash = name_clash(names, config.get("export", {}).get("sets", SET_KINDS))
    if clash:
        raise DicerError(f"{source}: key 'materials': {clash}")
    # the names labels.map gives, in the order of their smallest value (as the labels stage numbers
    # them): a clash among them is the config's, said before any stage (a label volume's values
    # the map leaves out add names only the stage knows)
    mapped = dict.fromkeys(name for _, name in sorted((int(k), v) for k, v in section.get("map", {}).items()))
    clash = name_clash(list(mapped), config.get("export", {}).get("sets", SET_KINDS))
    if clash:
        raise DicerError(f"{source}: key 'labels.map': {clash}")
    _check_combinations(config, source)
    return config


def _check_combinations(config: dict, source: str) -> None:
    """Refuse settings that contradict each other, when the configuration is read rather than
    at the stage that reads them (after the stages before it have run)."""
    smooth = config.get("smooth", {})
    if smooth.get("keep_bounding_planes") is False and smooth.get("bounding_planes", "mirror") != "free":
        raise DicerError(f"{source}: key 'smooth.keep_bounding_planes': false lets plane nodes leave their plane, "
                         "which only smooth.bounding_planes: free does; set smooth.bounding_planes: free with it, "
                         "or keep_bounding_planes: true")
    order = config.get("export", {}).get("order")
    etype = config.get("export", {}).get("element_type")
    if order is not None and etype is not None:
        from dicer.export.model import ELEMENT_TYPES, element_types

        dim, etype_order = ELEMENT_TYPES.get(etype, (None, order))
        if etype_order != order:
            raise DicerError(f"{source}: key 'export.element_type': {etype} has order {etype_order} and export.order "
                             f"is {order}; set export.order: {etype_order}, or an element type of order {order} "
                             f"({', '.join(element_types(dim, order))})")
    exports = config.get("workflow", {}).get("exports", ())
    if order is not None and isinstance(exports, list):
        from dicer.export.registry import BY_SUFFIX

        for ext in exports:
            fmt = BY_SUFFIX.get(f".{ext}")
            if fmt is not None and order not in fmt.orders:
                raise DicerError(f"{source}: key 'workflow.exports': {ext} ({fmt.name}) holds elements of order "
                                 f"{', '.join(map(str, fmt.orders))} only, and export.order is {order}; drop {ext} "
                                 f"from workflow.exports or set export.order: {fmt.orders[0]}")


def unused_smooth_settings(smooth: dict) -> list[str]:
    """The smooth settings given other values than their defaults that the others leave
    unused (they were ignored without a word), each as a sentence.

    Parameters
    ----------
    smooth : dict
        A loaded configuration's ``smooth`` section.

    Returns
    -------
    list of str
    """
    default = section_defaults("smooth")
    changed = {k for k, v in smooth.items() if k in default and v != default[k]}
    out = []

    def unused(key, why):
        if key in changed:
            out.append(f"smooth.{key}={json.dumps(smooth[key])} is not used: {why}")

    if not (smooth.get("surface_from_image") or places_faces_by_scan(smooth)):
        unused("image_sigma", "it smooths the scan for smooth.surface_from_image or smooth.fit_to_scan, which these "
                              "settings leave unused")
    if not smooth.get("pillow"):
        unused("pillow_thickness", "it is the thickness of the layer smooth.pillow adds, which is off")
    if not smooth.get("surface_from_labels"):
        for key in ("label_samples", "label_surface_radius"):  # fit_to_scan: false there turns nothing off
            unused(key, "it shapes the fit of smooth.surface_from_labels, which is off")
    return out


def smoothing_reads_scan(smooth: dict) -> bool:
    """Whether the smooth stage with these settings reads the scan it is given.

    It reads it for the scan's iso-surfaces, or to place the labels' faces before their fit.

    Parameters
    ----------
    smooth : dict
        The smooth stage's settings (``stage_kwargs(config, "smooth")``).

    Returns
    -------
    bool
    """
    return bool(smooth["surface_from_image"] or places_faces_by_scan(smooth))


def places_faces_by_scan(smooth: dict) -> bool:
    """Whether the labels' faces, given a scan, are placed by it before the fit.

    ``smooth.fit_to_scan`` places the faces' centres; with ``label_samples: relaxed`` the
    staircase is relaxed through those places.

    Parameters
    ----------
    smooth : dict
        The smooth section with every key (a loaded config's, or the stage's keyword arguments).

    Returns
    -------
    bool
        True where a scan given to the stage places the faces of the labels' fit.
    """
    return bool(smooth["fit_to_scan"] and smooth["surface_from_labels"])


def relaxes_staircase(smooth: dict, placed: bool) -> bool:
    """Whether the labels' fit takes their staircase relaxed within its voxels
    (``smooth.label_samples``: relaxed, or auto where no scan places the faces).

    Parameters
    ----------
    smooth : dict
        The smooth section with every key.
    placed : bool
        A scan places the labels' faces (:func:`places_faces_by_scan`, and the scan given).

    Returns
    -------
    bool
    """
    return smooth["label_samples"] == "relaxed" or (smooth["label_samples"] == "auto" and not placed)


SET_KINDS = ("planes", "materials", "interfaces", "exterior")
"""The kinds of node and element sets an export can write (``export.sets``)."""


def name_clash(names: list[str], sets=SET_KINDS) -> str | None:
    """Why material names would give two export sets one name, or None when every name is distinct.

    Solvers read names in upper case, so names are compared that way. An export names
    each material's element set and material after it, the faces of the exterior
    EXTERIOR_S1..S6 (the surface and node set EXTERIOR), of enclosed voids' walls CAVITIES_S1..S6
    (the surface and node set CAVITIES) and, by ``sets``, the node sets ``<a>_BOUNDARY`` (materials) and
    ``<a>_<b>`` for materials a before b (interfaces). Two of those clash when one
    string splits two ways at its underscores, as ``a_b`` + ``c`` and ``a`` + ``b_c``
    do; that is looked up through the names' prefixes, so the work follows the
    number of names and underscores, not the number of pairs.

    Parameters
    ----------
    names : list of str
        Label i is names[i - 1].
    sets : collection of str, optional
        The kinds of export sets written (of :data:`SET_KINDS`).

    Returns
    -------
    str or None
    """
    label: dict[str, int] = {}
    for i, name in enumerate(names, start=1):
        up = name.upper()
        if up in label:
            return (f"names {names[label[up] - 1]} and {name} differ only in case, and solvers read names "
                    "in upper case; rename one")
        label[up] = i
    if "exterior" in sets:
        for up, i in label.items():
            if up in {f"{surface}{tail}" for surface in ("EXTERIOR", "CAVITIES")
                      for tail in ("", *(f"_S{s}" for s in range(1, 7)))}:
                return f"name {names[i - 1]} is the name of an exterior face set; rename it"
    bound, inter = "materials" in sets, "interfaces" in sets
    if not inter:
        return None  # <a>_BOUNDARY are distinct for distinct names
    if bound and label.get("BOUNDARY", 1) > 1:
        first = names[0]
        return (f"the boundary of {first} and its interface with {names[label['BOUNDARY'] - 1]} would both be "
                f"{first}_BOUNDARY; rename {names[label['BOUNDARY'] - 1]}")
    # a string a_m_t read as a + (m_t) and as (a_m) + t: a, a_m and m_t are names, t is
    # BOUNDARY or a name; ``after[m]`` lists the names m_t
    after: dict[str, list[str]] = {}
    for up in label:
        for cut in (i for i, ch in enumerate(up) if ch == "_"):
            after.setdefault(up[:cut], []).append(up)
    for long_left, i_long in label.items():
        for cut in (i for i, ch in enumerate(long_left) if ch == "_"):
            left, middle = long_left[:cut], long_left[cut + 1 :]
            if left not in label:
                continue
            for right in after.get(middle, ()):
                if label[right] <= label[left]:
                    continue  # no interface set left_right: right comes first
                tail = right[len(middle) + 1 :]
                if tail == "BOUNDARY" and bound:
                    other = f"the boundary of {names[i_long - 1]}"
                elif tail in label and label[tail] > i_long:
                    other = f"the interface of {names[i_long - 1]} and {names[label[tail] - 1]}"
                else:
                    continue
                a, b = names[label[left] - 1], names[label[right] - 1]
                return (f"the interface of {a} and {b} and {other} would both be {a}_{b} in an export; "
                        "rename one of these materials")
    return None


def _label_keys(user: dict) -> dict:
    """``labels.map`` with its keys as strings: YAML reads ``3: brain`` with an integer key,
    JSON (the workflow's settings) and ``--set labels.map.3=brain`` with a string one, and
    both must give one config (and one config hash). Other keys become text too, so that the
    schema refuses them (``1.9: a`` was read as label 1, ``yes: a`` as label 1)."""
    section = user.get("labels")
    if isinstance(section, dict) and isinstance(section.get("map"), dict):
        section = dict(section)
        section["map"] = {(k if isinstance(k, str) else str(k)): v for k, v in section["map"].items()}
        user = {**user, "labels": section}
    return user


def load_config(path: str | Path | None = None, sets: list[str] | tuple = (), settings: dict | None = None,
                sets_named: str = "--set", properties_used: bool = False) -> dict:
    """The configuration: defaults <- YAML file <- ``settings`` <- ``--set`` items.

    Parameters
    ----------
    path : str or Path, optional
        A YAML configuration file.
    sets : sequence of str, optional
        ``--set`` items (:func:`parse_set`).
    settings : dict, optional
        Settings merged over the file.
    sets_named : str, optional
        What the ``sets`` are called in messages (a command's own option given as an item).
    properties_used : bool, optional
        The caller writes the materials' properties (a deck, materials.json): warn of listed
        materials that leave some out (:func:`materials_left_to_defaults`).

    Returns
    -------
    dict
        Validated, defaults filled in.

    Raises
    ------
    DicerError
        A bad file, item or key.
    """
    user: dict = {}
    source = "config"
    if path is not None:
        user = read_config_file(path)
        source = str(path)
    if settings:
        user = deep_merge(user, settings)
    for item in sets:
        user = deep_merge(user, parse_set(item))
        source = f"{source} with {sets_named}" if sets_named not in source else source
    user = _label_keys(user)
    validate(user, source)  # unknown keys and types, before defaults hide nothing
    if user.get("preset") is not None:  # under the user's own keys
        preset = preset_settings(user["preset"])
        _say_overridden_preset_keys(user["preset"], preset, user, source)
        user = deep_merge(preset, user)
    if properties_used:
        _say_defaulted_properties(user, source)
    config = _fill(copy.deepcopy(user), schema())
    return validate(config, source)


def preset_settings(name: str) -> dict:
    """The settings of a preset (``dicer/presets/<name>.yaml``, the schema's ``preset`` names).

    Parameters
    ----------
    name : str

    Returns
    -------
    dict
        Its sections, without defaults.
    """
    return read_config_file(Path(str(resources.files("dicer").joinpath("presets").joinpath(f"{name}.yaml"))))


def stage_settings(config: dict, stage: str) -> dict:
    """The part of a configuration a stage reads (see :data:`STAGE_SECTIONS` and :data:`STAGE_KEYS`).

    Parameters
    ----------
    config : dict
    stage : str
        A command name (``segment``, ``mesh``, ...).

    Returns
    -------
    dict
    """
    part = {k: copy.deepcopy(config[k]) for k in STAGE_SECTIONS[stage] if k in config}
    if stage in NAMES_ONLY and "materials" in part:
        part["materials"] = [{"name": m["name"]} for m in part["materials"]]
    for dotted in STAGE_KEYS.get(stage, ()):
        section, key = dotted.split(".")
        if key in config.get(section, {}):
            part.setdefault(section, {})[key] = copy.deepcopy(config[section][key])
    return part


def _plain(value):
    """``value`` as plain JSON types (a fresh copy): tuples become lists and numpy scalars
    Python numbers, so the schema checks library arguments as it checks a YAML file."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:  # numpy scalars
        return value.item()
    return value


def _stage_sections(config: dict, stage: str, source: str = "settings") -> dict:
    """The sections ``stage`` reads, each completed from the schema's defaults and validated."""
    config = _label_keys(config)
    sections = {}
    for name in STAGE_SECTIONS[stage]:
        node = _schema()["properties"][name]
        sections[name] = _fill(_plain(config[name]) if name in config else _defaults(node), node)
    # export.sets decide which material names clash; a stage that does not read them
    # checks the names for what holds whatever the sets (:func:`validate` did the rest)
    validate(sections if "export" in sections else {**sections, "export": {"sets": []}}, source)
    return sections


def _names(sections: dict) -> list[str]:
    return [m["name"] for m in sections["materials"]]


# The stage settings that segment's class cleaning takes; downsample cleans again with them.
_MORPHOLOGY = ("opening_radius", "closing_radius", "keep", "min_component_size", "priority")

#: sections -> keyword arguments of each stage's library function
_ADAPTERS = {
    "segment": lambda s: {"names": _names(s), **s["segment"]},
    "labels": lambda s: {"materials": s["materials"], "map": s["labels"]["map"], "drop": s["labels"]["drop"]},
    "downsample": lambda s: {"names": _names(s), **s["downsample"], **{k: s["segment"][k] for k in _MORPHOLOGY}},
    "fix": lambda s: {"names": {str(i): n for i, n in enumerate(_names(s), start=1)}, **s["fix"]},
    "mesh": lambda s: {"names": _names(s), **s["mesh"]},
    "merge": lambda s: dict(s["merge"]),
    "smooth": lambda s: dict(s["smooth"]),
    "export": lambda s: {"materials": s["materials"], **s["export"]},
    "quality": lambda s: {"names": _names(s), **s["quality"]},
}


def stage_kwargs(config: dict, stage: str, source: str = "settings") -> dict:
    """The keyword arguments of a stage's library function, from a configuration.

    The one path from settings to the stages: the command line, ``dicer run`` and the
    workflow's rules call every stage function with what this returns. Only the
    sections the stage reads (:data:`STAGE_SECTIONS`) are used; a key or section left
    out takes the schema's default (the schema is the only source of defaults and
    ranges), and the sections are validated against the schema.

    Parameters
    ----------
    config : dict
        A configuration, whole (as :func:`load_config` gives it) or partial.
    stage : str
        A stage name (``segment``, ``labels``, ``downsample``, ``fix``, ``mesh``,
        ``merge``, ``smooth``, ``export``, ``quality``).
    source : str, optional
        Named in error messages.

    Returns
    -------
    dict
        The stage's own section keys under their names (``labels``: ``map``, ``drop``),
        plus ``materials`` (export, labels) or the material ``names`` (segment,
        downsample, mesh: a list; fix: label value as a string -> name);
        ``downsample`` also takes segment's class-cleaning keys.

    Raises
    ------
    DicerError
        A bad key or value, named.
    """
    return _ADAPTERS[stage](_stage_sections(config, stage, source))


def _section_of(stage: str, key: str) -> str | None:
    """The section of ``stage`` whose key (or which itself) is named ``key``."""
    for name in STAGE_SECTIONS[stage]:
        node = _schema()["properties"][name]
        if name == key and node.get("type") != "object":
            return name
        if key in node.get("properties", {}):
            return name
    return None


def takes_settings(stage: str, section: bool = False):
    """Decorator of a stage function whose settings are keyword-only arguments without defaults.

    The decorated function may also be called the short way a library user or test
    writes: with a configuration (``section=True``: the stage's own section) as one
    more positional argument, and with settings left out. The settings given (as
    keywords, or in that dict) then go through :func:`stage_kwargs`, which checks them
    against the schema and completes them with its defaults, so the function body
    always receives every setting, checked.

    Parameters
    ----------
    stage : str
        The stage whose settings the function takes (:data:`STAGE_SECTIONS`).
    section : bool, optional
        The positional dict is the section named ``stage``, not a configuration.

    Returns
    -------
    callable
        The decorator.
    """
    def decorate(fn):
        params = inspect.signature(fn).parameters.values()
        n_positional = sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params)
        wanted = [p.name for p in params if p.kind == p.KEYWORD_ONLY and p.default is p.empty]
        optional = [p.name for p in params if p.kind == p.KEYWORD_ONLY and p.default is not p.empty]

        @functools.wraps(fn)
        def call(*args, **kwargs):
            config: dict = {}
            if len(args) > n_positional:
                # the short form: (data..., config[, the optional keywords in order])
                extra = args[n_positional + 1:]
                if len(extra) > len(optional):
                    raise TypeError(f"{fn.__name__}() takes at most {n_positional + 1 + len(optional)} positional "
                                    "arguments")
                for name, value in zip(optional, extra):
                    if name in kwargs:
                        raise TypeError(f"{fn.__name__}() got multiple values for argument {name!r}")
                    kwargs[name] = value
                given = args[n_positional] or {}
                config = {stage: given} if section else given
                args = args[:n_positional]
            derived = {}
            for key in [k for k in kwargs if k in wanted]:
                name = _section_of(stage, key)
                if name is None:
                    derived[key] = kwargs.pop(key)  # e.g. names, made from materials
                elif name == key:
                    config = {**config, key: kwargs.pop(key)}
                else:
                    config = deep_merge(config, {name: {key: kwargs.pop(key)}})
            settings = stage_kwargs(config, stage, f"{fn.__name__}()")
            settings.update(derived)
            return fn(*args, **{k: settings[k] for k in wanted}, **kwargs)

        return call

    return decorate


def for_label_volume(config: dict) -> dict:
    """``config`` for a label volume made elsewhere (an atlas).

    ``downsample.morphology`` left unset (null) becomes false: the segment section's opening
    and closing, made for the few classes of a scan, remove and regrow an atlas's small
    parcels; ``downsample.vote`` left unset becomes plurality: an atlas's label numbers
    order nothing.

    Parameters
    ----------
    config : dict
        A loaded configuration.

    Returns
    -------
    dict
        ``config`` itself when nothing changes, else a new dict (the input is not changed).
    """
    section = config.get("downsample", {})
    unset = {key: value for key, value in (("morphology", False), ("vote", "plurality")) if key in section
             and section[key] is None}
    if not unset:
        return config
    return {**config, "downsample": {**section, **unset}}


def downsample_applies(config: dict) -> bool:
    """Whether downsample.factor or downsample.voxel_size asks for a coarser grid: a label
    volume given to 'dicer run --labels' is downsampled only then, since the stage's
    morphology would otherwise reshape a segmentation the user already made.

    Parameters
    ----------
    config : dict
        A loaded configuration (its ``downsample`` section).

    Returns
    -------
    bool
    """
    ds = config["downsample"]
    return ds["voxel_size"] is not None or coarsening(ds["factor"])


def coarsening(factor) -> bool:
    """Whether downsample.factor (one value or one per axis) is other than 1 anywhere.

    Parameters
    ----------
    factor : int or list of int
        ``downsample.factor``.

    Returns
    -------
    bool
    """
    return any(f != 1 for f in (factor if isinstance(factor, list) else [factor]))


def config_hash(config: dict) -> str:
    """Short SHA-256 of the canonical JSON of a configuration (provenance in exported decks).

    Parameters
    ----------
    config : dict
        Any configuration or part of one.

    Returns
    -------
    str
        16 hex digits.
    """
    text = json.dumps(_canonical_numbers(config), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _canonical_numbers(value):
    """``value`` with every whole float written as an integer: ``1`` and ``1.0`` are one setting."""
    if isinstance(value, dict):
        return {k: _canonical_numbers(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical_numbers(v) for v in value]
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def unknown_materials(materials: list[str], priority, key: str) -> str | None:
    """What a priority list (``key``: ``fix.priority``, ``segment.priority``) names that the
    ``materials`` do not hold, as a message, or None.

    Parameters
    ----------
    materials : list of str
    priority : list of str or None
    key : str

    Returns
    -------
    str or None
    """
    unknown = [n for n in priority or [] if n not in materials]
    if not unknown:
        return None
    return (f"{key} names {', '.join(map(repr, unknown))}, which the materials do not hold (they are "
            f"{', '.join(materials)}); list material names")


def material_names(config: dict) -> dict[int, str]:
    """Class names by label value.

    Parameters
    ----------
    config : dict

    Returns
    -------
    dict of int to str
    """
    return {i + 1: m["name"] for i, m in enumerate(config["materials"])}
