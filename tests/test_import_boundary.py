"""The simulator stays behind its boundary: training code imports neither robosuite nor MuJoCo."""

from __future__ import annotations

import os
import subprocess
import sys

TRAINING_MODULES = [
    "capvector.module",
    "capvector.data.datamodule",
    "capvector.cli",
    "capvector.callbacks",
    "capvector.vectors",
    "capvector.envs",
    "capvector.eval",
    "capvector.envs.base",
    "capvector.envs.robosuite.spec",
    "capvector.envs.libero.spec",
    "capvector.envs.robosuite.suite",
    "capvector.envs.libero.suite",
    "capvector.policy",
    "capvector.eval.results",
    "capvector.training.resume",
    "capvector.workflows.serve",
    "capvector.serve.server",
]


def test_importing_training_code_loads_no_simulator() -> None:
    """The modules one after another in one fresh interpreter, not one each (13 starts of torch):
    an import only adds modules, so none loading the simulator together means none alone, and the
    first that loads it is named."""
    code = (
        "import importlib, os, sys\n"
        f"for module in {TRAINING_MODULES!r}:\n"
        "    importlib.import_module(module)\n"
        "    heavy = sorted(m for m in ('robosuite', 'mujoco') if m in sys.modules)\n"
        "    assert not heavy, f'importing {module} loaded {heavy}'\n"
        "    assert 'MUJOCO_GL' not in os.environ, f'importing {module} set MUJOCO_GL'\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
