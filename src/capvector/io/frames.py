"""How recorded demos store per-step images and depth in HDF5 (``capvector demos``, robosuite and
LIBERO alike)."""

from __future__ import annotations

import h5py
import numpy as np


def write_frames(group: h5py.Group, key: str, frames: np.ndarray) -> None:
    """Per-step images or depth ``(T, ...)``: one gzip chunk per frame, as a data loader reads
    random frames (gzip shrinks them ~3x)."""
    group.create_dataset(
        key, data=frames, chunks=(1, *frames.shape[1:]), compression="gzip", compression_opts=4
    )
