"""Log what a training step costs: wall-clock seconds per optimizer step and peak memory."""

from __future__ import annotations

import resource
import sys
import time
from collections import deque
from typing import Any

import lightning as L
import torch


def peak_memory_mib(device: torch.device) -> float:
    """Peak memory of this process so far: CUDA's allocator peak on a GPU, else peak RSS."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return (
        peak / 2**20 if sys.platform == "darwin" else peak / 2**10
    )  # bytes on macOS, KiB on Linux


class StepCost(L.Callback):
    """Logs ``perf/step_seconds``, the mean wall time of the last ``log_every_n_steps`` training
    steps, and ``perf/peak_memory_mib``.

    A step is timed from its batch's start to the next batch's start: loading and augmenting the
    data (in this process unless ``data.num_workers`` > 0), logging, checkpoints and the loop's own
    work count, as they count in the fit's wall time; validation runs between two batches are left
    out. The value logged at a batch's end covers the steps before it (the current one ends when
    the next begins)."""

    def __init__(self) -> None:
        self._last_start: float | None = None
        self._validating_since = 0.0
        self._validation_seconds = 0.0  # since the last batch start
        self._seconds: deque[float] = deque()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last_start = None

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        now = time.perf_counter()
        if self._last_start is not None:
            self._seconds.append(now - self._last_start - self._validation_seconds)
            while len(self._seconds) > max(1, trainer.log_every_n_steps):
                self._seconds.popleft()
        self._last_start, self._validation_seconds = now, 0.0

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._validating_since = time.perf_counter()

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._validation_seconds += time.perf_counter() - self._validating_since

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any
    ) -> None:
        # Only where Lightning writes logs (its rule: every log_every_n_steps optimizer steps, and
        # when stopping): a value logged in between is overwritten unread, and costs a step time.
        every = trainer.log_every_n_steps
        if not every or (trainer.global_step % every and not trainer.should_stop):
            return
        if self._seconds:
            pl_module.log("perf/step_seconds", sum(self._seconds) / len(self._seconds))
        pl_module.log("perf/peak_memory_mib", peak_memory_mib(pl_module.device))
