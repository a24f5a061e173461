# Two entry points for a fresh machine (see README.md):
#   make demo   installs gdiff into .venv, then runs the whole workflow on the built-in demo scene
#   make test   installs gdiff into .venv, then runs the test suite
VENV ?= .venv
PYTHON ?= python3
# The CPU build of torch; override for CUDA, e.g. `make demo TORCH=torch`.
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin

.PHONY: demo test install clean-results

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/python -m pip install --quiet "$(TORCH)"
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(BIN)/python -c "from gdiff.splat import csrc; csrc.load()"  # build the CPU kernels once (torch fallback without a compiler)
	touch $@

demo: install
	$(BIN)/snakemake --cores 2

test: install
	$(BIN)/python -c "from gdiff.splat import csrc; csrc.load(required=True)"  # (re)build after edits
	$(BIN)/python -m pytest -q -n 2 --durations=15

clean-results:
	rm -rf results logs resources .snakemake
