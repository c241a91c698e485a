"""`StepCost`: step time and peak memory, as a fit logs them."""

from __future__ import annotations

import csv
from pathlib import Path

from lightning.pytorch.loggers import CSVLogger

from capvector.callbacks import StepCost
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
