# Two commands work on a fresh machine: `make demo` and `make test` (both create the venv first).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv test demo bench lint clean eval report

venv: $(STAMP)

# The install uses uv (itself a PyPI package, installed by pip into the venv) when it can: on a
# fresh 2-core machine with empty caches it took 12 s of CPU against pip's 39 s for the same
# packages and versions. Plain pip is the fallback when uv cannot be installed or fails.
# uv does not precompile bytecode (--compile-bytecode would cost 20 s of CPU for every module
# of every package); the modules that are imported are compiled once, on first import, which
# is why the recipes below must be allowed to write .pyc files (see unexport).
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	if $(PY) -m pip install --quiet uv && \
	   $(VENV)/bin/uv pip install --quiet --python $(PY) -e ".[dev]"; then :; else \
	  echo "uv unavailable: installing with pip"; \
	  $(PY) -m pip install --quiet --upgrade pip && $(PY) -m pip install --quiet -e ".[dev]"; fi
	touch $(STAMP)

# Without .pyc files on disk every Python process (pytest's workers, the notebook kernels, the
# tests' subprocesses) would compile jax, scipy & co. from source again: ~5 s of CPU each.
unexport PYTHONDONTWRITEBYTECODE

# The suite runs on every core (pytest-xdist); a file's tests stay on one worker so that its
# module fixtures are built once, and files start in collection order (tests/conftest.py puts
# the longest first). TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= auto
test: venv
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder tests

demo: venv
	$(PY) -m wrinkle_jax.cli demo --out outputs/demo

# bench_reference.py times the authors' PyTorch code beside ours: it runs only with
# AUTHORS_REPO=PATH (their public repository) and torch installed (pip install -e .[reference]).
bench: venv
	@for f in benchmarks/bench_*.py; do \
	  if [ "$$f" = benchmarks/bench_reference.py ]; then \
	    if [ -z "$(AUTHORS_REPO)" ]; then \
	      echo "== $$f skipped (needs AUTHORS_REPO=PATH and torch)"; continue; fi; \
	    echo "== $$f"; $(PY) $$f --authors-repo "$(AUTHORS_REPO)" \
	      --train-impls im2col_bf16 winograd_bf16 \
	      || exit 1; continue; fi; \
	  echo "== $$f"; $(PY) $$f || exit 1; done

# The evaluation suite on the shipped model (hours on 2 cores; each step resumes or reuses
# what is stored), then experiments/results/REPORT.md. The PatchGAN and sheet-only rows need
# the training data first (see the README's experiments section).
eval: venv
	$(PY) -m experiments.table1
	$(PY) -m experiments.table2
	$(PY) -m experiments.stride
	$(PY) -m experiments.temporal --frames 30
	$(PY) -m experiments.timing --frames 30 --model wrinkle_jax/assets/enhancer.npz
	mkdir -p experiments/results/lift
	$(PY) benchmarks/bench_lift.py --quick > experiments/results/lift/bench.json
	$(PY) benchmarks/bench_sim.py --quick --part substeps > experiments/results/sim/substeps.json
	$(PY) -m experiments.report

report: venv
	$(PY) -m experiments.report

lint: venv
	$(VENV)/bin/ruff check wrinkle_jax tests benchmarks experiments notebooks

clean:
	rm -rf $(VENV) outputs .pytest_cache .ruff_cache
