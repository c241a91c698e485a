"""A CSV logger whose history survives a resumed fit.

Lightning's ``CSVLogger`` deletes ``metrics.csv`` when its version folder already holds files, so a
fit resumed from a checkpoint into the same folder (what ``capvector recipe`` does after an
interruption) loses every metric logged before the interruption: the rollout evaluations at earlier
steps vanish from the success-against-steps curves. This logger appends instead. Steps between the
last checkpoint and the interruption are trained and logged again, so they appear twice; readers
take the last row of a step (``capvector.workflows.report`` does).
"""

from __future__ import annotations

import csv
import os
from typing import Any

from lightning.fabric.utilities.cloud_io import get_filesystem
from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment


class AppendingExperimentWriter(ExperimentWriter):
    """Lightning's writer, but an existing ``metrics.csv`` is kept and extended, header and all,
    and the version folder is made when something is first written, not when the writer is made:
    Lightning makes the writer before setup, and a fit refused there must leave no empty folder."""

    def __init__(self, log_dir: str) -> None:
        # Not ExperimentWriter.__init__: it deletes an earlier metrics.csv and makes the folder.
        self.metrics: list[dict[str, float]] = []
        self.metrics_keys: list[str] = []
        self.hparams: dict[str, Any] = {}
        self._fs = get_filesystem(log_dir)
        self.log_dir = log_dir
        self.metrics_file_path = os.path.join(log_dir, self.NAME_METRICS_FILE)
        if self._fs.isfile(self.metrics_file_path):
            with self._fs.open(self.metrics_file_path, "r", newline="") as f:
                # The earlier columns: new keys are added to them, so old rows keep their values.
                self.metrics_keys = next(csv.reader(f), [])

    def _ensure_dir(self) -> None:
        self._fs.makedirs(self.log_dir, exist_ok=True)

    def log_hparams(self, params: dict[str, Any]) -> None:
        self._ensure_dir()
        super().log_hparams(params)

    def save(self) -> None:
        if self.metrics:
            self._ensure_dir()
            super().save()


class CSVLogger(LightningCSVLogger):
    """``lightning.pytorch.loggers.CSVLogger`` that appends to an earlier run's ``metrics.csv`` and
    makes its folders at the first write."""

    @property
    @rank_zero_experiment
    def experiment(self) -> AppendingExperimentWriter:
        if self._experiment is None:
            self._experiment = AppendingExperimentWriter(log_dir=self.log_dir)
        return self._experiment


__all__ = ["CSVLogger"]
