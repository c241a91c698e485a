"""What ``data.cache_mb`` saves: a batch read from the demo files against the same batch from memory.

Two datasets over the same HDF5 demos: one without a frame cache (every frame read and gunzipped
from its file, as when the demos outgrow ``data.cache_mb``), one with every episode cached first.
Both read the same random batches, interleaved batch by batch, so machine load hits both alike; the
times are CPU time of this process. Also prints the decoded size of the demos: the ``cache_mb`` that
holds them all.

    python benchmarks/bench_frame_cache.py --data runs/libero_study/demos_down50/demos \\
        [--batch 16] [--batches 60] [--depth]
"""

from __future__ import annotations

import argparse
import random
import statistics
import time
from pathlib import Path

import torch

from capvector.data.hdf5 import HDF5RobotDataset


def batch_seconds(dataset: HDF5RobotDataset, indices: list[int]) -> float:
    start = time.process_time()
    dataset.__getitems__(indices)
    return time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a demo file or a folder of them")
    parser.add_argument("--cameras", nargs="+", default=["agentview", "robot0_eye_in_hand"])
    parser.add_argument("--proprio-keys", nargs="+", default=["ee_states", "gripper_states"])
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--batches", type=int, default=60)
    parser.add_argument("--depth", action="store_true", help="read depth too (spatial alignment)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    files = sorted(args.data.glob("*.hdf5")) if args.data.is_dir() else [args.data]
    settings = dict(cameras=args.cameras, proprio_keys=args.proprio_keys, chunk_size=8,
                    load_depth=args.depth)  # fmt: skip
    from_files = HDF5RobotDataset(files, cache_mb=0, **settings)
    decoded = sum(from_files._episode_bytes(e) for e in from_files.episodes) / 2**20
    from_memory = HDF5RobotDataset(files, cache_mb=decoded + 1, **settings)
    for sample, (_, t) in enumerate(from_memory.index):  # fill the cache: every episode once
        if t == 0:
            from_memory._frames(sample)
    rng = random.Random(0)
    files_s, memory_s = [], []
    for _ in range(args.batches):
        indices = [rng.randrange(len(from_files)) for _ in range(args.batch)]
        files_s.append(batch_seconds(from_files, indices))
        memory_s.append(batch_seconds(from_memory, indices))
    print(f"{len(files)} files, {len(from_files.episodes)} episodes, {decoded:.0f} MiB decoded")
    print(f"\n| batch of {args.batch} | CPU ms (median of {args.batches}) | × from memory |")
    print("|---|---|---|")
    memory = statistics.median(memory_s)
    for name, times in (("from the files (cache_mb=0)", files_s), ("from memory", memory_s)):
        median = statistics.median(times)
        print(f"| {name} | {median * 1000:.1f} | {median / memory:.1f} |")


if __name__ == "__main__":
    main()
