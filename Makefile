# Set-up and entry points on a fresh machine with python3 (each target builds .venv as needed):
#   make demo     -- install NEMO (no viewer) and run the workflow on the bundled default config
#   make test     -- install NEMO + test tools + the napari viewer, run the test suite
#   make viewer   -- install the napari viewer (extra [napari]) for `nemo view`
# Each install step leaves a stamp file in .venv, so `make demo` then `make test` installs
# only what is still missing, and editing pyproject.toml reinstalls.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CORES  ?= 2
# --no-compile: pip would byte-compile every installed module (a third of the install time);
# Python compiles the modules actually imported on first use instead and caches them, unless
# PYTHONDONTWRITEBYTECODE is set (some machines' images set it): then every process, each of the
# workflow's jobs and the tests' commands, compiles snakemake, numpy, scipy, ... from source again
# (~4 s of a 6 s `snakemake -n`), so the targets below run without it.
unexport PYTHONDONTWRITEBYTECODE
# PYTHONWARNINGS=ignore: setuptools' notice about editable installs is not for users.
PIP    := $(BIN)/python -m pip --quiet --disable-pip-version-check
PIPI   := PYTHONWARNINGS=ignore $(PIP) install --no-compile

STAMP_CORE   := $(VENV)/.stamp-core
STAMP_NAPARI := $(VENV)/.stamp-napari
STAMP_TEST   := $(VENV)/.stamp-test

.PHONY: demo test test-slow test-slurm viewer install clean

$(BIN)/python:
	@echo "make: creating the virtualenv $(VENV)"
	@$(PYTHON) -m venv $(VENV) || { rm -rf $(VENV); \
	echo "make: cannot create a virtualenv with $(PYTHON) (Debian/Ubuntu: apt-get install python3-venv)"; exit 1; }
	@$(PIP) install --upgrade pip

$(STAMP_CORE): pyproject.toml | $(BIN)/python
	@echo "make: installing NEMO into $(VENV) (about 1-2 min on first run)..."
	@start=$$(date +%s); $(PIPI) -e . && touch $@ && \
	echo "make: NEMO installed in $$(( $$(date +%s) - start )) s"

$(STAMP_NAPARI): $(STAMP_CORE)
	@echo "make: installing the napari viewer (napari + PyQt6) into $(VENV) (about 1 min on first run)..."
	@start=$$(date +%s); $(PIPI) -e '.[napari]' && touch $@ && \
	echo "make: napari installed in $$(( $$(date +%s) - start )) s"

$(STAMP_TEST): $(STAMP_NAPARI)
	@echo "make: installing the test tools (pytest, hypothesis) into $(VENV)..."
	@$(PIPI) -e '.[test,napari]' && touch $@

install: $(STAMP_CORE)

viewer: $(STAMP_NAPARI)
	@echo "make: the viewer is ready: $(BIN)/nemo view results/demo"

demo: $(STAMP_CORE)
	@echo "make: running the workflow on config/config.yaml with $(CORES) cores (results/demo/)"
	$(BIN)/snakemake --cores $(CORES) --configfile config/config.yaml --rerun-incomplete
	@echo "make: done; figures in results/demo/summary/. To browse in 3D: make viewer, then $(BIN)/nemo view results/demo"

test: $(STAMP_TEST)
	$(BIN)/python -m pytest -n 2 --durations=20 tests

test-slow: $(STAMP_TEST)
	$(BIN)/python -m pytest -m slow tests

test-slurm: $(STAMP_TEST)
	bash tests/slurm/run_slurm_test.sh

clean:
	rm -rf results .snakemake
