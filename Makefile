# Two entry points for a fresh Debian/Ubuntu machine with Python >= 3.11:
#   make demo   set up, then run the workflow on the demo cohort (config/patients.tsv)
#   make test   set up, then run the whole test suite
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
CORES  ?= 2
SUDO    = $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: setup system demo test test-all bench bench-stages clean

# System packages: the CalculiX solver (tests run it) and venv support; Chromium, with which
# the tests open the Snakemake report as a reader would (optional: without it they check the
# report's HTML only).
system:
	@if ! command -v ccx >/dev/null 2>&1 || ! $(PYTHON) -c 'import ensurepip' >/dev/null 2>&1; then \
	  echo "installing system packages: calculix-ccx python3-venv"; \
	  $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq calculix-ccx python3-venv >/dev/null; \
	fi
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "installing system package: chromium (headless, for the report test)"; \
	  ( $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null ) \
	    || echo "chromium could not be installed: the report test checks the HTML only"; \
	fi

# the libraries at the versions of constraints.txt: the same bytes from the same input a year later
$(BIN)/dicer: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e '.[test,slurm]'
	@# bytecode now, as a regular install makes it: where PYTHONDONTWRITEBYTECODE is set, every
	@# dicer process would otherwise compile the package from source (0.1-0.2 s each)
	$(BIN)/python -m compileall -q dicer
	@touch $@

setup: system $(BIN)/dicer

demo: setup
	$(BIN)/snakemake --cores $(CORES) --workflow-profile workflow/profiles/local

# on CORES worker processes (pytest-xdist): 5.2 min on 2 cores where one process takes 8.9
test: setup
	$(BIN)/python -m pytest -q -n $(CORES)

# the slow cases too (real-data end-to-end runs, large volumes)
test-all: setup
	$(BIN)/python -m pytest -q -n $(CORES) -m ''

# whole processes, dicer's commands beside automesh's, at 64^3, 128^3 and 256^3, the
# fastest of three runs each (a shared or virtual machine varies by a quarter run to run);
# make bench BENCH_ARGS='--sizes 64,128,256,512' adds 512^3 (long; about 24 GB)
BENCH_ARGS ?= --repeat 3
bench: setup
	$(BIN)/pip install -q -c constraints.txt -e '.[test,bench]'
	$(BIN)/python -m bench --processes $(BENCH_ARGS)

# the stages' library functions, each in its own process, beside PyVista, meshio and automesh
bench-stages: setup
	$(BIN)/pip install -q -c constraints.txt -e '.[test,bench]'
	$(BIN)/python -m bench

clean:
	rm -rf results logs benchmarks .snakemake
