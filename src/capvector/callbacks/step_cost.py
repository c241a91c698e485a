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
    """Logs ``perf/step_seconds``, the mean time of the last ``log_every_n_steps`` training steps
    from batch start to batch end (forward, backward and optimizer; not validation or data
    loading), and ``perf/peak_memory_mib``."""

    def __init__(self) -> None:
        self._started = 0.0
        self._seconds: deque[float] = deque()

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        self._started = time.perf_counter()

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any
    ) -> None:
        self._seconds.append(time.perf_counter() - self._started)
        while len(self._seconds) > max(1, trainer.log_every_n_steps):
            self._seconds.popleft()
        # Logged every step; Lightning writes the latest value at its logging interval.
        pl_module.log("perf/step_seconds", sum(self._seconds) / len(self._seconds))
        pl_module.log("perf/peak_memory_mib", peak_memory_mib(pl_module.device))
