# mapserver — developer entry points. Python 3.11; torch pinned to the cached CPU build.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DB_URL ?= sqlite:///./var/mapserver.db
HOST   ?= 127.0.0.1
PORT   ?= 8000
BROKER ?= redis://127.0.0.1:6379/0
CLUSTER_DB ?= postgresql+psycopg://postgres@127.0.0.1:5432/test

.PHONY: install run cluster test lint bench clean browser

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

# the API (Celery jobs) and two workers on this machine's Redis and PostgreSQL; Ctrl-C stops all three
cluster: install
	mkdir -p var/cluster-uploads
	$(BIN)/mapserver db upgrade --db $(CLUSTER_DB)
	trap 'kill $$(jobs -p) 2>/dev/null; wait' EXIT INT TERM; \
	$(BIN)/mapserver worker --db $(CLUSTER_DB) --broker $(BROKER) --name w1@$$(hostname) & \
	$(BIN)/mapserver worker --db $(CLUSTER_DB) --broker $(BROKER) --name w2@$$(hostname) & \
	$(BIN)/mapserver serve --db $(CLUSTER_DB) --jobs celery --broker $(BROKER) --upload-dir $(CURDIR)/var/cluster-uploads \
		--host $(HOST) --port $(PORT) --allow-anonymous-reads

lint: install
	$(BIN)/ruff check .
	$(BIN)/mypy

# the viewer's browser tests drive the system's headless Chromium (Debian package; never a downloaded build)
CHROMIUM ?= /usr/bin/chromium
browser:
	@test -x $(CHROMIUM) || { [ "$$(id -u)" = 0 ] && apt-get update -qq && apt-get install -y -qq chromium >/dev/null; } \
		|| { echo "ERROR: $(CHROMIUM) missing; install the Debian package chromium (as root)" >&2; exit 1; }

test: install lint browser
	$(BIN)/python -m pytest -n 2 --durations=15

bench: install
	$(BIN)/python bench/core_throughput.py --preset irat --templates 1000
	$(BIN)/python bench/core_throughput.py --preset irat --templates 5000
	$(BIN)/python bench/core_throughput.py --preset irat --templates 20000
	$(BIN)/python bench/core_throughput.py --preset poseidon --templates 1000
	$(BIN)/python bench/store.py
	$(BIN)/python bench/api.py
	$(BIN)/python bench/generalisation.py --small --seeds 1 --families street,campus --jobs 1

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache .hypothesis
