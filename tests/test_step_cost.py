"""`StepCost`: step time and peak memory, as a fit logs them."""

from __future__ import annotations

import csv
from pathlib import Path

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger
from torch.utils.data import DataLoader, Dataset

from capvector.callbacks import StepCost, step_cost
from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule
from conftest import cpu_trainer


def test_step_cost_logs_step_seconds_and_peak_memory(tmp_path: Path, demo_file: Path) -> None:
    dm = RobotDataModule(train_files=[str(demo_file)], batch_size=4)
    module = VLAModule(backbone="openvla-oft-tiny", data_spec=dm.spec)
    logger = CSVLogger(tmp_path, name="fit", version="v")
    cpu_trainer(4, logger=logger, log_every_n_steps=2, callbacks=[StepCost()]).fit(module, dm)
    with open(tmp_path / "fit" / "v" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["perf/step_seconds"]]
    assert [int(r["step"]) for r in rows] == [1, 3]  # at the trainer's logging interval
    for r in rows:
        # a tiny-preset step takes milliseconds; the process holds at least torch (> 100 MiB)
        assert 1e-4 < float(r["perf/step_seconds"]) < 60
        assert float(r["perf/peak_memory_mib"]) > 100


class Clock:
    """Time that passes only where the test says: loading a sample, a training step."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


class Loading(Dataset):
    """Each sample costs ``seconds`` of the clock to load."""

    def __init__(self, clock: Clock, seconds: float) -> None:
        self.clock, self.seconds = clock, seconds

    def __len__(self) -> int:
        return 64

    def __getitem__(self, i: int) -> torch.Tensor:
        self.clock.now += self.seconds
        return torch.ones(2)


class Regression(L.LightningModule):
    def __init__(self, clock: Clock) -> None:
        super().__init__()
        self.clock = clock
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        self.clock.now += 0.5
        return self.layer(batch).sum()

    def validation_step(self, batch: torch.Tensor, batch_idx: int) -> None:
        self.clock.now += 50.0

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(Loading(self.clock, 1.0), batch_size=2)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(Loading(self.clock, 100.0), batch_size=2)


def test_step_seconds_run_from_batch_start_to_batch_start_without_validation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A step is its batch's loading (2 samples x 1 s) and its training step (0.5 s); the
    validation runs between steps (200 s of loading, 50 s of steps) are not."""
    clock = Clock()
    monkeypatch.setattr(step_cost, "time", clock)
    logger = CSVLogger(tmp_path, name="fit", version="v")
    trainer = cpu_trainer(
        7, logger=logger, log_every_n_steps=1, callbacks=[StepCost()],
        limit_val_batches=1, val_check_interval=3, num_sanity_val_steps=1,
    )  # fmt: skip
    trainer.fit(Regression(clock))
    with open(tmp_path / "fit" / "v" / "metrics.csv") as f:
        logged = [
            float(r["perf/step_seconds"]) for r in csv.DictReader(f) if r["perf/step_seconds"]
        ]
    assert logged == [2.5] * 6  # from the second step's end on; two validations ran in between
