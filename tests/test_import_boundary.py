"""The simulator stays behind its boundary: training code imports neither robosuite nor MuJoCo."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from capvector.workflows.launchers import GPU_DEVICE_FILES

REPO = Path(__file__).resolve().parents[1]
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


def test_a_recipe_reads_its_stages_and_status_without_lightning_or_a_needless_torch(
    tmp_path: Path,
) -> None:
    """`capvector recipe --status` of a recipe with ``${best_scale:...}`` (a sweep stage's λ):
    what the recipe does before and between its stages, in a process that may wait for days,
    imports no Lightning, and torch only to count GPUs on a machine with a GPU driver (~300 MB
    resident, seconds of every start)."""
    code = (
        "import sys\n"
        "from capvector.workflows.recipe import run\n"
        "run('configs/recipes/quick.yaml', ['run_dir=' + sys.argv[1]], status=True)\n"
        "print(sorted(m for m in ('torch', 'lightning') if m in sys.modules))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env,
                          capture_output=True, text=True, cwd=REPO)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "not started" in done.stdout
    gpu_driver = any(Path(path).exists() for path in GPU_DEVICE_FILES)
    assert done.stdout.splitlines()[-1] == ("['torch']" if gpu_driver else "[]")
