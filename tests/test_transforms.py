"""OFT's augmentation on a batch of images: torchvision's per-image kernels are the referee."""

from __future__ import annotations

import torch
import torchvision.transforms.v2.functional as TF

from capvector.data.transforms import (
    BRIGHTNESS,
    CONTRAST,
    HUE,
    SATURATION,
    ImageTransform,
    color_jitter,
)


def test_batched_jitter_is_torchvisions_jitter_image_by_image() -> None:
    generator = torch.Generator().manual_seed(0)
    images = torch.rand((12, 3, 32, 32), generator=generator)
    images[0] = 0.5  # grey: no hue or saturation
    images[1, :, :8] = images[1, 0, :8]  # a grey band beside colour

    def draw(low_high: tuple[float, float]) -> torch.Tensor:
        low, high = low_high
        return low + (high - low) * torch.rand(12, generator=generator)

    factors = draw(BRIGHTNESS), draw(CONTRAST), draw(SATURATION), draw(HUE)
    batched = color_jitter(images, *factors)
    for image, out, (b, c, s, h) in zip(images, batched, torch.stack(factors, 1), strict=True):
        expected = (image + float(b)).clamp(0, 1)  # OFT's additive brightness
        expected = TF.adjust_contrast(expected, float(c))
        expected = TF.adjust_saturation(expected, float(s))
        expected = TF.adjust_hue(expected, float(h)).clamp(0, 1)
        torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)


def test_batched_crop_is_torchvisions_resized_crop_and_geometry_follows() -> None:
    images = torch.randint(0, 256, (6, 3, 64, 64), dtype=torch.uint8)
    depth = torch.rand(6, 64, 64)
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]).repeat(6, 1, 1)
    transform = ImageTransform(augment=True, center_crop=False)
    torch.manual_seed(3)
    _, out_depth, out_K = transform.batch(images, depth, K)
    torch.manual_seed(3)  # the same crops again: (top, left) drawn as the transform draws them
    top, left = torch.randint(0, 4, (6,)), torch.randint(0, 4, (6,))
    for n in range(6):
        y, x = int(top[n]), int(left[n])
        expected = TF.resized_crop(
            depth[n, None], y, x, 61, 61, [64, 64], interpolation=TF.InterpolationMode.NEAREST
        )[0]
        torch.testing.assert_close(out_depth[n], expected, atol=0, rtol=0)  # type: ignore[index]
        torch.testing.assert_close(out_K[n, 0, 2], torch.tensor((32.0 - x) * 64 / 61))  # type: ignore[index]
    crops = ImageTransform(augment=False, center_crop=True).batch(images)[0]
    for n in range(6):
        expected = TF.resized_crop(images[n], 1, 1, 61, 61, [64, 64], antialias=True)
        torch.testing.assert_close(crops[n], expected.float() / 255, atol=0, rtol=0)


def test_jitter_changes_images_within_the_configured_ranges() -> None:
    """On a grey image contrast, saturation and hue change nothing (torchvision's definitions), so
    what is left is the additive brightness: at most ±0.2, and spread over that range."""
    grey = torch.full((256, 3, 16, 16), 128, dtype=torch.uint8)
    transform = ImageTransform(
        augment=True, center_crop=False, generator=torch.Generator().manual_seed(0)
    )
    shift = transform.batch(grey)[0] - 128 / 255
    per_image = shift.flatten(1)
    assert (per_image.max(1).values - per_image.min(1).values).abs().max() < 1e-6  # uniform
    assert shift.abs().max() <= BRIGHTNESS[1] + 1e-6
    assert per_image[:, 0].min() < -0.15 and per_image[:, 0].max() > 0.15
    # A coloured image changes image by image, and stays an image.
    colour = torch.randint(0, 256, (64, 3, 16, 16), dtype=torch.uint8)
    out = transform.batch(colour)[0]
    assert out.min() >= 0 and out.max() <= 1
    assert (out - transform.batch(colour)[0]).abs().amax(dim=(1, 2, 3)).min() > 0.01
