# The two commands of the README. Both create or reuse .venv and install what they need.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)

.PHONY: run test lint bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,plots]'
	rm -f $(VENV)/.installed-* && touch $@

# The main job on the embedded default: the daemon, headless, on the simulated floor.
run: $(STAMP)
	$(BIN)/kmead --headless --frames $${FRAMES:-300} --log out/run.csv

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n 2 $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/kmea bench

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
