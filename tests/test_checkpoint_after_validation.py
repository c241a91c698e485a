"""A fit stopped during a validation resumes and runs that validation: CheckpointAfterValidation
against Lightning's ModelCheckpoint, in real `capvector fit` processes killed mid-validation."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from conftest import write_demo_file

TESTS = Path(__file__).parent


def fit(root: Path, data: Path, checkpoint: str, *extra: str) -> int:
    """A 6-step fit validating (held-out L1) after steps 3 and 6, checkpointing every step; the
    test callback kills it during the validation after step 3 the first time."""
    args = [
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=6", "--trainer.val_check_interval=3",
        "--trainer.check_val_every_n_epoch=null", "--trainer.limit_val_batches=1",
        "--trainer.num_sanity_val_steps=0", "--trainer.enable_progress_bar=false",
        "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={root}", "--trainer.logger.init_args.name=fit",
        f"--trainer.callbacks+={checkpoint}", "--trainer.callbacks.save_last=true",
        "--trainer.callbacks.every_n_train_steps=1",
        "--trainer.callbacks+=stop_fit.StopDuringValidation",
        f"--trainer.callbacks.marker={root / 'stopped'}", "--trainer.callbacks.step=3",
        "--model.backbone=openvla-oft-tiny", f"--data.train_files=[{data}]",
        f"--data.val_files=[{data}]", "--data.batch_size=4", *extra,
    ]  # fmt: skip
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
    }
    completed = subprocess.run(
        [sys.executable, "-m", "capvector.cli", *args], capture_output=True, text=True, env=env,
        timeout=600,
    )  # fmt: skip
    assert completed.returncode in (0, 3), completed.stderr[-3000:]
    return completed.returncode


def validated_steps(root: Path) -> list[int]:
    with (root / "fit" / "version_0" / "metrics.csv").open() as f:
        return sorted(int(r["step"]) for r in csv.DictReader(f) if r.get("val/action_l1"))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("checkpoint", "steps_validated"),
    [
        # Resumed from step 3's checkpoint, which says step 3 is over: its validation is skipped.
        ("lightning.pytorch.callbacks.ModelCheckpoint", 1),
        # Resumed from step 2's: step 3 is trained again and validated.
        ("capvector.callbacks.CheckpointAfterValidation", 2),
    ],
)
def test_a_fit_stopped_during_validation_runs_it_again_when_resumed(
    tmp_path: Path, checkpoint: str, steps_validated: int
) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5")
    assert fit(tmp_path, data, checkpoint) == 3  # killed during the validation after step 3
    assert fit(tmp_path, data, checkpoint, "--ckpt_path=last") == 0
    assert len(set(validated_steps(tmp_path))) == steps_validated


@pytest.mark.slow
def test_a_fit_checkpointed_by_lightnings_callback_resumes_with_this_one(tmp_path: Path) -> None:
    """Fits started before the recipe switched callbacks resume into the same last.ckpt (under
    another state key the callback's state is dropped and Lightning writes last-v1.ckpt beside
    the stale one)."""
    data = write_demo_file(tmp_path / "demos.hdf5")
    assert fit(tmp_path, data, "lightning.pytorch.callbacks.ModelCheckpoint") == 3
    assert (
        fit(tmp_path, data, "capvector.callbacks.CheckpointAfterValidation", "--ckpt_path=last")
        == 0
    )
    checkpoints = tmp_path / "fit" / "version_0" / "checkpoints"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["epoch=2-step=6.ckpt", "last.ckpt"]
    assert torch.load(checkpoints / "last.ckpt", weights_only=False)["global_step"] == 6
