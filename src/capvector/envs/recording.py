"""Recording scripted-expert demos, for every suite: the attempt loop and the one HDF5 writer.

A suite's ``record_demos`` (:class:`~capvector.envs.base.Suite`) builds its env and expert and
says how one attempt goes (``attempt(seed) -> Demo | None | SKIP``); :func:`record_file` runs the
attempts into one file, written atomically, and :func:`write_demo` writes each demo as
``data/demo_<i>`` of the robomimic / LIBERO layout :class:`capvector.data.hdf5.HDF5RobotDataset`
reads. What differs between suites is only which datasets and attributes a demo has (robosuite's:
``envs/robosuite/demos.py``; LIBERO's released layout: ``envs/libero/demos.py``).

No simulator import: suites import this module freely.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, TypeVar

import h5py
import numpy as np

from capvector.envs.base import DemoSummary
from capvector.errors import CapVectorError
from capvector.io.frames import check_room_for_demo, write_frames
from capvector.io.outputs import atomic_write_file

FRAME_SUFFIXES = ("_image", "_rgb", "_depth")
"""Per-step datasets stored as frames (one gzip chunk each): robosuite's ``<camera>_image``,
LIBERO's ``<camera>_rgb``, and depth beside either."""
S = TypeVar("S", bound=DemoSummary)
SKIP: Final = "skip"
"""What an attempt returns for a seed that is not an attempt (e.g. a LIBERO placement that is an
official evaluation state): not counted, not recorded."""


@dataclass
class Demo:
    """One successful episode, as the file stores it and as the policy saw it."""

    seed: int
    """The seed its initial state was drawn from."""
    steps: dict[str, np.ndarray | list[str]]
    """Every per-step dataset (``T`` rows) by its key under ``data/demo_<i>``: ``actions``,
    ``states``, ``obs/<key>``, ``annotations`` (strings), ..."""
    attrs: dict[str, Any]
    """The demo group's attributes besides ``num_samples`` and ``seed`` (``model_file``, ...)."""
    length: int
    """Policy steps to success (a demo may go on a few steps after it)."""
    images: dict[str, np.ndarray] = field(default_factory=dict)
    """``{camera: (T, H, W, 3) uint8}`` upright, as ``Episode.observe`` shows them (views of the
    stored frames, which a suite may keep in its own orientation)."""
    proprio: np.ndarray | None = None
    """``(T, 8)`` float32, the observation's proprio (``capvector.envs.base.Observation``)."""

    @property
    def num_samples(self) -> int:
        return len(self.steps["actions"])


def write_demo(group: h5py.Group, demo: Demo) -> None:
    """``demo`` into ``group`` (``data/demo_<i>``): frames chunked per step, strings as UTF-8."""
    for key, value in demo.steps.items():
        if key.endswith(FRAME_SUFFIXES):
            write_frames(group, key, np.asarray(value))
        elif isinstance(value, list):
            group.create_dataset(key, data=value, dtype=h5py.string_dtype(encoding="utf-8"))
        else:
            group.create_dataset(key, data=value)
    group.attrs["num_samples"] = demo.num_samples
    group.attrs["seed"] = demo.seed
    for name, value in demo.attrs.items():
        group.attrs[name] = value


def record_file(
    path: Path,
    summary: S,
    episodes: int,
    attempt: Callable[[int], Demo | None | str],
    *,
    seed: int,
    max_attempts: int,
    give_up: str,
    data_attrs: Callable[[DemoSummary], Mapping[str, Any]],
    bar: Any = None,
) -> S:
    """Attempts from seeds ``seed, seed + 1, ...`` until ``episodes`` demos succeeded, each written
    to ``path`` (atomically: a failure leaves no file) as it lands; then ``data_attrs(summary)``
    on ``data``. More than ``max_attempts`` attempts is an error: ``give_up``, after "only N of M
    attempts succeeded" (say what to change). ``summary`` (its ``path`` and ``task``) is filled
    in and returned."""
    start = time.perf_counter()
    next_seed = seed
    with atomic_write_file(path, what="demo file") as tmp, h5py.File(tmp, "w") as f:
        data = f.create_group("data")
        while summary.demos < episodes:
            if summary.attempts >= max_attempts:
                raise CapVectorError(
                    f"{summary.task}: only {summary.demos} of {summary.attempts} attempts "
                    f"succeeded (seeds from {seed}), short of the {episodes} demos asked for: "
                    f"{give_up}"
                )
            attempt_seed, next_seed = next_seed, next_seed + 1
            demo = attempt(attempt_seed)
            if isinstance(demo, str):  # SKIP
                continue
            summary.attempts += 1
            if demo is not None:
                arrays = [*demo.steps.values(), *demo.attrs.values()]
                check_room_for_demo(path, arrays, "")
                write_demo(data.create_group(f"demo_{summary.demos}"), demo)
                summary.demos += 1
                summary.samples += demo.num_samples
                summary.seeds.append(demo.seed)
                summary.lengths.append(demo.length)
                if bar is not None:
                    bar.update(1)
            if bar is not None:
                bar.set_postfix(attempts=summary.attempts, success=f"{summary.success_rate:.0%}")
        for name, value in data_attrs(summary).items():
            data.attrs[name] = value
    summary.seconds = time.perf_counter() - start
    return summary
