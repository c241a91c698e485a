"""Image transforms that follow OpenVLA-OFT's training augmentation and its evaluation crop.

Training (``prismatic/vla/datasets/rlds/obs_transforms.py`` + ``dataset_kwargs``), per camera with
its own randomness: random resized crop of 90% of the area (aspect 1) back to the input size, then
brightness ±0.2, contrast [0.8, 1.2], saturation [0.8, 1.2], hue ±0.05. Evaluation of a model trained
with augmentation: a centre crop of 90% of the area resized back (``center_crop=True`` in OFT's eval).
Depth maps and camera intrinsics, when present, follow the same crop so geometry stays aligned.

Everything runs on a batch of images at once (``ImageTransform.batch``), each image with its own
crop and jitter factors and the numbers of torchvision's per-image kernels: one resize for all the
crops, the jitter a few images per tensor pass, the hue shift in closed form (torchvision's HSV
round trip takes more passes). Loading a batch of 8 costs 7.8 ms of CPU instead of 44 ms
(``docs/performance.md``), against a tiny model's step of about 100 ms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torchvision.transforms.v2.functional as TF
from torch import Tensor

CROP_AREA = 0.9
BRIGHTNESS = (-0.2, 0.2)
"""Added to every channel (``tf.image.random_brightness``, as OFT; torchvision's multiplies)."""
CONTRAST = (0.8, 1.2)
SATURATION = (0.8, 1.2)
HUE = (-0.05, 0.05)
"""A shift of the hue, in turns of the colour wheel."""
JITTER_PIXELS = 2**14
"""Pixels jittered at once: 192 KiB of float RGB, which a core's L2 cache holds."""

# ITU-R 601-2 luma, as torchvision's rgb_to_grayscale (and its contrast and saturation) use.
_LUMA = torch.tensor([0.2989, 0.587, 0.114]).view(3, 1, 1)
_RGB_OFFSETS = torch.tensor([5.0, 3.0, 1.0]).view(3, 1, 1)  # see _shift_hue
_NEXT, _AFTER_NEXT = [1, 2, 0], [2, 0, 1]  # channel indices: (g, b, r) and (b, r, g)


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
        images, depths, Ks = self.batch(
            image[None],
            None if depth is None else depth[None],
            None if intrinsics is None else intrinsics[None],
        )
        return images[0], None if depths is None else depths[0], None if Ks is None else Ks[0]

    def batch(
        self, images: Tensor, depth: Tensor | None = None, intrinsics: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """images (N, 3, H, W) uint8 -> float [0, 1], each image with its own crop and jitter;
        depth (N, H, W) and intrinsics (N, 3, 3) follow each image's crop."""
        count, _, height, width = images.shape
        boxes = self._crop_boxes(count, height, width)
        if boxes is None:
            return images.float() / 255.0, depth, intrinsics
        top, left, crop_h, crop_w = boxes
        # Crop then resize, as TF.resized_crop does per image (one uint8 resize for all, the same
        # numbers): the crops all have one size, only their corners differ.
        images = TF.resize(
            _crop(images, top, left, crop_h, crop_w), [height, width], antialias=True
        )
        if depth is not None:
            depth = TF.resize(
                _crop(depth[:, None], top, left, crop_h, crop_w), [height, width],
                interpolation=TF.InterpolationMode.NEAREST,
            )[:, 0]  # fmt: skip
        if intrinsics is not None:  # a crop shifts the principal point, the resize scales focals
            intrinsics = intrinsics.clone()
            intrinsics[:, 0, 2] -= left
            intrinsics[:, 1, 2] -= top
            intrinsics[:, 0] *= width / crop_w
            intrinsics[:, 1] *= height / crop_h
        floats = images.float() / 255.0
        if self.augment:
            low, high = torch.tensor([BRIGHTNESS, CONTRAST, SATURATION, HUE]).T
            factors = low + (high - low) * torch.rand((count, 4), generator=self.generator)
            # A few images at a time: each pass over them stays in the CPU's cache (the jitter is
            # ~30 passes; 3.7 against 4.5-5.3 ms of CPU for 16 images at 64 px here).
            step = max(1, JITTER_PIXELS // (height * width))
            floats = torch.cat(
                [
                    color_jitter(floats[i : i + step], *factors[i : i + step].unbind(-1))
                    for i in range(0, count, step)
                ]
            )
        return floats, depth, intrinsics

    def _crop_boxes(
        self, count: int, height: int, width: int
    ) -> tuple[Tensor, Tensor, int, int] | None:
        """(top (N,), left (N,), crop height, crop width), or None for no crop."""
        side = math.sqrt(CROP_AREA)
        crop_h, crop_w = round(height * side), round(width * side)
        if self.augment:
            top = torch.randint(0, height - crop_h + 1, (count,), generator=self.generator)
            left = torch.randint(0, width - crop_w + 1, (count,), generator=self.generator)
        elif self.center_crop:
            top = torch.full((count,), (height - crop_h) // 2)
            left = torch.full((count,), (width - crop_w) // 2)
        else:
            return None
        return top, left, crop_h, crop_w


def _crop(images: Tensor, top: Tensor, left: Tensor, crop_h: int, crop_w: int) -> Tensor:
    """(N, C, crop_h, crop_w): image n's window at (top[n], left[n]) of (N, C, H, W)."""
    # Slices: a few microseconds each, where one gather over all images costs milliseconds.
    return torch.stack(
        [
            image[:, y : y + crop_h, x : x + crop_w]
            for image, y, x in zip(images, top.tolist(), left.tolist(), strict=True)
        ]
    )


def color_jitter(
    images: Tensor, brightness: Tensor, contrast: Tensor, saturation: Tensor, hue: Tensor
) -> Tensor:
    """images (N, 3, H, W) float in [0, 1], each with its own factors (N,), in OFT's order.

    Image by image this is ``(image + brightness).clamp(0, 1)`` then torchvision's
    ``adjust_contrast``, ``adjust_saturation`` and ``adjust_hue`` with those factors (the same
    numbers to float rounding; ``tests/test_transforms.py``). Unlike
    ``torchvision.transforms.ColorJitter`` the order is fixed and brightness adds instead of
    multiplying: OFT's ``tf.image`` augmentation does both."""

    def per_image(factor: Tensor) -> Tensor:
        return factor.to(images.dtype).view(-1, 1, 1, 1)

    images = (images + per_image(brightness)).clamp_(0, 1)
    # torchvision's _blend(image, other, ratio) = image·ratio + other·(1 - ratio), clamped
    mean = _grayscale(images).mean(dim=(-3, -2, -1), keepdim=True)
    images = torch.lerp(mean, images, per_image(contrast)).clamp_(0, 1)
    images = torch.lerp(_grayscale(images), images, per_image(saturation)).clamp_(0, 1)
    return _shift_hue(images, per_image(hue)).clamp_(0, 1)


def _grayscale(images: Tensor) -> Tensor:
    """(N, 1, H, W) luma, as torchvision's rgb_to_grayscale."""
    return (images * _LUMA.to(images)).sum(dim=-3, keepdim=True)


def _shift_hue(images: Tensor, shift: Tensor) -> Tensor:
    """Hue moved by ``shift`` (N, 1, 1, 1) turns: torchvision's ``adjust_hue``, an RGB -> HSV ->
    RGB round trip (after Pillow's ``Convert.c``), in closed form. A hue shift keeps each pixel's
    largest and smallest channel values; with h the hue in sixths of a turn (from the channels'
    differences, as ``_rgb_to_hsv``) each channel becomes max - (max - min)·ramp(k), where
    ramp(k) = clamp(min(k, 4 - k), 0, 1) and k = (n + h + 6·shift) mod 6 for n = 5, 3, 1 (R, G, B):
    ``_hsv_to_rgb``'s choice among (v, p, q, t) written as one expression."""
    r, g, b = images.unbind(dim=-3)
    high = torch.maximum(torch.maximum(r, g), b).unsqueeze_(-3)
    spread = high - torch.minimum(torch.minimum(r, g), b).unsqueeze_(-3)
    divisor = torch.where(spread == 0, 1.0, spread)  # grey: no hue, and every channel is max
    # (g - b, b - r, r - g) / spread: the hue within the sector of the largest channel
    sector_hue = (images[:, _NEXT] - images[:, _AFTER_NEXT]) / divisor
    is_r = high == images[:, :1]
    is_g = high == images[:, 1:2]
    sixths = torch.where(
        is_r, sector_hue[:, :1], torch.where(is_g, sector_hue[:, 1:2] + 2, sector_hue[:, 2:] + 4)
    )
    k = (sixths + 6.0 * shift + _RGB_OFFSETS.to(images)).remainder_(6.0)
    ramp = torch.minimum(k, 4.0 - k).clamp_(0.0, 1.0)
    return high - spread * ramp
