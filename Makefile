# Every target bootstraps .venv on first use; nothing needs to be installed beforehand.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export JAX_PLATFORMS ?= cpu
# Compiled XLA programs are reused across test processes and reruns.
export JAX_COMPILATION_CACHE_DIR ?= $(CURDIR)/.cache/jax
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS ?= 2

.PHONY: demo test lint bench lock clean

# The tested versions (constraints.txt); `make test CONSTRAINTS=` takes the newest releases.
CONSTRAINTS ?= constraints.txt
PIN := $(if $(CONSTRAINTS),-c $(CONSTRAINTS))

$(STAMP): pyproject.toml $(CONSTRAINTS)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(PIN) -e ".[dev]"
	# ROS 2 wheels exist for x86_64 Linux only; elsewhere the live-node test skips.
	$(PY) -m pip install -q $(PIN) -e ".[dev,ros]" || echo "ROS 2 wheels not installable here: tests/test_ros2.py will skip its live test"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) experiments/demo.py --out demo_out

# Two worker processes, one per test file at a time: the suite is compile-bound and XLA
# compiles on one thread. TEST_WORKERS=0 runs everything in this process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile tests

lint: $(STAMP)
	$(PY) -m ruff check src sim experiments tests
	$(PY) -m ruff format --check src sim experiments tests

# Benchmark-only: the PyTorch peer needs torch (a CPU wheel of 2.13.0 ships with these
# machines); bench_lidar compares with mujoco-lidar when it is installed and says so if not.
bench: $(STAMP)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	for b in experiments/bench_*.py; do $(PY) $$b || exit 1; done

# Newest releases into a scratch venv, frozen into constraints.txt (then run make test).
LOCK_VENV := .cache/lock-venv
lock:
	rm -rf $(LOCK_VENV)
	$(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/python -m pip install -q --upgrade pip
	$(LOCK_VENV)/bin/python -m pip install -q -e ".[dev,ros]"
	sed -n '/^#/p' constraints.txt > constraints.txt.tmp
	$(LOCK_VENV)/bin/python -m pip freeze --exclude-editable >> constraints.txt.tmp
	mv constraints.txt.tmp constraints.txt
	rm -rf $(LOCK_VENV)

clean:
	rm -rf $(VENV) demo_out .pytest_cache .cache
