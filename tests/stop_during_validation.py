"""A callback for tests/test_checkpoint_after_validation.py: the process dies in the middle of a
validation, as a preempted job or a killed session does (``os._exit``: nothing runs after it)."""

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
