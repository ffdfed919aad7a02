"""Log lines that stay readable for atlases with a hundred labels or more.

A stage's log line names its figures per material (volumes, voxel counts, islands
removed); the report files keep them all, the line keeps the first few.
"""

from __future__ import annotations

import json

__all__ = ["LIMIT", "brief_json", "brief_names"]

LIMIT = 8
"""Entries per mapping or list a log line shows."""


def _shorten(value, limit: int):
    if isinstance(value, dict):
        items = list(value.items())
        out = {str(k): _shorten(v, limit) for k, v in items[:limit]}
        if len(items) > limit:
            out["..."] = f"{len(items) - limit} more"
        return out
    if isinstance(value, (list, tuple)) and len(value) > limit:
        return [_shorten(v, limit) for v in value[:limit]] + [f"... {len(value) - limit} more"]
    if isinstance(value, (list, tuple)):
        return [_shorten(v, limit) for v in value]
    return value


def brief_json(value, limit: int = LIMIT, sort_keys: bool = False, whole_top: bool = False) -> str:
    """``value`` as JSON, every mapping and list cut to its first ``limit`` entries.

    Parameters
    ----------
    value : JSON-serialisable
    limit : int
        Entries kept per mapping or list; the rest are counted (``"...": "90 more"``).
    sort_keys : bool
        Sort mappings by key before cutting them (as ``json.dumps(sort_keys=True)``).
    whole_top : bool
        Keep every key of a top-level mapping (a report's own figures); cut what lies below.

    Returns
    -------
    str
    """
    if sort_keys:
        value = json.loads(json.dumps(value, sort_keys=True))
    if whole_top and isinstance(value, dict):
        return json.dumps({str(k): _shorten(v, limit) for k, v in value.items()})
    return json.dumps(_shorten(value, limit))


def brief_names(names, limit: int = LIMIT) -> str:
    """The first ``limit`` names joined by commas, then how many more."""
    names = [str(n) for n in names]
    text = ", ".join(names[:limit])
    return text + (f" and {len(names) - limit} more" if len(names) > limit else "")
