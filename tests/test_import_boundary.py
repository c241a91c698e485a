"""The simulator stays behind its boundary: training code imports neither robosuite nor MuJoCo."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

TRAINING_MODULES = [
    "capvector.module",
    "capvector.data.datamodule",
    "capvector.cli",
    "capvector.callbacks",
    "capvector.vectors",
    "capvector.sim",
    "capvector.eval",
    "capvector.eval.episodes",
    "capvector.eval.policy",
    "capvector.eval.results",
    "capvector.training.resume",
    "capvector.serve.cli",
    "capvector.serve.server",
]


@pytest.mark.parametrize("module", TRAINING_MODULES)
def test_importing_training_code_loads_no_simulator(module: str) -> None:
    code = (
        f"import os, sys, {module}\n"
        "heavy = sorted(m for m in ('robosuite', 'mujoco') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
        "assert 'MUJOCO_GL' not in os.environ, 'importing set MUJOCO_GL'\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
