"""A CSV logger whose history survives a resumed fit, and videos and figures for the loggers people
watch (TensorBoard, Weights & Biases, MLflow), whichever are attached.

Lightning's ``CSVLogger`` deletes ``metrics.csv`` when its version folder already holds files, so a
fit resumed from a checkpoint into the same folder (what ``capvector recipe`` does after an
interruption) loses every metric logged before the interruption: the rollout evaluations at earlier
steps vanish from the success-against-steps curves. This logger appends instead. Steps between the
last checkpoint and the interruption are trained and logged again, so they appear twice; readers
take the last row of a step (``capvector.workflows.report`` does).

Every metric name a fit logs is a leaf: no name is also a prefix folder of another
(``val/success_rate`` beside ``val/success_rate_by_task/Lift``, not ``val/success_rate/Lift``), as
MLflow's file store keeps a metric as a file at its name's path and cannot hold both.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from lightning.fabric.utilities.cloud_io import get_filesystem
from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import Logger, rank_zero_experiment
from lightning.pytorch.utilities.rank_zero import rank_zero_only

if TYPE_CHECKING:
    import lightning as L


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


def run_folder(trainer: L.Trainer) -> Path:
    """The local folder of a fit's own files (export, rollout videos, ``episodes.csv``).

    The first logger's ``log_dir`` when it has one (CSV, TensorBoard: ``trainer.log_dir``); for
    other loggers ``<save_dir>/<name>/<version>``, the folder Lightning's ``ModelCheckpoint`` puts
    ``checkpoints/`` in (``__resolve_ckpt_dir``), so the files sit beside the checkpoints.
    ``trainer.log_dir`` would give such a logger's bare ``save_dir``: for MLflow the file store's
    root, where a folder that is not an experiment makes MLflow report the store as malformed.
    Collective under DDP: every rank calls it; rank 0's answer is used.
    """
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    log_dir = trainer.log_dir  # collective: broadcasts rank 0's log_dir
    path = Path(log_dir or trainer.default_root_dir)
    logger = trainer.loggers[0] if trainer.loggers else None
    # The loggers trainer.log_dir takes log_dir from (Trainer.log_dir); others give save_dir.
    if logger is not None and not isinstance(logger, (CSVLogger, TensorBoardLogger)):
        version = logger.version if isinstance(logger.version, str) else f"version_{logger.version}"
        path = Path(logger.save_dir or trainer.default_root_dir) / str(logger.name) / version
    return Path(trainer.strategy.broadcast(str(path)))


def logging_step(trainer: L.Trainer) -> int:
    """The step Lightning gives what ``LightningModule.log`` logs: the number of optimizer steps
    completed before the current batch. During a validation run inside a fit this is
    ``global_step - 1``; files logged beside the metrics (rollout videos) use it too, so a
    validation's video and its success rate share a step in every logger."""
    # Lightning has no public accessor; _LoggerConnector.log_metrics reads this counter
    # (lightning/pytorch/trainer/connectors/logger_connector/logger_connector.py).
    return int(trainer.fit_loop.epoch_loop._batches_that_stepped)


@rank_zero_only
def log_file(
    loggers: Iterable[Logger], path: str | os.PathLike[str], folder: str | None = None
) -> None:
    """A file the fit keeps on disk (``episodes.csv``) sent to each logger that stores files:
    MLflow as an artifact (replacing the earlier copy). TensorBoard and W&B show no such files;
    they stay in the run folder."""
    from lightning.pytorch.loggers import MLFlowLogger

    for logger in loggers:
        if isinstance(logger, MLFlowLogger):
            logger.experiment.log_artifact(logger.run_id, str(path), folder)


@rank_zero_only
def log_video(
    loggers: Iterable[Logger],
    key: str,
    frames: Sequence[np.ndarray],
    path: str | os.PathLike[str],
    step: int | None = None,
    fps: int = 20,
) -> None:
    """A rollout video to each logger that shows videos: TensorBoard gets ``frames`` ((H, W, 3)
    uint8) as an animated GIF, W&B and MLflow the mp4 already written at ``path``. CSV loggers
    keep the mp4 on disk, beside their ``metrics.csv``."""
    from lightning.pytorch.loggers import MLFlowLogger, TensorBoardLogger, WandbLogger

    for logger in loggers:
        if isinstance(logger, TensorBoardLogger):
            _tensorboard_gif(logger, key, frames, step, fps)
        elif isinstance(logger, WandbLogger):
            logger.log_video(key, [str(path)], step=step)
        elif isinstance(logger, MLFlowLogger):
            logger.experiment.log_artifact(logger.run_id, str(path), _artifact_folder(key, step))


@rank_zero_only
def log_figure(
    loggers: Iterable[Logger], key: str, path: str | os.PathLike[str], step: int | None = None
) -> None:
    """A figure written as a PNG at ``path`` to each logger that shows images (TensorBoard, W&B;
    MLflow as an artifact)."""
    from lightning.pytorch.loggers import MLFlowLogger, TensorBoardLogger, WandbLogger

    for logger in loggers:
        if isinstance(logger, TensorBoardLogger):
            import imageio.v2 as imageio

            image = imageio.imread(path)[..., :3]  # RGBA from matplotlib: TensorBoard takes RGB
            logger.experiment.add_image(key, image, global_step=step, dataformats="HWC")
        elif isinstance(logger, WandbLogger):
            logger.log_image(key, [str(path)], step=step)
        elif isinstance(logger, MLFlowLogger):
            logger.experiment.log_artifact(logger.run_id, str(path), _artifact_folder(key, step))


def _tensorboard_gif(
    logger: Logger, key: str, frames: Sequence[np.ndarray], step: int | None, fps: int
) -> None:
    """What ``SummaryWriter.add_video`` writes (an image summary holding an animated GIF, which
    TensorBoard's image tab plays), encoded by imageio: ``add_video`` needs moviepy 1.x."""
    import imageio.v2 as imageio
    from torch.utils.tensorboard.summary import Summary

    video = np.stack([np.asarray(f, dtype=np.uint8) for f in frames])
    buffer = io.BytesIO()
    imageio.mimsave(buffer, list(video), format="GIF", duration=1000 / fps, loop=0)
    image = Summary.Image(
        height=video.shape[1], width=video.shape[2], colorspace=3,
        encoded_image_string=buffer.getvalue(),
    )  # fmt: skip
    summary = Summary(value=[Summary.Value(tag=key, image=image)])
    # The writer every SummaryWriter.add_* method writes through (its public ``file_writer``,
    # made in its constructor); None only after the logger was closed at the end of the fit.
    writer = logger.experiment.file_writer
    if writer is None:
        raise RuntimeError(
            f"TensorBoard logger {logger.log_dir} is closed; log videos during the fit"
        )
    writer.add_summary(summary, step)


def _artifact_folder(key: str, step: int | None) -> str:
    return str(Path(key.replace("/", "_")) / ("" if step is None else f"step{step:06d}"))


__all__ = ["CSVLogger", "log_figure", "log_file", "log_video", "logging_step", "run_folder"]
