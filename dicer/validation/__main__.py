"""``python -m dicer.validation [--out DIR] [--work DIR]``: run the validation study (needs ccx),
write results.json, tables.md and the figures into DIR (default docs/validation)."""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from dicer.validation.figures import write_all
from dicer.validation.study import run_study


def main(argv: list[str] | None = None) -> int:
    """Run the validation study and write its results, tables and figures.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status, 0.
    """
    p = argparse.ArgumentParser(prog="python -m dicer.validation", description=__doc__)
    p.add_argument("--out", default="docs/validation", help="folder for results.json, tables.md and the PNGs")
    p.add_argument("--work", default=None, help="folder for the models and solver runs (default: a temporary one)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="dicer-validation-") as tmp:
        results = run_study(args.work or tmp)
    (out / "results.json").write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")
    tables = write_all(results, out)
    (out / "tables.md").write_text(tables)
    print(tables)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
