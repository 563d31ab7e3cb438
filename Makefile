# Two commands work on a fresh machine: `make demo` and `make test` (both create the venv first).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv test demo bench lint clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

test: venv
	$(PY) -m pytest -q tests

demo: venv
	$(PY) -m wrinkle_jax.cli demo --out outputs/demo

bench: venv
	@for f in benchmarks/bench_*.py; do echo "== $$f"; $(PY) $$f || exit 1; done

lint: venv
	$(VENV)/bin/ruff check wrinkle_jax tests benchmarks experiments

clean:
	rm -rf $(VENV) outputs .pytest_cache .ruff_cache
