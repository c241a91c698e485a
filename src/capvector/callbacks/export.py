"""Write an export folder (merged weights + config + statistics) when training ends."""

from __future__ import annotations

from pathlib import Path

import lightning as L
from lightning.pytorch.utilities.rank_zero import rank_zero_info

from capvector.io.weights import parse_dtype
from capvector.training.loggers import run_folder


class ExportOnFitEnd(L.Callback):
    """At the end of ``fit``, export the model to ``dirpath`` (default: ``export/`` in the run folder,
    ``capvector.training.loggers.run_folder``), every floating tensor in ``dtype`` (default: the
    base's, ``model.frozen_dtype``; ``float32`` keeps what trained unrounded:
    ``VLAModule.export``)."""

    def __init__(self, dirpath: str | None = None, dtype: str | None = None) -> None:
        if dtype is not None:
            parse_dtype(dtype)  # refused when the fit starts, not after it
        self.dirpath = dirpath
        self.dtype = dtype

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        folder = run_folder(trainer)  # collective: every rank asks
        target = Path(self.dirpath) if self.dirpath else folder / "export"
        pl_module.export(
            target, overwrite=True, dtype=self.dtype
        )  # collective under FSDP2; rank 0 writes
        rank_zero_info(f"exported the model to {target}")
        trainer.strategy.barrier("capvector-export")
