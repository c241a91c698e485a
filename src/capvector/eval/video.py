"""Write rollout frames to mp4 (H.264 through imageio-ffmpeg) or GIF, atomically."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from capvector.io.outputs import atomic_write_file


def write_video(
    frames: Sequence[np.ndarray],
    path: str | os.PathLike[str],
    *,
    fps: int = 20,
    scale: int = 1,
) -> Path:
    """Write (H, W, 3) uint8 ``frames`` to ``path``; the suffix picks the format (.mp4 or .gif).

    ``scale`` repeats pixels (nearest neighbour) so 64 px policy views stay watchable. Odd mp4
    sizes are padded by one black row/column (H.264 in yuv420p needs even sizes). 20 fps is
    robosuite's control rate, i.e. real time.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise ValueError(f"write_video writes .mp4 or .gif, not {path.name!r}")
    if not frames:
        raise ValueError(f"no frames to write to {path}")
    if scale < 1:
        raise ValueError(f"scale must be a positive integer, got {scale}")
    video = np.stack([np.asarray(f, dtype=np.uint8) for f in frames])
    if video.ndim != 4 or video.shape[-1] != 3:
        raise ValueError(f"frames must be (H, W, 3) uint8, got {video.shape[1:]}")
    if scale > 1:
        video = video.repeat(scale, axis=1).repeat(scale, axis=2)
    # A temporary sibling with the same suffix (ffmpeg and Pillow pick the format from it).
    with atomic_write_file(path) as tmp:
        if suffix == ".mp4":
            pad_h, pad_w = video.shape[1] % 2, video.shape[2] % 2
            if pad_h or pad_w:
                video = np.pad(video, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)))
            with imageio.get_writer(
                tmp,
                format="FFMPEG",
                mode="I",
                fps=fps,
                codec="libx264",
                pixelformat="yuv420p",
                macro_block_size=1,
                ffmpeg_log_level="error",
            ) as writer:
                for frame in video:
                    writer.append_data(frame)
        else:
            # Pillow's GIF writer takes the frame duration in milliseconds.
            imageio.mimsave(tmp, list(video), format="GIF", duration=1000 / fps, loop=0)
    return path
