"""A real `capvector fit` of ``openvla-oft-mini`` with its YAML (issue 59, item 3): stopped after
a step as a killed session is, resumed from its checkpoint, it logs the uninterrupted run's losses
and exports its weights to the bit; the checkpoint and the export stay within the 25 MB a fit may
commit; `capvector evaluate` and the server load the LoRA-form export.

Opt-in (``-m mini``): three fit processes of the whole preset, minutes on this CPU.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from conftest import write_demo_file

pytestmark = [pytest.mark.mini, pytest.mark.sim]

REPO = Path(__file__).resolve().parents[3]
TESTS = REPO / "tests"
BUDGET = 25 * 2**20
STEPS, STOP = 4, 2


def fit(root: Path, data: Path, *extra: str) -> int:
    """A seeded 4-step fit of the mini in its own process, checkpointing every step."""
    args = [
        "--config", str(REPO / "configs/recipes/sft.yaml"),
        "--config", str(REPO / "configs/backbones/openvla-oft-mini.yaml"),
        f"--data.train_files=[{data}]", "--data.batch_size=4", "--data.load_depth=false",
        "--data.load_annotations=false", f"--trainer.max_steps={STEPS}",
        "--trainer.log_every_n_steps=1", "--trainer.enable_progress_bar=false",
        "--trainer.logger.init_args.version=version_0",
        f"--trainer.default_root_dir={root}", f"--trainer.logger.init_args.save_dir={root}",
        "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
        f"--trainer.callbacks.dirpath={root / 'checkpoints'}", "--trainer.callbacks.save_last=true",
        "--trainer.callbacks.every_n_train_steps=1", *extra,
    ]  # fmt: skip
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
    }
    completed = subprocess.run(
        [sys.executable, "-m", "capvector.cli", "fit", *args], capture_output=True, text=True,
        env=env, timeout=1800,
    )  # fmt: skip
    assert completed.returncode in (0, 3), completed.stderr[-3000:]
    (root / "said.txt").write_text(completed.stdout + completed.stderr)
    return completed.returncode


def losses(root: Path) -> list[tuple[int, str]]:
    with open(root / "fit/version_0/metrics.csv", newline="") as f:
        return [(int(r["step"]), r["train/loss"]) for r in csv.DictReader(f) if r.get("train/loss")]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("mini_fit")
    data = write_demo_file(root / "demos.hdf5", lengths=(10, 8), image_size=64)
    assert fit(root / "whole", data) == 0
    stopped = root / "stopped"
    stop = [
        "--trainer.callbacks+=stop_fit.StopAfterStep", f"--trainer.callbacks.step={STOP}",
        f"--trainer.callbacks.marker={stopped / 'marker'}",
    ]  # fmt: skip
    assert fit(stopped, data, *stop) == 3
    resume = f"--ckpt_path={stopped / 'checkpoints/last.ckpt'}"
    assert fit(stopped, data, *stop, resume) == 0
    return root / "whole", stopped


def test_a_stopped_and_resumed_fit_follows_the_uninterrupted_one(runs: tuple[Path, Path]) -> None:
    whole, stopped = runs
    assert [step for step, _ in losses(whole)] == list(range(STEPS))
    assert losses(stopped) == losses(whole)
    a = load_file(whole / "fit/version_0/export/model.safetensors")
    b = load_file(stopped / "fit/version_0/export/model.safetensors")
    assert a.keys() == b.keys()
    assert [k for k in a if not torch.equal(a[k], b[k])] == []


def test_the_tower_kept_in_eval_mode_is_said_once_not_warned(runs: tuple[Path, Path]) -> None:
    """The mini's BatchNorm tower stays in eval mode by design (EfficientNetVision): Lightning's
    warning of modules in eval mode at the start of training is replaced by one info line."""
    said = (runs[0] / "said.txt").read_text()
    assert "module(s) in eval mode at the start of training" not in said
    assert said.count("modules stay in eval mode on purpose") == 1


def test_checkpoint_and_export_hold_only_what_trains(runs: tuple[Path, Path]) -> None:
    whole, _ = runs
    checkpoint = whole / "checkpoints/last.ckpt"
    export = whole / "fit/version_0/export"
    assert checkpoint.stat().st_size <= BUDGET
    assert sum(f.stat().st_size for f in export.rglob("*") if f.is_file()) <= BUDGET
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["state_dict"]
    assert not [k for k in state if "embed_tokens" in k or ".vision_backbone." in k]
    weights = load_file(export / "model.safetensors")
    assert any(k.endswith(".lora_A.weight") for k in weights)
    assert not [k for k in weights if "embed_tokens" in k or k.startswith("vision_backbone.")]


def test_evaluate_and_serve_load_the_lora_form_export(runs: tuple[Path, Path]) -> None:
    from capvector.workflows.serve import ServedPolicy

    export = runs[0] / "fit/version_0/export"
    completed = subprocess.run(
        [sys.executable, "-m", "capvector.cli", "evaluate", "--ckpt", str(export), "--task", "Lift",
         "--episodes", "1", "--max-steps", "8", "--workers", "0", "--videos", "0"],
        capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=900,
    )  # fmt: skip
    assert completed.returncode == 0, completed.stderr[-3000:]
    served = ServedPolicy(str(export), torch.device("cpu"), "32-true")
    served.warm_up()
    size = served.spec.image_size
    observation = {
        "images": {c: np.full((size, size, 3), 128, np.uint8) for c in served.spec.cameras},
        "proprio": np.zeros(served.spec.proprio_dim, np.float32),
        "instruction": "lift the red cube",
    }
    (chunk,) = served.act_batch([observation])
    assert chunk.shape == (8, 7) and np.isfinite(chunk).all()
