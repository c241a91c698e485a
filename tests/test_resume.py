"""``capvector fit ... --ckpt_path last`` resumes the newest run of the log folder that holds a
checkpoint, in that same version folder, so its metrics go on where they stopped."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from capvector.cli import main
from conftest import write_demo_file


def fit(out: Path, data: Path, steps: int, *extra: str) -> int:
    return main(
        [
            "fit", "--seed_everything=0", "--trainer.accelerator=cpu", "--trainer.devices=1",
            f"--trainer.max_steps={steps}", "--trainer.log_every_n_steps=1",
            "--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false",
            f"--trainer.default_root_dir={out}",
            "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
            f"--trainer.logger.init_args.save_dir={out}", "--trainer.logger.init_args.name=fit",
            "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
            "--trainer.callbacks.save_last=true",
            "--model.backbone=openvla-oft-tiny", f"--data.train_files=[{data}]",
            "--data.batch_size=4", *extra,
        ]
    )  # fmt: skip


def logged_steps(run: Path) -> list[int]:
    with open(run / "metrics.csv", newline="") as f:
        return [int(row["step"]) for row in csv.DictReader(f) if row.get("train/loss")]


def global_step(ckpt: Path) -> int:
    return torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"]


def test_ckpt_path_last_resumes_the_newest_run_with_a_checkpoint_in_its_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(10, 8))
    out = tmp_path / "runs"
    assert fit(out, data, 2) == 0
    runs = out / "fit"
    first = runs / "version_0" / "checkpoints" / "last.ckpt"
    assert global_step(first) == 2 and logged_steps(runs / "version_0") == [0, 1]
    # A newer run that stopped before its first checkpoint: `last` passes over it.
    (runs / "version_1").mkdir()
    (runs / "version_1" / "config.yaml").write_text("{}\n")
    capsys.readouterr()

    assert fit(out, data, 4, "--ckpt_path=last") == 0
    assert f"capvector fit: resuming {first}" in capsys.readouterr().out
    assert sorted(p.name for p in runs.iterdir()) == ["version_0", "version_1"]  # no new folder
    assert sorted(p.name for p in (runs / "version_1").iterdir()) == ["config.yaml"]
    # Two more steps from step 2, logged after the first run's rows; a fresh start would log from 0
    # again. (Lightning numbers the resumed rows from 3: its logging step skips one on a restore.)
    assert global_step(first) == 4
    steps = logged_steps(runs / "version_0")
    assert steps[:2] == [0, 1] and len(steps) == 4 and steps[2] > 1 and steps[3] > steps[2]


def test_ckpt_path_last_follows_an_explicit_checkpoint_folder(tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(10, 8))
    out, ckpts = tmp_path / "runs", tmp_path / "ckpts"
    assert fit(out, data, 2, f"--trainer.callbacks.dirpath={ckpts}") == 0
    assert fit(out, data, 3, f"--trainer.callbacks.dirpath={ckpts}", "--ckpt_path=last") == 0
    assert global_step(ckpts / "last.ckpt") == 3
