"""Normalisation statistics in OpenVLA-OFT's ``dataset_statistics.json`` schema, and the q01/q99
(BOUNDS_Q99) normalisation OFT trains with.

Schema (``prismatic/vla/datasets/rlds/utils/data_utils.py``)::

    {"<dataset name>": {"action":  {"mean", "std", "max", "min", "q01", "q99", "mask"},
                        "proprio": {"mean", "std", "max", "min", "q01", "q99"},
                        "num_transitions": int, "num_trajectories": int}}

``mask`` is True for dimensions that are normalised; the gripper (last action dimension) is False
and stays raw, as in OFT.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

# OFT's BOUNDS_Q99 adds this to the denominator so constant dimensions do not divide by zero.
_EPS = 1e-8


def compute_statistics(
    actions: np.ndarray, proprio: np.ndarray, num_trajectories: int, gripper_raw: bool = True
) -> dict[str, Any]:
    """Statistics entry for one dataset from all its transitions: actions (N, A), proprio (N, P)."""

    def describe(x: np.ndarray) -> dict[str, list[float]]:
        x = x.astype(np.float64)
        return {
            "mean": x.mean(0).tolist(),
            "std": x.std(0).tolist(),
            "max": x.max(0).tolist(),
            "min": x.min(0).tolist(),
            "q01": np.quantile(x, 0.01, axis=0).tolist(),
            "q99": np.quantile(x, 0.99, axis=0).tolist(),
        }

    action_stats: dict[str, Any] = describe(actions)
    mask = [True] * actions.shape[1]
    if gripper_raw:
        mask[-1] = False
    action_stats["mask"] = mask
    return {
        "action": action_stats,
        "proprio": describe(proprio) if proprio.shape[1] else {},
        "num_transitions": int(actions.shape[0]),
        "num_trajectories": int(num_trajectories),
    }


@dataclass
class Normalizer:
    """q01/q99 normalisation to [-1, 1] (clipped); masked-out dimensions pass through."""

    stats: dict[str, Any]
    """One dataset's entry of the statistics file."""

    def _bounds(self, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        entry = self.stats[kind]
        q01 = np.asarray(entry["q01"], dtype=np.float32)
        q99 = np.asarray(entry["q99"], dtype=np.float32)
        mask = np.asarray(entry.get("mask", [True] * len(q01)), dtype=bool)
        constant = np.asarray(entry["min"], dtype=np.float32) == np.asarray(
            entry["max"], dtype=np.float32
        )
        return q01, q99, mask, constant

    def normalize(self, kind: str, x: np.ndarray) -> np.ndarray:
        """``kind`` is "action" or "proprio"; x (..., D)."""
        if not self.stats.get(kind):
            return x.astype(np.float32)
        q01, q99, mask, constant = self._bounds(kind)
        scaled = np.clip(2 * (x - q01) / (q99 - q01 + _EPS) - 1, -1, 1)
        # OFT zeroes dimensions that never change (min == max) instead of mapping them to -1.
        scaled = np.where(constant & mask, 0.0, scaled)
        return np.where(mask, scaled, x).astype(np.float32)

    def unnormalize(self, kind: str, x: np.ndarray) -> np.ndarray:
        if not self.stats.get(kind):
            return x.astype(np.float32)
        q01, q99, mask, _ = self._bounds(kind)
        raw = 0.5 * (x + 1) * (q99 - q01 + _EPS) + q01
        return np.where(mask, raw, x).astype(np.float32)
