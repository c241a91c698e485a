"""How recorded demos store per-step images and depth in HDF5 (``capvector demos``, robosuite and
LIBERO alike)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from capvector.io.outputs import check_room


def write_frames(group: h5py.Group, key: str, frames: np.ndarray) -> None:
    """Per-step images or depth ``(T, ...)``: one gzip chunk per frame, as a data loader reads
    random frames (gzip shrinks them ~3x)."""
    group.create_dataset(
        key, data=frames, chunks=(1, *frames.shape[1:]), compression="gzip", compression_opts=4
    )


DEMO_METADATA_BYTES = 1 << 20
"""Room kept for one demo's HDF5 metadata (chunk indexes, attributes): generous."""


def check_room_for_demo(out: Path | str, arrays: Sequence[object], model_xml: str) -> None:
    """Refuse a demo its disk has no room for, before libhdf5 writes any of it.

    libhdf5 writes a gzip-chunked dataset's chunks when h5py frees the dataset, inside
    ``ObjectID.__dealloc__``, where Python can only print an error ("Exception ignored"): on a
    full disk the recorder never learnt of it, went on recording for minutes, and libhdf5 crashed
    closing the file (exit 139, its temporary and lock left behind). Room for the demo
    uncompressed (gzip only shrinks it) keeps libhdf5 from meeting the full disk at all.
    """
    needed = sum(np.asarray(a).nbytes for a in arrays) + len(model_xml.encode())
    check_room(out, needed + DEMO_METADATA_BYTES, "--out")
