"""What decoding LeRobot video on one thread costs: FFmpeg's default thread pools against one thread.

The LeRobot reader (``capvector.data.lerobot``) decodes and converts on one thread, since FFmpeg's
pools hung or crashed DataLoader workers forked after their parent had decoded. This writes a
256x256 mp4 with LeRobot's default encoding (libsvtav1, CRF 30, a keyframe every 2 frames; libx264
where PyAV lacks SVT-AV1) and reads the same random frames with the reader's own frame lookup
(``_VideoFiles``), once with FFmpeg's pools and once on one thread, alternating query by query so
machine load hits both alike. Times are wall clock: a pool's threads run beside the caller.

    python benchmarks/bench_video_decode.py [--frames 300] [--queries 300]
"""

from __future__ import annotations

import argparse
import random
import statistics
import tempfile
import time
from pathlib import Path

import av
import numpy as np

from capvector.data.lerobot import _VideoFiles

SIZE = 256
FPS = 10


def write_video(path: Path, frames: int) -> str:
    """A moving textured scene, encoded as LeRobot's ``encode_video_frames`` does by default."""
    codec = "libsvtav1" if "libsvtav1" in av.codecs_available else "libx264"
    texture = np.random.default_rng(0).integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=FPS, options={"g": "2", "crf": "30"})
        stream.width, stream.height, stream.pix_fmt = SIZE, SIZE, "yuv420p"
        for t in range(frames):
            image = np.roll(texture, (t, 2 * t), axis=(0, 1))
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    return codec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=300, help="frames in the video")
    parser.add_argument("--queries", type=int, default=300, help="random frames read by each arm")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "video.mp4"
        codec = write_video(path, args.frames)
        readers = {"pools": _VideoFiles(threads=0), "one thread": _VideoFiles()}
        seconds: dict[str, list[float]] = {name: [] for name in readers}
        rng = random.Random(0)
        for _ in range(args.queries):
            t = rng.randrange(args.frames) / FPS
            for name, reader in readers.items():
                start = time.perf_counter()
                reader.frame(path, t, tolerance_s=0.5 / FPS)
                seconds[name].append(time.perf_counter() - start)
    median = {name: statistics.median(s) * 1e3 for name, s in seconds.items()}
    print(f"{codec} {SIZE}x{SIZE}, {args.queries} random frames per arm, median wall time:")
    for name, ms in median.items():
        print(f"  {name:10s} {ms:6.2f} ms per frame")
    print(f"  one thread / pools: {median['one thread'] / median['pools']:.2f}x")


if __name__ == "__main__":
    main()
