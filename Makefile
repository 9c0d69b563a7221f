# Every target sets itself up: a fresh clone needs only Python 3.11 and make.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test lint bench-render bench-storage clean

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

# MDS (mosaicml-streaming) needs torchvision, so the storage benchmark has its own environment:
# torch 2.14.1 + torchvision 0.29.1 (about 6 GB), kept apart from the project's.
.venv-bench/bin/.installed: pyproject.toml
	$(PYTHON) -m venv .venv-bench
	.venv-bench/bin/pip install --quiet --upgrade pip
	.venv-bench/bin/pip install --quiet -e '.[dev]' torch==2.14.1 torchvision==0.29.1 \
		mosaicml-streaming webdataset
	touch $@

bench-storage: .venv-bench/bin/.installed
	.venv-bench/bin/python -m benchmarks.storage

clean:
	rm -rf $(VENV) .venv-bench out .pytest_cache .ruff_cache
