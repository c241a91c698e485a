"""Image transforms that follow OpenVLA-OFT's training augmentation and its evaluation crop.

Training (``prismatic/vla/datasets/rlds/obs_transforms.py`` + ``dataset_kwargs``), per camera with
its own randomness: random resized crop of 90% of the area (aspect 1) back to the input size, then
brightness ±0.2, contrast [0.8, 1.2], saturation [0.8, 1.2], hue ±0.05. Evaluation of a model trained
with augmentation: a centre crop of 90% of the area resized back (``center_crop=True`` in OFT's eval).
Depth maps and camera intrinsics, when present, follow the same crop so geometry stays aligned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torchvision.transforms.v2.functional as TF
from torch import Tensor

CROP_AREA = 0.9


@dataclass
class ImageTransform:
    augment: bool
    """Random crop + colour jitter (training). False gives the deterministic evaluation view."""
    center_crop: bool
    """Centre crop of the same area: used at evaluation when training augmented."""
    generator: torch.Generator | None = None

    def __call__(
        self, image: Tensor, depth: Tensor | None = None, intrinsics: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """image (3, H, W) uint8 -> float [0, 1]; depth (H, W) and intrinsics (3, 3) follow the crop."""
        height, width = image.shape[-2:]
        crop = self._crop_box(height, width)
        if crop is None:
            return image.float() / 255.0, depth, intrinsics
        top, left, crop_h, crop_w = crop
        image = TF.resized_crop(image, top, left, crop_h, crop_w, [height, width], antialias=True)
        if depth is not None:
            depth = TF.resized_crop(
                depth[None], top, left, crop_h, crop_w, [height, width],
                interpolation=TF.InterpolationMode.NEAREST,
            )[0]  # fmt: skip
        if (
            intrinsics is not None
        ):  # a crop shifts the principal point, the resize scales focal lengths
            intrinsics = intrinsics.clone()
            intrinsics[0, 2] -= left
            intrinsics[1, 2] -= top
            intrinsics[0] *= width / crop_w
            intrinsics[1] *= height / crop_h
        image = image.float() / 255.0
        if self.augment:
            image = self._jitter(image)
        return image, depth, intrinsics

    def _crop_box(self, height: int, width: int) -> tuple[int, int, int, int] | None:
        side = math.sqrt(CROP_AREA)
        crop_h, crop_w = round(height * side), round(width * side)
        if self.augment:
            top = int(torch.randint(0, height - crop_h + 1, (1,), generator=self.generator))
            left = int(torch.randint(0, width - crop_w + 1, (1,), generator=self.generator))
        elif self.center_crop:
            top, left = (height - crop_h) // 2, (width - crop_w) // 2
        else:
            return None
        return top, left, crop_h, crop_w

    def _jitter(self, image: Tensor) -> Tensor:
        def uniform(low: float, high: float) -> float:
            return low + (high - low) * float(torch.rand((), generator=self.generator))

        # tf.image.random_brightness is additive, unlike torchvision's multiplicative brightness.
        image = (image + uniform(-0.2, 0.2)).clamp(0, 1)
        image = TF.adjust_contrast(image, uniform(0.8, 1.2))
        image = TF.adjust_saturation(image, uniform(0.8, 1.2))
        image = TF.adjust_hue(image, uniform(-0.05, 0.05))
        return image.clamp(0, 1)
