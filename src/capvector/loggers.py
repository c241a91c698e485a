"""A CSV logger whose history survives a resumed fit.

Lightning's ``CSVLogger`` deletes ``metrics.csv`` when its version folder already holds files, so a
fit resumed from a checkpoint into the same folder (what ``capvector recipe`` does after an
interruption) loses every metric logged before the interruption: the rollout evaluations at earlier
steps vanish from the success-against-steps curves. This logger appends instead. Steps between the
last checkpoint and the interruption are trained and logged again, so they appear twice; readers
take the last row of a step (``capvector.report`` does).
"""

from __future__ import annotations

import csv

from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment


class AppendingExperimentWriter(ExperimentWriter):
    """Lightning's writer, but an existing ``metrics.csv`` is kept and extended, header and all."""

    def __init__(self, log_dir: str) -> None:
        super().__init__(log_dir)
        if self._fs.isfile(self.metrics_file_path):
            with self._fs.open(self.metrics_file_path, "r", newline="") as f:
                # The earlier columns: new keys are added to them, so old rows keep their values.
                self.metrics_keys = next(csv.reader(f), [])

    def _check_log_dir_exists(self) -> None:
        """Lightning deletes the earlier metrics here; they are the run's history, so keep them."""


class CSVLogger(LightningCSVLogger):
    """``lightning.pytorch.loggers.CSVLogger`` that appends to an earlier run's ``metrics.csv``."""

    @property
    @rank_zero_experiment
    def experiment(self) -> AppendingExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = AppendingExperimentWriter(log_dir=self.log_dir)
        return self._experiment


__all__ = ["CSVLogger"]
