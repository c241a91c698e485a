"""Demo frames kept in memory after their first read, up to ``data.cache_mb``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from capvector.data import keys
from capvector.data.datamodule import RobotDataModule
from capvector.data.hdf5 import DatasetError, HDF5RobotDataset
from conftest import CAMERAS

PROPRIO = ["robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"]
EPISODE_MB = 12 * 2 * 64 * 64 * (3 + 4) / 2**20  # demo_0: 12 steps, 2 cameras, image + depth


def dataset(path: Path, cache_mb: float) -> HDF5RobotDataset:
    return HDF5RobotDataset(
        [path], cameras=CAMERAS, proprio_keys=PROPRIO, chunk_size=8, load_depth=True,
        load_annotations=True, cache_mb=cache_mb,
    )  # fmt: skip


def everything(ds: HDF5RobotDataset) -> list[dict]:
    return ds.__getitems__(list(range(len(ds))))


@pytest.mark.parametrize("cache_mb", [EPISODE_MB, 1024])
def test_cached_samples_are_the_files_and_need_no_file(demo_file: Path, cache_mb: float) -> None:
    """With room for one episode (demo_0) or for all, samples are those read from the file; once
    read, cached episodes are served without the file."""
    uncached, cached = dataset(demo_file, 0), dataset(demo_file, cache_mb)
    for ours, theirs in zip(everything(cached), everything(uncached), strict=True):
        assert ours.keys() == theirs.keys()
        for key, value in ours.items():
            if isinstance(value, torch.Tensor):
                torch.testing.assert_close(value, theirs[key], atol=0, rtol=0)
            else:
                assert value == theirs[key]
    assert uncached._cache.used == 0
    cached_episodes = 1 if cache_mb == EPISODE_MB else 2
    assert cached._cache.used == pytest.approx(cached_episodes * EPISODE_MB * 2**20, rel=0.2)
    moved = demo_file.rename(demo_file.with_suffix(".moved"))
    for ds in (cached, uncached):
        for handle in ds._handles.values():
            handle.close()
        ds._handles.clear()
    first_episode = [i for i, (ep, _) in enumerate(cached.index) if ep == 0]
    assert cached.__getitems__(first_episode)[0][keys.ANNOTATION] == "step 0 of demo 0"
    with pytest.raises(OSError):
        uncached[first_episode[0]]
    moved.rename(demo_file)


def test_cache_mb_is_shared_among_workers_and_checked(demo_file: Path) -> None:
    dm = RobotDataModule(train_files=[str(demo_file)], cache_mb=100, num_workers=4)
    assert dm.train_dataset._cache.limit == 25 * 2**20  # type: ignore[union-attr]
    with pytest.raises(DatasetError, match=r"data.cache_mb is -1"):
        dataset(demo_file, -1)
