"""Normalisation statistics in OpenVLA-OFT's ``dataset_statistics.json`` schema, and the two q01/q99
normalisations of the families we follow.

Schema (``prismatic/vla/datasets/rlds/utils/data_utils.py``)::

    {"<dataset name>": {"action":  {"mean", "std", "max", "min", "q01", "q99", "mask"},
                        "proprio": {"mean", "std", "max", "min", "q01", "q99"},
                        "num_transitions": int, "num_trajectories": int,
                        "normalization": "bounds_q99" | "bounds" | "quantiles"}}

``mask`` is True for dimensions that are normalised; OFT leaves the gripper (last action dimension)
raw. ``normalization`` is our addition (absent means ``bounds_q99``), so the rule travels with the
statistics into checkpoints and evaluation:

- ``bounds_q99`` (OpenVLA-OFT, ``NormalizationType.BOUNDS_Q99`` in prismatic's ``data_utils.py``):
  2(x − q01)/(q99 − q01 + 1e-8) − 1 clipped to [−1, 1]; dimensions that never change are set to 0.
- ``bounds`` (OpenVLA-OFT's ALOHA recipe, ``NormalizationType.BOUNDS``): the same with min/max in
  place of q01/q99 (``data_utils.py: normalize_action_and_proprio``, ``modeling_prismatic.py:
  _unnormalize_actions``).
- ``quantiles`` (Pi0.5: LeRobot ``NormalizationMode.QUANTILES`` in
  ``src/lerobot/processor/normalize_processor.py``; openpi ``shared/normalize.py``
  ``_normalize_quantile``): 2(x − q01)/(q99 − q01) − 1 with 1e-8 only where q99 == q01, **not
  clipped**, every dimension (the gripper too). openpi adds 1e-6 to every denominator instead; the
  two differ by about 1e-6 relative and we follow LeRobot, whose checkpoints we import.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from capvector.errors import CapVectorError

# OFT's BOUNDS_Q99 adds this to the denominator so constant dimensions do not divide by zero;
# LeRobot's QUANTILES uses it only where the denominator is 0.
_EPS = 1e-8
BOUNDS_Q99 = "bounds_q99"
BOUNDS = "bounds"
QUANTILES = "quantiles"
NORMALIZATIONS = (BOUNDS_Q99, BOUNDS, QUANTILES)


def check_normalization(normalization: str) -> str:
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"unknown normalization {normalization!r}; known: {list(NORMALIZATIONS)}")
    return normalization


def compute_statistics(
    actions: np.ndarray,
    proprio: np.ndarray,
    num_trajectories: int,
    gripper_raw: bool = True,
    normalization: str = BOUNDS_Q99,
) -> dict[str, Any]:
    """Statistics entry for one dataset from all its transitions: actions (N, A), proprio (N, P).

    ``gripper_raw`` leaves the last action dimension raw (OFT); it is ignored for ``quantiles``,
    which normalises every dimension as LeRobot and openpi do.
    """
    check_normalization(normalization)

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
    if gripper_raw and normalization == BOUNDS_Q99:
        mask[-1] = False
    action_stats["mask"] = mask
    entry = {
        "action": action_stats,
        "proprio": describe(proprio) if proprio.shape[1] else {},
        "num_transitions": int(actions.shape[0]),
        "num_trajectories": int(num_trajectories),
    }
    if normalization != BOUNDS_Q99:
        entry["normalization"] = normalization
    check_finite_statistics(entry, "the statistics computed from the data")
    return entry


def check_finite_statistics(statistics: Mapping[str, Any], source: str) -> None:
    """Refuse statistics that hold a nan or an infinity: they would normalise every sample to nan
    and travel into checkpoints and exports. ``source`` names where they come from."""
    for where, value in _numbers(statistics):
        if not math.isfinite(value):
            raise CapVectorError(
                f"{source}: statistic {where} is {value}; the data it was computed from holds a "
                "non-finite value: fix or drop that data and compute the statistics again"
            )


def _numbers(tree: Any, where: str = "") -> Iterator[tuple[str, float]]:
    """(dotted path, value) of every number in nested dicts and lists, e.g. ``action.q99[3]``."""
    if isinstance(tree, Mapping):
        for key, value in tree.items():
            yield from _numbers(value, f"{where}.{key}" if where else str(key))
    elif isinstance(tree, list | tuple | np.ndarray):
        for i, value in enumerate(tree):
            yield from _numbers(value, f"{where}[{i}]")
    elif isinstance(tree, int | float | np.number):
        yield where, float(tree)


@dataclass
class Normalizer:
    """q01/q99 normalisation to about [-1, 1] by the entry's rule (see the module docstring);
    masked-out dimensions pass through."""

    stats: dict[str, Any]
    """One dataset's entry of the statistics file."""

    @property
    def normalization(self) -> str:
        return check_normalization(self.stats.get("normalization", BOUNDS_Q99))

    def _bounds(self, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        entry = self.stats[kind]
        low, high = ("min", "max") if self.normalization == BOUNDS else ("q01", "q99")
        q01 = np.asarray(entry[low], dtype=np.float32)
        q99 = np.asarray(entry[high], dtype=np.float32)
        mask = np.asarray(entry.get("mask", [True] * len(q01)), dtype=bool)
        if "min" not in entry:  # openpi's norm stats have no min/max; only bounds_q99 reads them
            return q01, q99, mask, np.zeros_like(mask)
        constant = np.asarray(entry["min"], dtype=np.float32) == np.asarray(
            entry["max"], dtype=np.float32
        )
        return q01, q99, mask, constant

    def normalize(self, kind: str, x: np.ndarray) -> np.ndarray:
        """``kind`` is "action" or "proprio"; x (..., D)."""
        if not self.stats.get(kind):
            return x.astype(np.float32)
        q01, q99, mask, constant = self._bounds(kind)
        if self.normalization == QUANTILES:
            scaled = 2 * (x - q01) / self._quantile_range(q01, q99) - 1  # no clipping
            return np.where(mask, scaled, x).astype(np.float32)
        scaled = np.clip(2 * (x - q01) / (q99 - q01 + _EPS) - 1, -1, 1)
        # OFT zeroes dimensions that never change (min == max) instead of mapping them to -1.
        scaled = np.where(constant & mask, 0.0, scaled)
        return np.where(mask, scaled, x).astype(np.float32)

    @staticmethod
    def _quantile_range(q01: np.ndarray, q99: np.ndarray) -> np.ndarray:
        span = q99 - q01
        return np.where(span == 0, np.float32(_EPS), span)

    def unnormalize(self, kind: str, x: np.ndarray) -> np.ndarray:
        if not self.stats.get(kind):
            return x.astype(np.float32)
        q01, q99, mask, _ = self._bounds(kind)
        if self.normalization == QUANTILES:
            raw = (x + 1) * self._quantile_range(q01, q99) / 2 + q01
            return np.where(mask, raw, x).astype(np.float32)
        raw = 0.5 * (x + 1) * (q99 - q01 + _EPS) + q01
        return np.where(mask, raw, x).astype(np.float32)
