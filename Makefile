# The two entry points: `make demo` (the main job on the embedded default) and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
CAPVECTOR := $(VENV)/bin/capvector
# Headless MuJoCo rendering on CPU through Mesa's EGL.
export MUJOCO_GL ?= egl

DEMOS := data/demos/lift_debug.hdf5

.PHONY: demo test lint format clean

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	# DeepSpeed (only its configs are checked here; it needs GPUs to run) imports torch in its
	# setup.py, so it is built against the installed torch, without build isolation.
	$(PY) -m pip install --quiet --no-build-isolation "deepspeed==0.19.8"
	touch $@

$(DEMOS): | $(VENV)/.installed
	$(CAPVECTOR) demos --task Lift --episodes 20 --image-size 64 --seed 10000 --out $@

demo: $(VENV)/.installed $(DEMOS)
	$(CAPVECTOR) fit --config configs/debug.yaml

test: $(VENV)/.installed
	$(PY) -m pytest -q

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format: $(VENV)/.installed
	$(VENV)/bin/ruff format . && $(VENV)/bin/ruff check --fix .

clean:
	rm -rf runs data/demos
