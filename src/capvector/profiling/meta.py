"""Building a preset on the ``meta`` device (no memory, no download).

On torch 2.6 (the oldest our ranges admit) a module whose first import happens inside
``with torch.device("meta")`` can fail at import: module-level code that makes a tensor and reads
it (``Tensor.item()``) gets a meta tensor, which has no value ("Tensor.item() cannot be called on
meta tensors"). The families import transformers, timm and torchvision lazily, inside their
constructors, so everything a meta build imports is imported here first, outside the device.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from contextlib import contextmanager

import torch

BUILD_IMPORTS = (
    "torchvision",
    "timm.models.vision_transformer",
    "transformers",
    "transformers.models.llama.modeling_llama",
    "transformers.models.gemma.modeling_gemma",
    "transformers.models.siglip.modeling_siglip",
    "transformers.models.qwen2_5_vl.modeling_qwen2_5_vl",
    "transformers.models.qwen3_vl.modeling_qwen3_vl",
    "peft",
)
"""What the families' constructors (and ``inject_lora``) import on first use."""


def import_build_dependencies() -> None:
    """Import ``BUILD_IMPORTS``; one missing (Qwen3-VL before transformers 4.57) is skipped: the
    preset that needs it fails at build with transformers' own message."""
    for name in BUILD_IMPORTS:
        try:
            importlib.import_module(name)
        except ImportError:
            continue


@contextmanager
def on_meta() -> Iterator[None]:
    """``torch.device("meta")`` with the build's imports done outside it."""
    import_build_dependencies()
    with torch.device("meta"):
        yield
