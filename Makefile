# The two commands: `make demo` and `make test`. Both create .venv on first use.
# `make lint`: the format, lint and type checks that CI runs before the tests.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | md5sum | cut -c1-8)

.PHONY: test lint demo install bench clean notebooks

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 tests

# ruff and pyright take their settings from pyproject.toml ([tool.ruff], [tool.pyright]).
lint: $(STAMP)
	$(BIN)/ruff format --check
	$(BIN)/ruff check
	$(BIN)/pyright

demo: $(STAMP)
	$(BIN)/llrmpp demo --out runs/demo

# Long: runs the ablation notebooks at the cpu scale (each table under an hour on 2 cores;
# about 2-3 hours for the four) and saves them with outputs. SCALE=smoke for a quick look.
notebooks: $(STAMP)
	JAX_COMPILATION_CACHE_DIR=$${JAX_COMPILATION_CACHE_DIR:-$$HOME/.cache/llrmpp-xla} \
	  $(BIN)/python notebooks/_execute.py --scale $${SCALE:-cpu} $(NOTEBOOKS)

clean:
	rm -rf $(VENV) runs .pytest_cache
