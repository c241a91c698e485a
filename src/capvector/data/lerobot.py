"""Robot demonstrations in a LeRobotDataset v3.0 folder, read without the ``lerobot`` package.

Layout read here (LeRobot ``src/lerobot/datasets/utils.py`` path constants,
``dataset_metadata.py``, ``dataset_reader.py``)::

    meta/info.json                          codebase_version "v3.0", fps, features, data_path, video_path
    meta/stats.json                         per feature: mean, std, min, max, count, q01 ... q99
    meta/tasks.parquet                      column task_index, indexed by the task (pandas metadata)
    meta/episodes/chunk-XXX/file-XXX.parquet  one row per episode: data/{chunk,file}_index and,
                                            per camera, videos/<key>/{chunk_index,file_index,from_timestamp}
    data/chunk-XXX/file-XXX.parquet         one row per frame, many episodes per file
    videos/<key>/chunk-XXX/file-XXX.mp4     many episodes concatenated per file

A sample has the same keys, shapes and normalisation as ``HDF5RobotDataset``: the observation at
frame t and the action chunk t..t+T-1. Unlike LeRobot, which clamps the chunk at the episode end and
marks ``action_is_pad``, chunks never run past the end (OFT's ``chunk_act_obs``, as the HDF5 reader):
only frames 0..len-T start a sample, and episodes shorter than T are skipped.

pyarrow and PyAV are imported lazily (the ``lerobot`` extra), as LeRobot does for optional backends.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch.utils.data import Dataset

from capvector.data.batch import Sample
from capvector.data.hdf5 import DatasetError
from capvector.data.statistics import (
    BOUNDS_Q99,
    Normalizer,
    check_finite_statistics,
    check_normalization,
    compute_statistics,
)
from capvector.data.transforms import ImageTransform
from capvector.errors import missing_extra

if TYPE_CHECKING:
    import av.container
    import pyarrow

logger = logging.getLogger(__name__)

CODEBASE_VERSION = "v3.0"

# LeRobot's defaults (``utils.py``); v3 info.json files carry the same templates.
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
DEFAULT_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DEFAULT_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"

_STAT_FIELDS = ("mean", "std", "max", "min", "q01", "q99")
_MAX_OPEN_VIDEOS = 16
"""Open containers per process; a large dataset has many mp4 files, each holding a file handle."""


def _pyarrow() -> tuple[Any, Any]:
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError as e:  # also a pyarrow built against another numpy major version
        raise missing_extra("reading LeRobot datasets", "lerobot", e) from e
    return pyarrow, pyarrow.parquet


def _av() -> Any:
    try:
        import av
    except ImportError as e:
        raise missing_extra("reading LeRobot datasets", "lerobot", e) from e
    return av


def _task_column(table: pyarrow.Table) -> str | None:
    """The column of ``meta/tasks.parquet`` that holds the task strings.

    LeRobot keeps tasks as a pandas frame indexed by the task string and writes it with
    ``DataFrame.to_parquet`` (``utils.py: write_tasks``), so the strings are the frame's index. Its
    v2.1 -> v3.0 converter names that index ``task`` and pandas stores it as a column of that name;
    its recorder (``LeRobotDataset.save_episode_tasks``) leaves it unnamed and pandas stores it as
    ``__index_level_0__``. Both are listed in the schema's pandas metadata (``index_columns``),
    which is what ``pandas.read_parquet`` restores the index from; a RangeIndex is recorded there as
    a dict, not a column, and cannot hold strings.
    """
    if "task" in table.column_names:
        return "task"
    index = [
        c
        for c in (table.schema.pandas_metadata or {}).get("index_columns", [])
        if isinstance(c, str)
    ]
    if len(index) == 1 and index[0] in table.column_names:
        return index[0]
    return None


@dataclass
class LeRobotEpisode:
    index: int
    """``episode_index`` in the dataset."""
    start: int
    """Row of the episode's first frame in the reader's frame arrays."""
    length: int
    videos: dict[str, tuple[Path, float]]
    """camera key -> (mp4 file, ``from_timestamp`` of the episode inside that file)."""


def statistics_from_lerobot(
    stats: Mapping[str, Any],
    num_trajectories: int,
    action_key: str = "action",
    state_key: str | None = "observation.state",
    gripper_raw: bool = True,
    normalization: str = BOUNDS_Q99,
) -> dict[str, Any] | None:
    """An OFT ``dataset_statistics.json`` entry converted from a ``meta/stats.json`` dict.

    Returns None when the file lacks a field q01/q99 normalisation needs (LeRobot datasets recorded
    before quantile stats have only mean/std/min/max; LeRobot then refuses QUANTILES mode).
    ``num_transitions`` is the action feature's ``count``. As ``compute_statistics``, the last action
    dimension (the gripper) is left raw when ``gripper_raw`` and ``normalization`` is OFT's
    ``bounds_q99``; ``quantiles`` (Pi0.5) normalises every dimension and is recorded in the entry.
    """
    check_normalization(normalization)

    def convert(key: str) -> dict[str, list[float]] | None:
        feature = stats.get(key, {})
        if not all(field in feature for field in _STAT_FIELDS):
            return None
        return {f: np.asarray(feature[f], np.float64).reshape(-1).tolist() for f in _STAT_FIELDS}

    action = convert(action_key)
    proprio = convert(state_key) if state_key else {}
    if action is None or proprio is None:
        return None
    mask = [True] * len(action["q01"])
    if gripper_raw and normalization == BOUNDS_Q99:
        mask[-1] = False
    count = stats[action_key].get("count")
    entry = {
        "action": {**action, "mask": mask},
        "proprio": proprio,
        "num_transitions": int(np.asarray(count).reshape(-1)[0]) if count is not None else 0,
        "num_trajectories": int(num_trajectories),
    }
    if normalization != BOUNDS_Q99:
        entry["normalization"] = normalization
    return entry


class LeRobotV3Dataset(Dataset):
    """Samples (observation at t, action chunk t..t+T-1) from a LeRobotDataset v3.0 folder."""

    def __init__(
        self,
        root: str | Path,
        cameras: Sequence[str],
        state_key: str | None = "observation.state",
        action_key: str = "action",
        chunk_size: int = 8,
        statistics: dict[str, Any] | None = None,
        transform: ImageTransform | None = None,
        episodes: Sequence[int] | None = None,
        normalization: str = BOUNDS_Q99,
    ) -> None:
        """
        Args:
            root: the dataset folder (the one holding ``meta/``, ``data/``, ``videos/``).
            cameras: video feature keys, e.g. ``observation.images.image``, in the model's order.
            state_key: the proprio feature; None for a dataset without one (proprio is then empty).
            action_key: the action feature.
            chunk_size: actions per sample.
            statistics: an entry of ``dataset_statistics.json`` (e.g. the training set's for a
                validation split); None converts ``meta/stats.json`` or recomputes from the data.
            transform: image transform; default is the deterministic evaluation view.
            episodes: ``episode_index`` values to read (LeRobot's ``episodes`` argument); None for all.
            normalization: the rule of statistics converted or computed here
                (``capvector.data.statistics``); given ``statistics`` carry their own.
        """
        self.normalization = check_normalization(normalization)
        _pyarrow()  # fail before reading anything when the extra is missing
        self.root = Path(root)
        self.cameras = list(cameras)
        self.state_key = state_key
        self.action_key = action_key
        self.chunk_size = chunk_size
        self.transform = transform or ImageTransform(augment=False, center_crop=False)

        self.info = self._read_info()
        self.fps = float(self.info["fps"])
        # Half a frame period: on a regular frame grid exactly one frame lies this close to a query.
        # LeRobot asserts a tighter 1e-4 s (``tolerance_s``); both pick the same frame when the
        # stored timestamps sit on the grid, and ours also tolerates float32 timestamp rounding.
        self.tolerance_s = 0.5 / self.fps
        self._check_features()
        self.tasks = self._read_tasks()
        table = self._read_episode_table()
        selected = self._select_episodes(table, episodes)

        frames = self._read_frames(table, selected)
        self._actions: np.ndarray = frames["action"]
        self._proprio: np.ndarray = frames["proprio"]
        self._timestamps: np.ndarray = frames["timestamp"]
        self._task_index: np.ndarray = frames["task_index"]

        table_row = {int(table["episode_index"][row]): row for row in selected}
        self.episodes: list[LeRobotEpisode] = []
        rows, sample_episode = [], []
        for episode_index, start, length in frames["episodes"]:
            if length < chunk_size:
                continue  # too short for one full chunk; OFT and the HDF5 reader drop it as well
            videos = self._episode_videos(table, table_row[episode_index])
            self.episodes.append(LeRobotEpisode(episode_index, start, length, videos))
            rows.append(np.arange(start, start + length - chunk_size + 1))
            sample_episode.append(np.full(length - chunk_size + 1, len(self.episodes) - 1))
        if not self.episodes:
            raise DatasetError(
                f"{self.root} holds no selected episode of at least chunk_size={chunk_size} frames"
            )
        self._rows = np.concatenate(rows)
        self._sample_episode = np.concatenate(sample_episode)
        self._check_videos_exist()

        self.action_dim = int(self._actions.shape[1])
        self.proprio_dim = int(self._proprio.shape[1])
        self.statistics = statistics or self._statistics()
        self.normalizer = Normalizer(self.statistics)
        self._videos: _VideoFiles | None = None

    # -- metadata ----------------------------------------------------------------------------

    def _meta_file(self, relative: str) -> Path:
        path = self.root / relative
        if not path.exists():
            if not self.root.is_dir():
                raise DatasetError(f"LeRobot dataset folder {self.root} does not exist")
            raise DatasetError(
                f"{self.root} is not a complete LeRobot v3 dataset: {relative} is missing. Download "
                "the whole dataset folder (meta/, data/, videos/)"
            )
        return path

    def _read_info(self) -> dict[str, Any]:
        info = json.loads(self._meta_file(INFO_PATH).read_text())
        version = str(info.get("codebase_version", "unknown"))
        major = version.lstrip("v").split(".")[0]
        if major in ("1", "2"):
            raise DatasetError(
                f"{self.root} is a LeRobot {version} dataset; this reader needs {CODEBASE_VERSION}. "
                "v2 folders must be converted with LeRobot's converter: `python -m "
                "lerobot.scripts.convert_dataset_v21_to_v30 --repo-id=<id> --root=<folder>` "
                "(`lerobot.datasets.v30.convert_dataset_v21_to_v30` in older LeRobot releases)"
            )
        if major != "3":
            # LeRobot's check_version_compatibility: same major reads, a minor difference only warns.
            raise DatasetError(
                f"{self.root} has codebase_version {version!r}; this reader reads {CODEBASE_VERSION}"
            )
        return info

    def _check_features(self) -> None:
        features: dict[str, Any] = self.info.get("features", {})
        visual = [k for k, f in features.items() if f.get("dtype") in ("video", "image")]
        for camera in self.cameras:
            if camera not in features:
                raise DatasetError(
                    f"camera {camera!r} is not a feature of {self.root}; its cameras are {visual}. "
                    "Set data.cameras to some of these keys"
                )
            if features[camera].get("dtype") != "video":
                raise DatasetError(
                    f"camera {camera!r} of {self.root} has dtype {features[camera].get('dtype')!r}: "
                    "images stored inside the parquet files are not supported, only video cameras. "
                    "Use the dataset's video (mp4) version, e.g. lerobot/libero instead of "
                    "HuggingFaceVLA/libero"
                )
        others = [k for k in features if k not in visual]
        for role, key in (("state_key", self.state_key), ("action_key", self.action_key)):
            if key is not None and key not in features:
                raise DatasetError(
                    f"{role} {key!r} is not a feature of {self.root}; its non-camera features are "
                    f"{others}"
                )

    def _read_tasks(self) -> dict[int, str]:
        _, pq = _pyarrow()
        path = self._meta_file(TASKS_PATH)
        table = pq.read_table(path)
        column = _task_column(table)
        if column is None or "task_index" not in table.column_names:
            raise DatasetError(
                f"{path} has columns {table.column_names} and no task column, named or recorded as "
                "the pandas index; expected task_index and the task strings. Rewrite it with "
                "LeRobot's write_tasks (a frame with column task_index indexed by task)"
            )
        return dict(
            zip(
                table.column("task_index").to_pylist(),
                table.column(column).to_pylist(),
                strict=True,
            )
        )

    def _episode_columns(self) -> list[str]:
        columns = ["episode_index", "data/chunk_index", "data/file_index"]
        for camera in self.cameras:
            columns += [
                f"videos/{camera}/{c}" for c in ("chunk_index", "file_index", "from_timestamp")
            ]
        return columns

    def _read_episode_table(self) -> dict[str, list[Any]]:
        _, pq = _pyarrow()
        # All files under meta/episodes, in path order (LeRobot's ``load_nested_dataset``); the
        # ``stats/...`` columns are not read.
        folder = self._meta_file(EPISODES_DIR)
        paths = sorted(folder.glob("*/*.parquet"))
        if not paths:
            raise DatasetError(
                f"{self.root} is not a complete LeRobot v3 dataset: {EPISODES_DIR} holds no "
                "chunk-XXX/file-XXX.parquet"
            )
        columns = self._episode_columns()
        table: dict[str, list[Any]] = {c: [] for c in columns}
        for path in paths:
            missing = [c for c in columns if c not in pq.read_schema(path).names]
            if missing:
                raise DatasetError(f"{path} lacks the episode columns {missing}")
            part = pq.read_table(path, columns=columns)
            for c in columns:
                table[c] += part.column(c).to_pylist()
        return table

    def _select_episodes(
        self, table: dict[str, list[Any]], episodes: Sequence[int] | None
    ) -> list[int]:
        """Rows of the episode table to read, in ``episode_index`` order."""
        row_of = {int(e): row for row, e in enumerate(table["episode_index"])}
        wanted = sorted(row_of) if episodes is None else sorted({int(e) for e in episodes})
        unknown = [e for e in wanted if e not in row_of]
        if unknown:
            raise DatasetError(
                f"episodes {unknown} are not in {self.root}; it has episode_index "
                f"{min(row_of)}..{max(row_of)} ({len(row_of)} episodes)"
            )
        return [row_of[e] for e in wanted]

    def _episode_videos(
        self, table: dict[str, list[Any]], row: int
    ) -> dict[str, tuple[Path, float]]:
        template = self.info.get("video_path") or DEFAULT_VIDEO_PATH
        videos = {}
        for camera in self.cameras:
            relative = template.format(
                video_key=camera,
                chunk_index=table[f"videos/{camera}/chunk_index"][row],
                file_index=table[f"videos/{camera}/file_index"][row],
            )
            videos[camera] = (
                self.root / relative,
                float(table[f"videos/{camera}/from_timestamp"][row]),
            )
        return videos

    def _check_videos_exist(self) -> None:
        files = {path for episode in self.episodes for path, _ in episode.videos.values()}
        missing = sorted(str(p) for p in files if not p.is_file())
        if missing:
            raise DatasetError(f"video files of {self.root} are missing: {missing[:5]}")

    # -- frames -------------------------------------------------------------------------------

    def _read_frames(self, table: dict[str, list[Any]], selected: list[int]) -> dict[str, Any]:
        """Numeric columns of the selected episodes, sorted by (episode_index, frame_index)."""
        _, pq = _pyarrow()
        template = self.info.get("data_path") or DEFAULT_DATA_PATH
        by_file: dict[Path, set[int]] = {}
        for row in selected:
            path = self.root / template.format(
                chunk_index=table["data/chunk_index"][row], file_index=table["data/file_index"][row]
            )
            by_file.setdefault(path, set()).add(int(table["episode_index"][row]))
        vectors = [self.action_key] + ([self.state_key] if self.state_key else [])
        columns = ["episode_index", "frame_index", "timestamp", "task_index", *vectors]
        parts: dict[str, list[np.ndarray]] = {c: [] for c in columns}
        for path, wanted in by_file.items():
            if not path.is_file():
                raise DatasetError(f"data file {path} of episodes {sorted(wanted)} is missing")
            missing = [c for c in columns if c not in pq.read_schema(path).names]
            if missing:
                raise DatasetError(f"{path} lacks the frame columns {missing}")
            part = pq.read_table(path, columns=columns)
            episode_index = part.column("episode_index").to_numpy()
            keep = np.isin(episode_index, sorted(wanted))
            kept = {
                c: (
                    _vectors(part.column(c), path, c) if c in vectors else part.column(c).to_numpy()
                )[keep]
                for c in columns
            }
            for c in vectors:
                self._check_vectors(kept[c], c, path, kept["episode_index"], kept["frame_index"])
            for c in columns:
                parts[c].append(kept[c])
        data = {c: np.concatenate(v) for c, v in parts.items()}
        order = np.lexsort((data["frame_index"], data["episode_index"]))
        data = {c: v[order] for c, v in data.items()}

        episode_ids, starts, lengths = np.unique(
            data["episode_index"], return_index=True, return_counts=True
        )
        wanted_ids = sorted(int(table["episode_index"][row]) for row in selected)
        empty = sorted(set(wanted_ids) - {int(e) for e in episode_ids})
        if empty:
            raise DatasetError(f"episodes {empty} have no frames in the data files of {self.root}")
        for episode_index, start, length in zip(episode_ids, starts, lengths, strict=True):
            frame_index = data["frame_index"][start : start + length]
            if not np.array_equal(frame_index, np.arange(length)):
                raise DatasetError(
                    f"episode {episode_index} of {self.root} does not have frames 0..{length - 1} "
                    "in its data file; action chunks need consecutive frames"
                )
        n = len(data["episode_index"])
        return {
            "action": data[self.action_key],
            "proprio": data[self.state_key] if self.state_key else np.zeros((n, 0), np.float32),
            "timestamp": data["timestamp"].astype(np.float64),
            "task_index": data["task_index"].astype(np.int64),
            "episodes": [
                (int(e), int(s), int(length))
                for e, s, length in zip(episode_ids, starts, lengths, strict=True)
            ],
        }

    def _check_vectors(
        self,
        values: np.ndarray,
        column: str,
        path: Path,
        episode_index: np.ndarray,
        frame_index: np.ndarray,
    ) -> None:
        """``values`` (N, D) of one data file have the width info.json declares and are finite
        (one nan would make the loss and recomputed statistics nan), checked before training."""
        declared = self.info["features"][column].get("shape")
        if declared is not None and values.shape[1] != math.prod(declared):
            raise DatasetError(
                f"{path}: column {column!r} has {values.shape[1]} values per frame but "
                f"{self.root / INFO_PATH} declares shape {declared}; repair the data file or the "
                "feature's shape"
            )
        bad = ~np.isfinite(values)
        if bad.any():
            row, dim = (int(i) for i in np.argwhere(bad)[0])
            raise DatasetError(
                f"{path}: column {column!r} has {int(bad.sum())} non-finite value(s) in float32, "
                f"the first {values[row, dim]} in episode {episode_index[row]}, frame "
                f"{frame_index[row]}, dimension {dim}; fix the episode or leave it out "
                "(data.train_episodes)"
            )

    # -- statistics ---------------------------------------------------------------------------

    def _statistics(self) -> dict[str, Any]:
        stats_path = self.root / STATS_PATH
        converted = None
        if stats_path.is_file():
            converted = statistics_from_lerobot(
                json.loads(stats_path.read_text()),
                num_trajectories=int(self.info.get("total_episodes", 0)),
                action_key=self.action_key,
                state_key=self.state_key,
                normalization=self.normalization,
            )
        if converted is not None:
            check_finite_statistics(converted, str(stats_path))
            # Dataset-wide statistics even for an episode subset, as LeRobot normalises with them.
            dims = (len(converted["action"]["q01"]), len(converted["proprio"].get("q01", [])))
            if dims != (self.action_dim, self.proprio_dim):
                raise DatasetError(
                    f"{stats_path} describes (action, state) dims {dims} but the data has "
                    f"{(self.action_dim, self.proprio_dim)}"
                )
            return converted
        logger.warning(
            "%s has no q01/q99 for %s; computing statistics from the %d selected episodes",
            stats_path,
            [k for k in (self.action_key, self.state_key) if k],
            len(self.episodes),
        )
        rows = np.concatenate([np.arange(e.start, e.start + e.length) for e in self.episodes])
        return compute_statistics(
            self._actions[rows],
            self._proprio[rows],
            len(self.episodes),
            normalization=self.normalization,
        )

    # -- samples ------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._rows)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_videos"] = None  # decoders are per process, opened lazily in each worker
        return state

    def _video_files(self) -> _VideoFiles:
        # A forked DataLoader worker inherits the parent's containers; FFmpeg state must not be shared.
        if self._videos is None or self._videos.pid != os.getpid():
            self._videos = _VideoFiles()
        return self._videos

    def __getitem__(self, i: int) -> Sample:
        row = int(self._rows[i])
        episode = self.episodes[int(self._sample_episode[i])]
        videos = self._video_files()
        images = []
        for camera in self.cameras:
            path, from_timestamp = episode.videos[camera]
            # The episode's frames start at from_timestamp in the concatenated file
            # (LeRobot ``dataset_reader.py`` ``_query_videos`` / ``shift_timestamps``).
            time_s = from_timestamp + float(self._timestamps[row])
            try:
                frame = videos.frame(path, time_s, self.tolerance_s)
            except _FrameNotFound as e:
                raise DatasetError(
                    f"camera {camera!r}, episode {episode.index}, frame {row - episode.start}: {e}. "
                    "The frame timestamps or the episode's from_timestamp disagree with the video; "
                    "leave the episode out (episodes=...) or re-encode it"
                ) from e
            image = torch.from_numpy(frame).permute(2, 0, 1)
            images.append(self.transform(image)[0])
        actions = self._actions[row : row + self.chunk_size]
        return {
            "images": torch.stack(images),
            "proprio": torch.from_numpy(self.normalizer.normalize("proprio", self._proprio[row])),
            "actions": torch.from_numpy(self.normalizer.normalize("action", actions)),
            "instruction": self.tasks[int(self._task_index[row])],
            "index": i,
        }


def _vectors(column: pyarrow.ChunkedArray, path: Path, name: str) -> np.ndarray:
    """(N, D) float32 from a list / fixed-size-list column, or (N, 1) from a scalar column."""
    pa, _ = _pyarrow()
    array = column.combine_chunks()
    n = len(array)
    if (
        pa.types.is_list(array.type)
        or pa.types.is_large_list(array.type)
        or pa.types.is_fixed_size_list(array.type)
    ):
        values = array.flatten().to_numpy(zero_copy_only=False)
        if n == 0 or values.size % n:
            raise DatasetError(
                f"{path}: column {name!r} does not hold one equal-length vector per frame"
            )
        return values.reshape(n, -1).astype(np.float32)
    return array.to_numpy(zero_copy_only=False).astype(np.float32).reshape(n, 1)


class _FrameNotFound(Exception):
    pass


class _VideoFiles:
    """PyAV containers open in this process, the least recently used closed first.

    FFmpeg decodes and converts on one thread here (its default is a pool of one per core): a
    DataLoader worker forks with its parent's open containers, and freeing a decoder whose pool
    threads stayed in the parent, or starting a pool beside them, hung or crashed the worker (34
    of 100 loaders in a row). The workers are the parallelism.
    """

    def __init__(self, max_open: int = _MAX_OPEN_VIDEOS, threads: int = 1) -> None:
        """``threads``: FFmpeg's per decoder and conversion; 0 is its default pool (what
        ``benchmarks/bench_video_decode.py`` compares against)."""
        self.pid = os.getpid()
        self.max_open = max_open
        self.threads = threads
        self._open: OrderedDict[Path, av.container.InputContainer] = OrderedDict()
        # PyAV 17 converts on a pool unless told `threads`; earlier ones use one thread and
        # refuse the argument (LeRobot 0.4 pins av < 16).
        pooled = int(_av().__version__.split(".")[0]) >= 17
        self._to_rgb: dict[str, Any] = {"format": "rgb24"} | (
            {"threads": threads} if pooled else {}
        )

    def _container(self, path: Path) -> av.container.InputContainer:
        if path in self._open:
            self._open.move_to_end(path)
        else:
            container = _av().open(str(path))
            container.streams.video[0].codec_context.thread_count = self.threads
            self._open[path] = container
            if len(self._open) > self.max_open:
                self._open.popitem(last=False)[1].close()
        return self._open[path]

    def frame(self, path: Path, time_s: float, tolerance_s: float) -> np.ndarray:
        """(H, W, 3) uint8 RGB of the frame whose presentation time is within ``tolerance_s``.

        Seeks to the last keyframe at or before the query and decodes forward, since only keyframes
        decode on their own. Frame times are pts * time_base as stored, as LeRobot's decoders use them.
        """
        container = self._container(path)
        stream = container.streams.video[0]
        time_base = float(stream.time_base)
        seek_s = max(time_s - tolerance_s, 0.0)
        back = 1.0
        while True:
            container.seek(int(seek_s / time_base), stream=stream, backward=True, any_frame=False)
            decoded: list[float] = []
            for frame in container.decode(stream):
                if frame.pts is None:
                    continue
                t = frame.pts * time_base
                if abs(t - time_s) < tolerance_s:
                    return frame.to_ndarray(**self._to_rgb)
                decoded.append(t)
                if t > time_s:
                    break
            if decoded and decoded[0] > time_s and seek_s > 0:
                # The demuxer landed on a keyframe after the query (its index can be by decode
                # time): seek further back until decoding starts before it.
                seek_s, back = max(seek_s - back, 0.0), back * 2
                continue
            nearby = ", ".join(f"{t:.4f}" for t in decoded[-3:]) or "none"
            raise _FrameNotFound(
                f"{path} has no frame within {tolerance_s * 1e3:.1f} ms of t={time_s:.4f} s "
                f"(decoded frames up to there: {nearby})"
            )
