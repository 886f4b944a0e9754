# mapserver — developer entry points. Python 3.11; torch pinned to the cached CPU build.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DB_URL ?= sqlite:///./var/mapserver.db
HOST   ?= 127.0.0.1
PORT   ?= 8000

.PHONY: install run test lint bench clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "ERROR: $(PYTHON) not found" >&2; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	mkdir -p var
	$(BIN)/mapserver db upgrade --db $(DB_URL)
	$(BIN)/mapserver demo --db $(DB_URL) --if-empty
	$(BIN)/mapserver serve --db $(DB_URL) --host $(HOST) --port $(PORT) --allow-anonymous-reads

lint: install
	$(BIN)/ruff check .

test: install lint
	$(BIN)/python -m pytest -n 2 --durations=15

bench: install
	$(BIN)/python bench/core_throughput.py --preset irat --templates 1000
	$(BIN)/python bench/core_throughput.py --preset irat --templates 5000
	$(BIN)/python bench/core_throughput.py --preset irat --templates 20000
	$(BIN)/python bench/core_throughput.py --preset poseidon --templates 1000
	$(BIN)/python bench/store.py
	$(BIN)/python bench/api.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis
