# Two commands on a fresh machine: `make demo` (the draft's experiment, a ball dropped on a sofa,
# coarse variant) and `make test`.
# Each builds .venv first when it is missing or when the pins changed.
VENV    := .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
OUT     ?= out/demo
SCENE   ?= scenes/ball_sofa_coarse.toml
# the demo's ranks: 2 where the machine has 2 cores (its body and shell stages overlap), else 1
RANKS   ?= $(shell [ "$$(nproc 2>/dev/null || echo 1)" -ge 2 ] && echo 2 || echo 1)
PYTEST_ARGS ?=
# the suite's workers (pytest-xdist), one per core; a module's cases stay on one worker
TEST_JOBS ?= $(shell nproc 2>/dev/null || echo 1)
export OMP_NUM_THREADS ?= 1
export OPENBLAS_NUM_THREADS ?= 1
export NUMBA_CACHE_DIR ?= $(CURDIR)/.cache/numba
# the code's bytecode, written before a run even where PYTHONDONTWRITEBYTECODE is set (as in
# many containers): else every process and rank compiles ~100 modules again (0.4 s each)
BYTECODE := $(PY) -m compileall -q -j 0 models solvers meshes wrinkles validation benchmarks

.PHONY: venv demo test test-all lint typecheck bench paper clean lock

venv: $(STAMP)

$(STAMP): requirements.lock pyproject.toml tools/find_python.sh
	@set -e; py=$$(tools/find_python.sh); \
	echo "creating $(VENV) with $$py"; \
	[ -x $(PY) ] || $$py -m venv $(VENV); \
	$(PY) -m pip install -q --upgrade pip; \
	$(PY) -m pip install -q -r requirements.lock; \
	$(PY) -m pip install -q --no-deps --no-build-isolation -e .; \
	touch $(STAMP)

demo: $(STAMP)
	@$(BYTECODE)
	$(VENV)/bin/mpiexec -n $(RANKS) $(VENV)/bin/wrinkles run $(SCENE) --out $(OUT) --overwrite
	$(VENV)/bin/wrinkles view $(OUT)
	$(VENV)/bin/wrinkles plot $(OUT)

test: $(STAMP)
	@$(BYTECODE)
	$(PY) -m pytest -m "not slow" -n $(TEST_JOBS) --dist loadscope $(PYTEST_ARGS)

test-all: $(STAMP)
	@$(BYTECODE)
	$(PY) -m pytest -n $(TEST_JOBS) --dist loadscope $(PYTEST_ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check models solvers meshes wrinkles validation tests benchmarks paper tools
	$(VENV)/bin/mypy

bench: $(STAMP)
	@$(BYTECODE)
	$(PY) benchmarks/shell_kernels.py
	$(PY) benchmarks/shell_solve.py
	$(PY) benchmarks/two_way.py

# Regenerate figures, tables and paper/build/paper.md (PAPER_ARGS=--quick for CI; see paper/README.md)
PAPER_ARGS ?=
paper: $(STAMP)
	@$(BYTECODE)
	$(PY) paper/make_paper.py $(PAPER_ARGS)

lock: $(STAMP)
	$(PY) -m pip freeze --exclude-editable | grep -v '^wrinkles' > requirements.lock.new && mv requirements.lock.new requirements.lock

clean:
	rm -rf out .cache .pytest_cache
