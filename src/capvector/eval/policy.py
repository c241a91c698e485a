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


class VLAPolicy:
    """Callable ``policy(observation) -> (T, A) float32`` in the simulator's raw action units.

    ``observation``: ``images`` {camera: uint8 (H, W, 3) upright}, ``proprio`` raw (P,),
    ``instruction`` str — the format ``capvector.eval.rollout.run_episode`` passes.
    """

    def __init__(self, backbone: VLABackbone, data_spec: DataSpec) -> None:
        self.backbone = backbone
        self.spec = data_spec
        self.normalizer = Normalizer(data_spec.stats_entry)
        self.transform = ImageTransform(augment=False, center_crop=data_spec.center_crop)

    def observations_to_batch(self, observations: Sequence[Mapping[str, Any]]) -> Batch:
        device = next(self.backbone.parameters()).device
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
        actions = self.backbone.predict_action(self.observations_to_batch(observations))
        return [self.normalizer.unnormalize("action", a) for a in actions.float().cpu().numpy()]
