# pugsd: the two set-up commands are `make demo` and `make test` (each sets up .venv on a fresh machine).
VENV ?= .venv
PY := $(VENV)/bin/python
BIN := $(VENV)/bin

.PHONY: demo test test-all lint bench evaluate setup clean

$(VENV)/.installed: pyproject.toml tools/setup-env
	./tools/setup-env $(VENV)
	touch $@

setup: $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/pugsd demo

lint: $(VENV)/.installed
	$(BIN)/ruff check pugsd tests tools
	$(BIN)/mypy pugsd

test: lint
	OMP_NUM_THREADS=1 $(BIN)/pytest -m "not slow and not gpu" -q

test-all: lint
	OMP_NUM_THREADS=1 $(BIN)/pytest -q

bench: $(VENV)/.installed
	$(BIN)/pugsd bench --json bench-results.json

evaluate: $(VENV)/.installed
	$(BIN)/pugsd evaluate --json results/results.json --figures results/figures

clean:
	rm -rf $(VENV) build *.egg-info
