"""`capvector fit` as a user types it: `--ckpt_path last`, and a fresh checkout's first command."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from capvector.cli import main
from capvector.data.datamodule import DemoGeneration, RobotDataModule
from capvector.data.hdf5 import DatasetError
from conftest import write_demo_file


def fit(root: Path, data: Path, steps: int, *extra: str) -> None:
    args = [
        "fit", "--trainer.accelerator=cpu", f"--trainer.max_steps={steps}",
        "--trainer.enable_progress_bar=false", "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={root}", "--trainer.logger.init_args.name=fit",
        "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
        "--trainer.callbacks.save_last=true", "--model.backbone=openvla-oft-tiny",
        f"--data.train_files=[{data}]", "--data.batch_size=4", *extra,
    ]  # fmt: skip
    assert main(args) == 0


def test_ckpt_path_last_resumes_the_latest_run_in_its_own_folder(tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5")
    fit(tmp_path, data, 2)
    fit(tmp_path, data, 2)  # a second run: version_1, the newest
    fit(tmp_path, data, 4, "--ckpt_path=last")
    versions = sorted(p.name for p in (tmp_path / "fit").iterdir())
    assert versions == ["version_0", "version_1"]  # no new version folder
    resumed = torch.load(tmp_path / "fit/version_1/checkpoints/last.ckpt", weights_only=False)
    assert resumed["global_step"] == 4
    first = torch.load(tmp_path / "fit/version_0/checkpoints/last.ckpt", weights_only=False)
    assert first["global_step"] == 2


@pytest.mark.sim
def test_data_generate_records_missing_demos_once(tmp_path: Path) -> None:
    target = tmp_path / "demos" / "lift.hdf5"
    with pytest.raises(DatasetError, match="data.generate"):
        RobotDataModule(train_files=[str(target)])
    dm = RobotDataModule(
        train_files=[str(target)], generate=DemoGeneration(episodes=1), load_depth=True
    )
    assert dm.spec.action_dim == 7 and target.is_file()  # recorded on first need, with depth
    assert dm.train_dataset is not None and dm.train_dataset[0]["depth"] is not None
    stamp = target.stat().st_mtime_ns
    dm.prepare_data()  # what Lightning calls: the file exists, nothing is recorded again
    assert target.stat().st_mtime_ns == stamp
