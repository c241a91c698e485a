"""Image transforms that follow OpenVLA-OFT's training augmentation and its evaluation crop.

Training (``prismatic/vla/datasets/rlds/obs_transforms.py`` + ``dataset_kwargs``), per camera with
its own randomness: random resized crop of 90% of the area (aspect 1) back to the input size, then
brightness ±0.2, contrast [0.8, 1.2], saturation [0.8, 1.2], hue ±0.05. Evaluation of a model trained
with augmentation: a centre crop of 90% of the area resized back (``center_crop=True`` in OFT's eval).
Depth maps and camera intrinsics, when present, follow the same crop so geometry stays aligned.

Everything runs on a batch of images at once (``ImageTransform.batch``), each image with its own
crop and jitter factors: per image, torchvision's kernels on one image cost about a millisecond of
Python and dispatch overhead, most of a tiny model's step.
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

# ITU-R 601-2 luma, as torchvision's rgb_to_grayscale (and its contrast and saturation) use.
_LUMA = (0.2989, 0.587, 0.114)
_RGB_OFFSETS = torch.tensor([5.0, 3.0, 1.0]).view(3, 1, 1)  # see _hsv_to_rgb


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
            floats = color_jitter(floats, *factors.unbind(-1))
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
    ``adjust_contrast``, ``adjust_saturation`` and ``adjust_hue`` (its HSV round trip, after Pillow)
    with those factors. Unlike ``torchvision.transforms.ColorJitter`` the order is fixed and
    brightness adds instead of multiplying: OFT's ``tf.image`` augmentation does both."""

    def per_image(factor: Tensor) -> Tensor:
        return factor.to(images.dtype).view(-1, 1, 1, 1)

    def blend(image: Tensor, other: Tensor, ratio: Tensor) -> Tensor:  # torchvision's _blend
        return (image * ratio + other * (1 - ratio)).clamp_(0, 1)

    images = (images + per_image(brightness)).clamp_(0, 1)
    mean = _grayscale(images).mean(dim=(-3, -2, -1), keepdim=True)
    images = blend(images, mean, per_image(contrast))
    images = blend(images, _grayscale(images), per_image(saturation))
    h, s, v = _rgb_to_hsv(images)
    return _hsv_to_rgb((h + per_image(hue)[:, 0]).remainder_(1.0), s, v).clamp_(0, 1)


def _grayscale(images: Tensor) -> Tensor:
    r, g, b = images.unbind(dim=-3)
    return (r * _LUMA[0] + g * _LUMA[1] + b * _LUMA[2]).unsqueeze(-3)


def _rgb_to_hsv(images: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(N, 3, H, W) RGB -> hue, saturation, value (N, H, W), each in [0, 1]: torchvision's
    ``_rgb_to_hsv`` (after Pillow's ``Convert.c``) in fewer tensor operations; where max == min
    the hue and saturation are 0 (no division by zero)."""
    r, g, b = images.unbind(dim=-3)
    # maximum/minimum of the three planes: aminmax over the channel dimension is strided, ~10x slower
    high, low = torch.maximum(torch.maximum(r, g), b), torch.minimum(torch.minimum(r, g), b)
    spread = high - low
    flat = spread == 0
    saturation = spread / torch.where(flat, 1.0, high)
    # (max - channel) / spread, for r, g, b at once
    rc, gc, bc = (
        (high.unsqueeze(-3) - images) / torch.where(flat, 1.0, spread).unsqueeze(-3)
    ).unbind(-3)
    hue = torch.where(high == r, bc - gc, torch.where(high == g, 2.0 + rc - bc, 4.0 + gc - rc))
    return (hue / 6.0 + 1.0).fmod_(1.0), saturation, high


def _hsv_to_rgb(hue: Tensor, saturation: Tensor, value: Tensor) -> Tensor:
    """Hue, saturation, value (N, H, W) -> (N, 3, H, W) RGB. torchvision's ``_hsv_to_rgb`` picks
    each channel from (v, p, q, t) by the hue's sector; this is the same function in closed form,
    channel = v - v·s·clamp(min(k, 4 - k), 0, 1) with k = (n + 6·hue) mod 6, n = 5, 3, 1 for R, G, B."""
    k = (_RGB_OFFSETS.to(hue.device) + 6.0 * hue.unsqueeze(-3)).remainder_(6.0)
    ramp = torch.minimum(k, 4.0 - k).clamp_(0.0, 1.0)
    return value.unsqueeze(-3) - (value * saturation).unsqueeze(-3) * ramp
