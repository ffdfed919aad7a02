#!/bin/sh
# Snakemake runs this in the environment it has just made from environment.yml (--sdm conda):
# install dicer from the checkout the workflow runs from, without dependencies (conda has them).
set -eu
if [ -z "${DICER_SOURCE:-}" ] || [ ! -f "$DICER_SOURCE/pyproject.toml" ]; then
    echo "error: DICER_SOURCE (the dicer checkout, set by its Snakefile) is not set or holds no pyproject.toml;" \
         "run the workflow with the project's Snakefile" >&2
    exit 2
fi
python -m pip install --no-deps --no-build-isolation --quiet -e "$DICER_SOURCE"
