"""Callbacks for tests that stop a real `capvector fit` process as a preempted job or a killed
session does (``os._exit``: nothing runs after it), then resume it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import lightning as L


class StopDuringValidation(L.Callback):
    """Exit with code 3 in the first validation batch after training step ``step``, once: the
    ``marker`` file it writes keeps the resumed fit alive."""

    def __init__(self, marker: str, step: int) -> None:
        self.marker = Path(marker)
        self.step = step

    def on_validation_batch_end(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        if trainer.sanity_checking or trainer.global_step != self.step or self.marker.exists():
            return
        self.marker.write_text("stopped during validation\n")
        os._exit(3)


class StopAfterStep(StopDuringValidation):
    """Exit with code 3 at the end of training step ``step``, once, after the callbacks listed
    before this one (a checkpoint callback's save) have run."""

    def on_validation_batch_end(self, *args: Any, **kwargs: Any) -> None:
        pass

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        if trainer.global_step != self.step or self.marker.exists():
            return
        self.marker.write_text("stopped after a training step\n")
        os._exit(3)
