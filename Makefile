# Two commands on a fresh machine: `make demo` runs the main job, `make test` runs the tests.
# Both create .venv and install everything first (idempotent: a stamp file skips a finished install).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
# The CPU wheel of torch lies on this machine's disk; elsewhere override, e.g. TORCH_SPEC="torch" for CUDA.
TORCH_SPEC ?= torch==2.13.0
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test test-float-paths test-slow check-install bench lint clean system-deps install

install: $(STAMP)

system-deps:
	@bash tools/ensure_system_deps.sh

$(STAMP): pyproject.toml | system-deps
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[dev,slurm,ray]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m pushtorch

# --dist loadscope: a module's tests share one worker, so its module fixtures (trained models, a tiny run) are made
# once rather than once per worker.
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadscope -q

# The numerical tests again with MKL pinned to the code paths other CPUs take (AVX-512 hosts round matmuls and
# reductions differently from AVX2 ones): a tolerance that holds on one host only fails here, on any host.
FLOAT_TESTS := tests/test_conditioning.py tests/test_kde.py tests/test_se3.py tests/test_anneal.py tests/test_distribution.py \
	tests/test_likelihood.py tests/test_fast_path.py tests/test_metrics.py
test-float-paths: $(STAMP)
	MKL_CBWR=COMPATIBLE $(PY) -m pytest -n 2 --dist loadscope -q $(FLOAT_TESTS)
	MKL_CBWR=AVX2 $(PY) -m pytest -n 2 --dist loadscope -q $(FLOAT_TESTS)

# A normal (non-editable) install in a fresh environment, at the declared lower bounds, run from outside the
# checkout: what CI runs after the tests (tools/check_install.sh).
check-install: $(STAMP)
	TORCH_SPEC="$(TORCH_SPEC)" PYTHON="$(PYTHON)" bash tools/check_install.sh

test-slow: $(STAMP)
	$(PY) -m pytest -m slow -q

bench: $(STAMP)
	$(PY) tools/bench_sim.py

lint: $(STAMP)
	$(VENV)/bin/ruff check pushtorch tests tools
	$(VENV)/bin/lint-imports

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
