"""Where a policy runs and in what precision: the ``--device`` and ``--precision`` of every tool
that runs a model (``evaluate``, ``serve``, ``sweep-scale``, ``import-original``), resolved in one
place so they mean the same everywhere."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Literal, get_args

import torch

from capvector.errors import CapVectorError

Precision = Literal["32-true", "bf16-mixed", "16-mixed"]
"""Lightning's spellings: float32, or the weights in float32 under autocast to bf16 / fp16."""
PRECISIONS: tuple[str, ...] = get_args(Precision)
AUTOCAST_DTYPES = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}


def resolve_device(device: str | None) -> torch.device:
    """``device``, or CUDA when there is one and the CPU otherwise; refused when unusable."""
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
        torch.empty(0, device=resolved)
    except (RuntimeError, AssertionError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CapVectorError(f"--device {device} is not usable here ({first}); e.g. cpu") from err
    return resolved


def resolve_precision(device: torch.device, precision: str | None) -> Precision:
    """``precision``, checked against ``device``; by default bf16 autocast on a GPU (what the
    full-size presets train in) and float32 elsewhere."""
    if precision is None:
        return "bf16-mixed" if device.type == "cuda" else "32-true"
    if precision not in PRECISIONS:
        raise CapVectorError(f"--precision {precision!r} is none of {', '.join(PRECISIONS)}")
    if precision == "16-mixed" and device.type == "cpu":  # Lightning refuses it on CPU too
        raise CapVectorError(
            "--precision 16-mixed needs a GPU (no fp16 autocast on CPU); use bf16-mixed"
        )
    return precision  # type: ignore[return-value]  # one of PRECISIONS, checked above


def native_bf16_cpu() -> bool:
    """Whether this CPU computes bf16 in hardware (AVX512-BF16 or AMX). Elsewhere torch emulates
    it, and a bf16 matmul costs more than a float32 one: 4.3x on an Ice Lake Xeon (2026-12-07)."""
    return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())


def precision_context(
    device: torch.device, precision: Precision
) -> Callable[[], AbstractContextManager]:
    """What each forward runs under: nothing for ``32-true``, else ``torch.autocast``, as
    Lightning's mixed-precision plugins do (weights stay float32)."""
    dtype = AUTOCAST_DTYPES.get(resolve_precision(device, precision))
    if dtype is None:
        return nullcontext
    return lambda: torch.autocast(device.type, dtype=dtype)
