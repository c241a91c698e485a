"""What decoding LeRobot video on one thread costs: FFmpeg's default thread pools against one thread.

The LeRobot reader (``capvector.data.lerobot``) decodes and converts on one thread, since FFmpeg's
pools hung or crashed DataLoader workers forked after their parent had decoded. This writes a
256x256 mp4 with LeRobot's default encoding (libsvtav1, CRF 30, a keyframe every 2 frames; libx264
where PyAV lacks SVT-AV1) and reads the same random frames the reader's way (seek to the keyframe
at or before the frame, decode forward, convert to RGB), once with FFmpeg's pools and once on one
thread, alternating query by query so machine load hits both alike. Times are wall clock: a pool's
threads run beside the caller.

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


def open_video(path: Path, threads: int) -> av.container.InputContainer:
    """``threads`` 0: FFmpeg's default (a pool sized to the cores); 1: the reader's."""
    container = av.open(str(path))
    container.streams.video[0].codec_context.thread_count = threads
    return container


def read_frame(container: av.container.InputContainer, t: float, threads: int) -> np.ndarray:
    stream = container.streams.video[0]
    time_base = float(stream.time_base)
    container.seek(int(t / time_base), stream=stream, backward=True, any_frame=False)
    for frame in container.decode(stream):
        if frame.pts is not None and abs(frame.pts * time_base - t) < 0.5 / FPS:
            return frame.to_ndarray(format="rgb24", threads=threads)
    raise RuntimeError(f"no frame at t={t}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=300, help="frames in the video")
    parser.add_argument("--queries", type=int, default=300, help="random frames read by each arm")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "video.mp4"
        codec = write_video(path, args.frames)
        arms = {"pools": 0, "one thread": 1}
        containers = {name: open_video(path, threads) for name, threads in arms.items()}
        seconds: dict[str, list[float]] = {name: [] for name in arms}
        rng = random.Random(0)
        for _ in range(args.queries):
            t = rng.randrange(args.frames) / FPS
            for name, threads in arms.items():
                start = time.perf_counter()
                read_frame(containers[name], t, threads)
                seconds[name].append(time.perf_counter() - start)
        for container in containers.values():
            container.close()
    median = {name: statistics.median(s) * 1e3 for name, s in seconds.items()}
    print(f"{codec} {SIZE}x{SIZE}, {args.queries} random frames per arm, median wall time:")
    for name, ms in median.items():
        print(f"  {name:10s} {ms:6.2f} ms per frame")
    print(f"  one thread / pools: {median['one thread'] / median['pools']:.2f}x")


if __name__ == "__main__":
    main()
