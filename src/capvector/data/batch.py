"""The training batch and a dataset sample: the one place their keys, shapes and dtypes are
declared.

Every dataset yields a ``Sample``, the default collate stacks samples into a ``Batch``, and every
backbone, objective and teacher reads a ``Batch``, so a backbone never depends on where the data
came from (HDF5, LeRobot, a live simulator). Code indexes them with these literal keys
(``batch["images"]``), which type checkers verify; ``tests/test_batch.py`` fails on a key read
anywhere in ``src/`` that is not declared here.

B batch, N_cam cameras, H x W pixels, P proprio dims, T chunk steps, A action dims.
"""

from __future__ import annotations

from typing import TypedDict

from torch import Tensor


class _Observation(TypedDict):
    images: Tensor
    """(B, N_cam, 3, H, W) float32 in [0, 1], upright, cameras in ``DataSpec.cameras`` order."""
    proprio: Tensor
    """(B, P) float32, normalised with the dataset's q01/q99 statistics by the family's rule
    (``capvector.data.statistics``: clipped to [-1, 1] for OpenVLA-OFT, not clipped for Pi0.5)."""
    instruction: list[str]
    """B language instructions of the task."""


class Batch(_Observation, total=False):
    """What a backbone's ``forward`` reads. Acting (``VLAPolicy``) passes the observation alone;
    the datamodule's training batches carry ``actions``, ``index`` and ``noise_seed`` too, and the
    optional keys when the data config loads them."""

    actions: Tensor
    """(B, T, A) float32: the action chunk, normalised as ``proprio`` (OFT leaves the gripper
    raw)."""
    index: Tensor
    """(B,) int64: each sample's position in its dataset (``dataset[i]``)."""
    noise_seed: Tensor
    """(B,) int64: a per-sample seed for the training noise of flow-matching backbones (ε and t).
    ``RobotDataModule`` sets it while training, from (``data.seed``, epoch, ``index``), so a sample
    draws the same noise whichever process it lands on; without it backbones use the global RNG."""
    depth: Tensor
    """(B, N_cam, H, W) float32 depth in metres (``data.load_depth``, for geometric teachers)."""
    intrinsics: Tensor
    """(B, N_cam, 3, 3) float32 pinhole intrinsics in pixels of the stored image (with
    ``depth``)."""
    annotation: list[str]
    """B text answers about the scene at this step (``data.load_annotations``, for reasoning)."""


class _SampleRequired(TypedDict):
    images: Tensor
    proprio: Tensor
    instruction: str
    actions: Tensor
    index: int


class Sample(_SampleRequired, total=False):
    """One item of a dataset: a ``Batch``'s keys and values without the leading B (``instruction``
    and ``annotation`` a ``str``, ``index`` an ``int``), and no ``noise_seed`` (the datamodule
    adds it per batch)."""

    depth: Tensor
    intrinsics: Tensor
    annotation: str


__all__ = ["Batch", "Sample"]
