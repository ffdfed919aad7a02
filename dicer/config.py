"""Configuration: schema defaults, YAML files, ``--set`` overrides, validation.

A configuration is a nested dict. Its schema (``dicer/schemas/config.schema.yaml``)
gives every key a default, so ``load_config()`` with no arguments is valid.
"""

from __future__ import annotations

import copy
import hashlib
import json
from importlib import resources
from pathlib import Path

import jsonschema
import yaml

from dicer.errors import DicerError

# The config sections each stage reads; the workflow passes exactly these to a rule
# through ``params:`` so that editing one section re-runs only the stages that read it.
STAGE_SECTIONS = {
    "segment": ("image", "materials", "segment"),
    "downsample": ("materials", "segment", "downsample"),
    "fix": ("materials", "fix"),
    "mesh": ("mesh",),
    "merge": ("merge",),
    "smooth": ("smooth",),
    "export": ("materials", "export"),
    "quality": ("quality",),
}


def schema() -> dict:
    """The configuration JSON Schema as a dict."""
    text = resources.files("dicer").joinpath("schemas/config.schema.yaml").read_text()
    return yaml.safe_load(text)


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


def default_config() -> dict:
    """Every key at its schema default."""
    return _fill({}, schema())


def deep_merge(base: dict, override: dict) -> dict:
    """A copy of ``base`` with ``override`` merged in (dicts merge, anything else replaces)."""
    out = copy.deepcopy(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_set(item: str, source: str = "--set") -> dict:
    """``a.b.c=VALUE`` -> ``{"a": {"b": {"c": VALUE}}}``; VALUE is read as YAML (``[1,1,1]``, ``0.8``, ``otsu``)."""
    if "=" not in item:
        raise DicerError(f"{source} {item!r}: expected KEY=VALUE, e.g. smooth.coefficient=0.8")
    key, _, text = item.partition("=")
    parts = key.strip().split(".")
    if not all(parts):
        raise DicerError(f"{source} {item!r}: empty key part; use dotted keys like export.order=2")
    try:
        value = yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError as exc:
        raise DicerError(f"{source} {item!r}: value is not valid YAML ({exc.problem}); quote strings") from None
    out: dict = {}
    node = out
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def read_config_file(path: str | Path) -> dict:
    """Read a YAML configuration file (no defaults, no validation)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DicerError(f"{path}: config file not found; check the path given to --config") from None
    except OSError as exc:
        raise DicerError(f"{path}: cannot read config file ({exc.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise DicerError(f"{path}: not valid YAML{where}; fix the syntax") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DicerError(f"{path}: a config file must be a YAML mapping of sections (materials:, segment:, ...)")
    return data


def _key_path(error: jsonschema.ValidationError) -> str:
    return ".".join(str(p) for p in error.absolute_path) or "(top level)"


def validate(config: dict, source: str = "config") -> dict:
    """Validate ``config`` against the schema; raise DicerError naming the first bad key."""
    validator = jsonschema.Draft202012Validator(schema())
    errors = sorted(validator.iter_errors(config), key=lambda e: (len(list(e.absolute_path)), e.message))
    if errors:
        err = errors[0]
        if err.validator == "additionalProperties":
            extra = sorted(set(err.instance) - set(err.schema.get("properties", {})))
            where = _key_path(err)
            name = f"{where}.{extra[0]}" if where != "(top level)" else extra[0]
            known = ", ".join(sorted(err.schema.get("properties", {}))) or "none"
            raise DicerError(f"{source}: unknown key '{name}'; known keys here: {known}")
        raise DicerError(f"{source}: key '{_key_path(err)}': {err.message}")
    names = [m["name"] for m in config.get("materials", [])]
    if len(set(names)) != len(names):
        raise DicerError(f"{source}: key 'materials': class names must be unique, got {names}")
    return config


def load_config(path: str | Path | None = None, sets: list[str] | tuple = (), settings: dict | None = None) -> dict:
    """Defaults <- YAML file <- ``settings`` dict <- ``--set`` items; validated, defaults filled."""
    user: dict = {}
    source = "config"
    if path is not None:
        user = read_config_file(path)
        source = str(path)
    if settings:
        user = deep_merge(user, settings)
    for item in sets:
        user = deep_merge(user, parse_set(item))
        source = f"{source} with --set" if "--set" not in source else source
    validate(user, source)  # unknown keys and types, before defaults hide nothing
    config = _fill(copy.deepcopy(user), schema())
    return validate(config, source)


def stage_settings(config: dict, stage: str) -> dict:
    """The part of ``config`` that ``stage`` reads (see STAGE_SECTIONS)."""
    return {k: copy.deepcopy(config[k]) for k in STAGE_SECTIONS[stage] if k in config}


def config_hash(config: dict) -> str:
    """Short SHA-256 of the canonical JSON of ``config`` (provenance in exported decks)."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def material_names(config: dict) -> dict[int, str]:
    """Label value -> class name."""
    return {i + 1: m["name"] for i, m in enumerate(config["materials"])}
