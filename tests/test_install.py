"""`pip install capvector[lerobot]` without the sim extra, as a cluster's training nodes install it:
numpy 2, no robosuite or MuJoCo, and `capvector fit` trains from a LeRobot v3 folder.

It builds a fresh environment (minutes: torch's wheels are large), so it runs only when ``-m``
names it, as `make test` does (``-m "install or not install"``, on its own xdist worker)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from conftest import write_demo_file
from test_lerobot import CAMERAS, write_lerobot_v3

pytestmark = pytest.mark.install

ROOT = Path(__file__).resolve().parents[1]
STEPS = 2
SIM_MISSING = (
    r"the simulator needs the sim extra: pip install 'capvector\[sim\]' "
    r"\(No module named '(mujoco|robosuite)'\)"
)


def _run(*args: str | Path, ok: bool = True) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MUJOCO_GL")}
    env["OMP_NUM_THREADS"] = "1"
    done = subprocess.run([str(a) for a in args], env=env, capture_output=True, text=True)
    if ok:
        assert done.returncode == 0, done.stderr[-3000:]
    return done


@pytest.fixture(scope="module")
def venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A new environment with capvector[lerobot] at the verified versions, and no simulator;
    PyAV as LeRobot 0.4 pins it (av>=15,<16), older than the test suite's own, so the LeRobot
    reader runs on a PyAV before 17 too (17 added threaded conversion and its `threads`)."""
    venv = tmp_path_factory.mktemp("install") / "venv"
    _run(sys.executable, "-m", "venv", venv)
    # --no-compile: byte-compiling all of torch and transformers added ~3 min to the install here
    # (setup 394 s -> 216 s); the commands below compile only what they import.
    _run(venv / "bin/python", "-m", "pip", "install", "--quiet", "--no-compile",
         "-c", ROOT / "constraints.txt", f"{ROOT}[lerobot]", "av>=15,<16")  # fmt: skip
    return venv


def test_without_the_sim_extra_numpy_is_2_and_the_simulator_absent(venv: Path) -> None:
    version = _run(venv / "bin/python", "-c", "import numpy; print(numpy.__version__)").stdout
    assert int(version.split(".")[0]) >= 2, version
    version = _run(venv / "bin/python", "-c", "import av; print(av.__version__)").stdout
    assert version.startswith("15."), version
    for simulator in ("robosuite", "mujoco"):
        done = _run(venv / "bin/python", "-c", f"import {simulator}", ok=False)
        assert f"No module named '{simulator}'" in done.stderr


def test_fit_trains_from_a_lerobot_folder_without_the_simulator(venv: Path, tmp_path: Path) -> None:
    write_lerobot_v3(tmp_path / "lerobot")  # with this environment's pyarrow and PyAV
    out = tmp_path / "runs"
    _run(
        venv / "bin/capvector", "fit", "--trainer.accelerator=cpu", f"--trainer.max_steps={STEPS}",
        "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={out}",
        "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={out}", "--trainer.logger.init_args.name=fit",
        "--model.backbone=openvla-oft-tiny", f"--data.lerobot_root={tmp_path / 'lerobot'}",
        f"--data.cameras=[{','.join(CAMERAS)}]", "--data.proprio_keys=[observation.state]",
        "--data.chunk_size=3", "--data.batch_size=4",
    )  # fmt: skip
    (checkpoint,) = (out / "fit/version_0/checkpoints").glob("*.ckpt")
    assert torch.load(checkpoint, weights_only=False)["global_step"] == STEPS


def test_the_simulators_commands_name_the_sim_extra(venv: Path, tmp_path: Path) -> None:
    done = _run(venv / "bin/capvector", "demos", "--task", "Lift", "--episodes", "1", "--out",
                tmp_path / "lift.hdf5", ok=False)  # fmt: skip
    assert done.returncode == 2
    assert re.fullmatch(f"capvector demos: error: {SIM_MISSING}\n", done.stderr), done.stderr
    assert not (tmp_path / "lift.hdf5").exists()


def test_rollout_validation_names_the_sim_extra_before_the_run(venv: Path, tmp_path: Path) -> None:
    write_demo_file(tmp_path / "demos.hdf5")
    out = tmp_path / "runs"
    done = _run(
        venv / "bin/capvector", "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=1",
        f"--trainer.default_root_dir={out}", "--model.backbone=openvla-oft-tiny",
        f"--data.train_files=[{tmp_path / 'demos.hdf5'}]", "--data.eval_tasks=[{task: Lift}]",
        ok=False,
    )  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.splitlines()[-1] == (
        "capvector fit: error: rollout validation (data.eval_tasks) needs the sim extra: "
        "pip install 'capvector[sim]' (No module named 'mujoco')"
    )
    assert not out.exists()
