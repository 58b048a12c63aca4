# The two commands a user needs (see README.md):
#   make demo   render the built-in Cornell box with 8 partitioned photon maps
#   make test   run the test suite
# Both create .venv/ on first use, install the package with its test extras, make sure a shared
# libLLVM >= 16 is present for Dr.Jit's LLVM backend, and run with DRJIT_LIBLLVM_PATH set.
# A second run reuses the environment: it reinstalls only when pyproject.toml or
# constraints.txt (the pinned versions of every package) changes.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.mi-partpm-installed
OUT    ?= out

# Evaluated only by the recipes that use it (recursive '='), so 'make help' installs nothing.
LLVM    = $(shell sh tools/libllvm.sh)
RUN_ENV = DRJIT_LIBLLVM_PATH="$(LLVM)"

.PHONY: demo test figures install llvm help clean

help:
	@echo "make demo   render the built-in cornell_box (480x480, 10^5 photons, 8 maps) to $(OUT)/"
	@echo "make test   run the test suite"
	@echo "make figures  rerun what the README's tables and figures and the notebooks come"
	@echo "              from (reusing runs of the same code and settings) and rewrite them;"
	@echo "              FIGURES_ARGS='--list' (or '--only bench') passes options"

$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]' -c constraints.txt
	@touch $(STAMP)

install: $(STAMP)

llvm:
	@test -n "$(LLVM)" || { echo "no usable libLLVM (see the message above)"; exit 1; }
	@echo "libLLVM: $(LLVM)"

demo: install llvm
	@mkdir -p $(OUT)
	$(RUN_ENV) $(BIN)/partpm render cornell_box --maps 8 --photons 100000 \
		--resolution 480x480 -o $(OUT)/cornell_box.exr

test: install llvm
	$(RUN_ENV) $(BIN)/python -m pytest -q $(PYTEST_ARGS)

# Every table and figure of README.md and the notebooks from the current code: the runs go
# to out/figures/ (one folder per step, reused when made by the same code and settings),
# the plots to docs/images/, the provenance to docs/figures.json (partpm figures --help).
figures: install llvm
	$(RUN_ENV) $(BIN)/partpm figures $(FIGURES_ARGS)

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
