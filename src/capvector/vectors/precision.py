"""How much of λ·c a merge keeps once the result is rounded to the weights' dtype.

A capability vector from a short extraction is small next to the weights: added into bf16 weights,
much of it can round away (bf16 keeps 8 significant bits, so an update below ~2⁻⁹ of a weight's
magnitude is lost). Merges compute in float32 and measure, per tensor, the relative error of what
the output dtype kept:

    ‖(round(θ + λc) − round(θ)) − λc‖ / ‖λc‖

where ``round(θ)`` is the base as stored (the merge's input) and ``round(θ + λc)`` the merged
output. Overall it is the same ratio over all tensors together.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from torch import Tensor

WARN_ABOVE = 0.10
"""Relative error above which merges warn (10 % of the vector lost to rounding)."""


@dataclass
class MergePrecision:
    """Squared norms of the intended update λc and of its rounding error, per tensor."""

    dtype: str = ""
    intended_sq: dict[str, float] = field(default_factory=dict)
    error_sq: dict[str, float] = field(default_factory=dict)

    def add(self, key: str, before: Tensor, after: Tensor, intended: Tensor) -> None:
        """Account a chunk of tensor ``key``: ``before``/``after`` as stored, ``intended`` = λc."""
        kept = after.float() - before.float()
        error = kept - intended.float()
        self.intended_sq[key] = self.intended_sq.get(key, 0.0) + float(
            intended.double().square().sum()
        )
        self.error_sq[key] = self.error_sq.get(key, 0.0) + float(error.double().square().sum())
        self.dtype = self.dtype or str(after.dtype).removeprefix("torch.")

    def relative_error(self, key: str | None = None) -> float:
        """Of one tensor, or overall (0 when the update is 0)."""
        if key is not None:
            intended, error = self.intended_sq[key], self.error_sq[key]
        else:
            intended, error = sum(self.intended_sq.values()), sum(self.error_sq.values())
        return math.sqrt(error / intended) if intended > 0 else 0.0

    def worst(self, n: int = 3) -> list[tuple[str, float]]:
        errors = [(k, self.relative_error(k)) for k in self.intended_sq if self.intended_sq[k] > 0]
        return sorted(errors, key=lambda item: -item[1])[:n]

    def summary(self) -> dict[str, Any]:
        """What merges record in their metadata."""
        return {
            "dtype": self.dtype,
            "relative_error": self.relative_error(),
            "worst": [{"tensor": k, "relative_error": e} for k, e in self.worst()],
        }

    def warning(self, threshold: float = WARN_ABOVE) -> str | None:
        return precision_warning(self.summary(), threshold)


def precision_warning(summary: Mapping[str, Any], threshold: float = WARN_ABOVE) -> str | None:
    """A message naming the worst tensors and what to do, when too much of λc was lost."""
    overall = float(summary["relative_error"])
    if overall <= threshold:
        return None
    worst = ", ".join(f"{w['tensor']} ({w['relative_error']:.0%})" for w in summary["worst"])
    return (
        f"the {summary['dtype']} weights keep λc only up to a {overall:.0%} relative error (worst: "
        f"{worst}); merge into float32 weights (capvector merge --dtype float32), or keep the "
        "capability parameters in float32 while the frozen rest is bf16"
    )
