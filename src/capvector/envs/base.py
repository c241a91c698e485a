"""The policy interface shared by robosuite rollouts and the LIBERO adapter (no simulator imports).

A policy is any callable ``policy(observation) -> (T, 7)`` array-like of actions: OSC deltas
(dx, dy, dz, drx, dry, drz) and the gripper, in the convention the caller declares (our demos and
robosuite: -1 open, +1 close).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypedDict

import numpy as np

ACTION_DIM = 7


class Observation(TypedDict, total=False):
    """What a policy receives; key names match ``capvector.data.batch.Batch``'s."""

    images: dict[str, np.ndarray]
    """``{camera: (H, W, 3) uint8}``, upright, in the order the caller asked for cameras."""
    proprio: np.ndarray
    """(8,) float32, raw (not normalised): eef pos, eef axis-angle, 2 finger joints."""
    instruction: str
    depth: dict[str, np.ndarray]
    """``{camera: (H, W) float32}`` metres along the optical axis (only when asked for)."""


Policy = Callable[[Observation], Any]
"""``policy(observation) -> (T, 7)`` actions (a single (7,) action counts as a chunk of 1)."""


@dataclass
class EpisodeResult:
    success: bool
    steps: int
    """Policy steps executed (the step at which success was reached, when it was)."""
    reason: str | None
    """Why the episode failed (step limit, simulation fault, non-finite action); None on success."""
    frames: list[np.ndarray] | None
    """One (H, N_cam * W, 3) uint8 frame per state (cameras side by side), when video was asked."""
    seed: int
    """The seed of the initial state (robosuite) or the index of the fixed init state (LIBERO)."""
    task: str
    robot: str
    variant: str | None = None
    """The scene variant the episode ran in (``capvector.envs.robosuite.variants``); None: as trained."""
    final_proprio: tuple[float, ...] | None = None
    """The robot's raw proprio after the last step (eef pos, axis-angle, fingers): where it ended,
    comparable across simulators (``capvector evaluate --json``)."""


def as_chunk(actions: Any) -> np.ndarray:
    """A policy's output as a (T, 7) float64 array; raises on any other shape."""
    chunk = np.asarray(actions, dtype=np.float64)
    if chunk.ndim == 1:
        chunk = chunk[None]
    if chunk.ndim != 2 or chunk.shape[1] != ACTION_DIM or chunk.shape[0] == 0:
        raise ValueError(f"policy must return (T, {ACTION_DIM}) actions, got shape {chunk.shape}")
    return chunk
