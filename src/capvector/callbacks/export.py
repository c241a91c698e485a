"""Write an export folder (merged weights + config + statistics) when training ends."""

from __future__ import annotations

from pathlib import Path

import lightning as L
from lightning.pytorch.utilities.rank_zero import rank_zero_info


class ExportOnFitEnd(L.Callback):
    """At the end of ``fit``, export the model to ``dirpath`` (default: ``<log_dir>/export``)."""

    def __init__(self, dirpath: str | None = None) -> None:
        self.dirpath = dirpath

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        target = Path(self.dirpath or Path(trainer.log_dir or trainer.default_root_dir) / "export")
        target = Path(trainer.strategy.broadcast(str(target)))  # log_dir is only known on rank 0
        pl_module.export(target, overwrite=True)  # collective under FSDP2; rank 0 writes
        rank_zero_info(f"exported the model to {target}")
        trainer.strategy.barrier("capvector-export")
