"""A CSV logger whose history survives a resumed fit, and videos and figures for the loggers people
watch (TensorBoard, Weights & Biases, MLflow), whichever are attached.

Lightning's ``CSVLogger`` deletes ``metrics.csv`` when its version folder already holds files, so a
fit resumed from a checkpoint into the same folder (what ``capvector recipe`` does after an
interruption) loses every metric logged before the interruption: the rollout evaluations at earlier
steps vanish from the success-against-steps curves. This logger appends instead. Steps between the
last checkpoint and the interruption are trained and logged again, so they appear twice; readers
take the last row of a step (``capvector.workflows.report`` does).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from lightning.fabric.utilities.cloud_io import get_filesystem
from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import Logger, rank_zero_experiment
from lightning.pytorch.utilities.rank_zero import rank_zero_only


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
    logger.experiment._get_file_writer().add_summary(summary, step)  # as add_video does


def _artifact_folder(key: str, step: int | None) -> str:
    return str(Path(key.replace("/", "_")) / ("" if step is None else f"step{step:06d}"))


__all__ = ["CSVLogger", "log_figure", "log_video"]
