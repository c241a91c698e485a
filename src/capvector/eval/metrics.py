"""Success rate as a torchmetrics metric: sums synchronised across ranks, then divided."""

from __future__ import annotations

import torch
from torchmetrics import Metric


class SuccessRate(Metric):
    full_state_update = False

    def __init__(self) -> None:
        super().__init__()
        self.add_state("successes", default=torch.tensor(0.0), dist_reduce_fx="sum")
        self.add_state("episodes", default=torch.tensor(0.0), dist_reduce_fx="sum")

    def update(self, success: bool) -> None:
        self.successes += float(success)
        self.episodes += 1.0

    def compute(self) -> torch.Tensor:
        return self.successes / self.episodes.clamp_min(1.0)
