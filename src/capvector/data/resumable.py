"""A training loader that a resumed fit continues exactly where its checkpoint left it.

Lightning saves the ``state_dict`` of a training loader that has one with every checkpoint and hands
it back to ``load_state_dict`` on resume (its stateful-loader protocol). Without one, a fit resumed
mid-epoch (a recipe's fits resume across sessions) starts its epoch's order again from the first
batch and draws other augmentations: it trains on other batches than the fit it continues.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler


class ResumableSampler(DistributedSampler):
    """``DistributedSampler``'s order (epoch e's permutation from ``seed + e``, then this rank's
    share), from sample ``start`` of the rank's share on for one pass: how a resumed epoch skips
    what its checkpoint had trained on. On one process, ``num_replicas=1, rank=0``."""

    def __init__(
        self, dataset: Dataset, num_replicas: int, rank: int, shuffle: bool, seed: int,
        drop_last: bool,
    ) -> None:  # fmt: skip
        super().__init__(
            dataset, num_replicas=num_replicas, rank=rank, shuffle=shuffle, seed=seed,
            drop_last=drop_last,
        )  # fmt: skip
        self.start = 0

    def __iter__(self) -> Iterator[int]:
        indices = list(super().__iter__())
        start, self.start = self.start, 0
        return iter(indices[start:])


class ResumableLoader(DataLoader):
    """A training ``DataLoader`` over a ``ResumableSampler`` whose state is its place in the
    epoch (epoch, batches handed out) and torch's global random state, which the training
    augmentation draws from. Exact with ``num_workers=0``; with workers, each draws from its own
    random state, which is not saved: the order resumes, the augmentation draws do not."""

    sampler: ResumableSampler

    def __init__(self, dataset: Dataset, sampler: ResumableSampler, **kwargs: Any) -> None:
        super().__init__(dataset, sampler=sampler, **kwargs)
        self._batches = 0  # handed out in the current pass
        self._resume: dict[str, Any] | None = None

    def __iter__(self) -> Iterator[Any]:  # type: ignore[override]
        # Lightning builds no lookahead for a loader with a length, so the batches handed out are
        # the batches trained on when a checkpoint is saved.
        resume, self._resume = self._resume, None
        self._batches = 0
        if resume is not None:
            torch.set_rng_state(resume["torch_rng"])
            if resume["batches"] < len(self):  # saved mid-pass: finish that pass
                # Its epoch's order, whatever epoch Lightning sets: a fit that ended at
                # max_steps counts its epoch as processed, and one resumed from its last
                # checkpoint with more steps gets the next epoch number for the same pass.
                self.sampler.set_epoch(resume["epoch"])
                self._batches = resume["batches"]
                self.sampler.start = self._batches * self.batch_size  # type: ignore[operator]
        for batch in super().__iter__():
            self._batches += 1
            yield batch

    def state_dict(self) -> dict[str, Any]:
        return {
            "epoch": self.sampler.epoch,
            "batches": self._batches,
            "torch_rng": torch.get_rng_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._resume = dict(state)
