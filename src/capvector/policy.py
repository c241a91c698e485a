"""A trained backbone as a closed-loop policy: simulator observation in, raw action chunk out.

Preprocessing is the training pipeline's own, read from the model's ``DataSpec`` (camera order,
normalisation statistics, the evaluation crop), never re-typed here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from capvector.backbones.base import VLABackbone
from capvector.data.batch import Batch
from capvector.data.spec import DataSpec
from capvector.data.statistics import Normalizer
from capvector.data.transforms import ImageTransform
from capvector.eval.device import Precision, precision_context


class VLAPolicy:
    """Callable ``policy(observation) -> (T, A) float32`` in the simulator's raw action units.

    ``observation``: ``images`` {camera: uint8 (H, W, 3) upright}, ``proprio`` raw (P,),
    ``instruction`` str — the format ``capvector.eval.rollout.run_episode`` passes. Each forward
    runs where the backbone's parameters are, under ``precision`` (``32-true``: as it is; inside
    Lightning's loops the Trainer's own precision already applies).
    """

    def __init__(
        self, backbone: VLABackbone, data_spec: DataSpec, precision: Precision = "32-true"
    ) -> None:
        self.backbone = backbone
        self.spec = data_spec
        self.precision = precision
        self._autocast = precision_context(self.device, precision)
        self.normalizer = Normalizer(data_spec.stats_entry)
        self.transform = ImageTransform(augment=False, center_crop=data_spec.center_crop)

    @property
    def device(self) -> torch.device:
        return next(self.backbone.parameters()).device

    def observations_to_batch(self, observations: Sequence[Mapping[str, Any]]) -> Batch:
        device = self.device
        images, proprio = [], []
        for observation in observations:
            views = []
            for camera in self.spec.cameras:
                image = torch.from_numpy(np.ascontiguousarray(observation["images"][camera]))
                views.append(self.transform(image.permute(2, 0, 1))[0])
            images.append(torch.stack(views))
            raw = np.asarray(observation["proprio"], np.float32)
            proprio.append(torch.from_numpy(self.normalizer.normalize("proprio", raw)))
        return {
            "images": torch.stack(images).to(device),
            "proprio": torch.stack(proprio).to(device),
            "instruction": [observation["instruction"] for observation in observations],
        }

    @torch.no_grad()
    def __call__(self, observation: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch([observation])[0]

    @torch.no_grad()
    def act_batch(self, observations: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
        """One forward for many episodes' observations (batched evaluation); a chunk each."""
        batch = self.observations_to_batch(observations)
        with self._autocast():  # autocast is per thread: entered in the thread that runs it
            actions = self.backbone.predict_action(batch)
        return [self.normalizer.unnormalize("action", a) for a in actions.float().cpu().numpy()]
