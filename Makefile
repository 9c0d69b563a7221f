# Every target sets itself up: a fresh clone needs only Python 3.11 and make.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test lint bench-render clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

# The main job on the embedded default: render one procedural material under 5 suns.
demo: $(BIN)/.installed
	$(BIN)/farm preview --material procedural --suns 5 --resolution 256 --samples 64 --out out/preview

test: $(BIN)/.installed lint
	$(BIN)/pytest -q

lint: $(BIN)/.installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench-render: $(BIN)/.installed
	$(BIN)/python -m benchmarks.render

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
