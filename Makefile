# Two commands do all the set-up on a fresh machine with python3:
#   make demo   -- build .venv if missing and run the workflow on the bundled default config
#   make test   -- build .venv if missing and run the test suite
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CORES  ?= 2

.PHONY: demo test test-slow test-slurm clean

$(BIN)/nemo: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,napari]'
	touch $(BIN)/nemo

demo: $(BIN)/nemo
	$(BIN)/snakemake --cores $(CORES) --configfile config/config.yaml --rerun-incomplete

test: $(BIN)/nemo
	$(BIN)/python -m pytest -n 2 tests

test-slow: $(BIN)/nemo
	$(BIN)/python -m pytest -m slow tests

test-slurm: $(BIN)/nemo
	bash tests/slurm/run_slurm_test.sh

clean:
	rm -rf results .snakemake
