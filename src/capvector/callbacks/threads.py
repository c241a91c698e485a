"""Keep a fit's torch threads at its share of the CPUs while other fits start and end."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch

from capvector.training import threads


class ShareCores(L.Callback):
    """Registers the fit as running (``capvector.training.threads``) and sets torch's threads to
    its share of the usable CPUs: at setup, then every ``every_seconds`` at a batch start, so a fit
    started alone gives cores up when another starts and takes them back when it ends. It never
    goes above the threads torch had at setup (torch's default: one per core), so a process that
    chose fewer keeps its choice. ``capvector fit`` adds it unless ``OMP_NUM_THREADS`` or a recipe
    stage fixed the threads."""

    def __init__(self, every_seconds: float = 10.0, registry: str | None = None) -> None:
        self.every_seconds = every_seconds
        self.registry = Path(registry) if registry else threads.REGISTRY
        self._entry: threads.RunningFit | None = None
        self._checked = 0.0
        self._threads_before = 0

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "fit" and self._entry is None:
            self._threads_before = torch.get_num_threads()
            self._entry = threads.RunningFit(self.registry).open()
            self._share()

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        if self._entry is not None and time.monotonic() - self._checked > self.every_seconds:
            self._share()

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "fit" and self._entry is not None:
            self._entry.close()
            self._entry = None
            torch.set_num_threads(self._threads_before)

    def _share(self) -> None:
        self._checked = time.monotonic()
        share = min(self._threads_before, threads.fair_threads(self.registry))
        if share != torch.get_num_threads():
            torch.set_num_threads(share)
            # Results depend on the thread count (a sum's order), so say when it changes.
            print(
                f"capvector fit: {share} torch thread(s), this fit's share of the CPUs beside the "
                "other fits running; set OMP_NUM_THREADS to fix the number",
                file=sys.stderr,
            )
