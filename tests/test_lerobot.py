"""The LeRobotDataset v3.0 reader on a small folder written here with pyarrow and PyAV (the layout of
LeRobot's v2.1 -> v3.0 converter), and on one recorded by lerobot 0.4.4's own writer."""

from __future__ import annotations

import json
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from capvector.cli import main
from capvector.data import keys
from capvector.data.hdf5 import DatasetError, HDF5RobotDataset
from capvector.data.lerobot import LeRobotV3Dataset, statistics_from_lerobot
from capvector.data.statistics import Normalizer, compute_statistics
from capvector.data.transforms import ImageTransform
from conftest import write_demo_file

RECORDED = Path(__file__).parent / "fixtures/lerobot_writer/lerobot_writer_tiny"
"""Written by lerobot 0.4.4's ``LeRobotDataset`` recorder; see PROVENANCE.md beside it."""
FPS = 10
SIZE = 32
CAMERAS = ("observation.images.image", "observation.images.wrist_image")
TASKS = ("put the bowl on the plate", "open the drawer")
EPISODE_TASKS = (0, 1, 0)
LENGTHS = (9, 6, 4)
# Episodes 0 and 1 share data file-000 and video file-000 (concatenated); episode 2 is in file-001.
FILE_OF_EPISODE = (0, 0, 1)
GOP = 4  # a keyframe every few frames, so most queries seek and then decode forward
# Lossy h264/mpeg4 on solid colours stays within this; neighbouring frames differ by 16/255.
COLOUR_TOLERANCE = 6 / 255


def colour(camera: int, episode: int, frame: int) -> tuple[int, int, int]:
    """A solid colour per frame: red codes the frame, green the camera, blue the episode."""
    return 16 + 16 * frame, 60 + 120 * camera, 40 + 80 * episode


def _encoder() -> str:
    import av

    for name in ("libx264", "mpeg4"):
        try:
            av.codec.Codec(name, "w")
            return name
        except Exception:
            continue
    pytest.skip("this PyAV build has neither a libx264 nor an mpeg4 encoder")


def _write_mp4(path: Path, frames: list[np.ndarray]) -> None:
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    codec = _encoder()
    options = {"g": str(GOP), "crf": "10"} if codec == "libx264" else {"g": str(GOP), "qscale": "2"}
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=FPS, options=options)
        stream.width, stream.height, stream.pix_fmt = SIZE, SIZE, "yuv420p"
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())


def _describe(x: np.ndarray) -> dict[str, list]:
    """LeRobot's stats.json entry for one feature (``compute_stats.py`` field names)."""
    x = x.astype(np.float64)
    stats = {
        "min": x.min(0),
        "max": x.max(0),
        "mean": x.mean(0),
        "std": x.std(0),
        "count": np.array([len(x)]),
    }
    for q in (1, 10, 50, 90, 99):
        stats[f"q{q:02d}"] = np.quantile(x, q / 100, axis=0)
    return {k: v.tolist() for k, v in stats.items()}


def write_lerobot_v3(root: Path, seed: int = 0) -> dict[str, np.ndarray]:
    """A LeRobot v3.0 folder with the files and names LeRobot writes; returns the raw frames."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(seed)
    total = sum(LENGTHS)
    actions = rng.uniform(-1, 1, (total, 7)).astype(np.float32)
    actions[:, -1] = np.sign(actions[:, -1])
    state = rng.normal(size=(total, 8)).astype(np.float32)
    episode_index = np.repeat(np.arange(len(LENGTHS)), LENGTHS)
    frame_index = np.concatenate([np.arange(n) for n in LENGTHS])
    timestamp = (frame_index / FPS).astype(np.float32)
    task_index = np.array([EPISODE_TASKS[e] for e in episode_index])

    def vectors(x: np.ndarray) -> pa.Array:
        return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])

    frames = pa.table(
        {
            "observation.state": vectors(state),
            "action": vectors(actions),
            "timestamp": pa.array(timestamp, pa.float32()),
            "frame_index": pa.array(frame_index, pa.int64()),
            "episode_index": pa.array(episode_index, pa.int64()),
            "index": pa.array(np.arange(total), pa.int64()),
            "task_index": pa.array(task_index, pa.int64()),
        }
    )
    for file_index in sorted(set(FILE_OF_EPISODE)):
        rows = np.isin(episode_index, [e for e, f in enumerate(FILE_OF_EPISODE) if f == file_index])
        path = root / f"data/chunk-000/file-{file_index:03d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(frames.filter(pa.array(rows)), path)

    episodes: dict[str, list] = {
        "episode_index": [],
        "tasks": [],
        "length": [],
        "data/chunk_index": [],
        "data/file_index": [],
        "dataset_from_index": [],
        "dataset_to_index": [],
    }
    starts = np.concatenate([[0], np.cumsum(LENGTHS)])
    for camera_id, camera in enumerate(CAMERAS):
        offset = dict.fromkeys(set(FILE_OF_EPISODE), 0.0)
        video_frames: dict[int, list[np.ndarray]] = {f: [] for f in set(FILE_OF_EPISODE)}
        for e, length in enumerate(LENGTHS):
            f = FILE_OF_EPISODE[e]
            for name, value in (
                ("chunk_index", 0),
                ("file_index", f),
                ("from_timestamp", offset[f]),
                ("to_timestamp", offset[f] + length / FPS),
            ):
                episodes.setdefault(f"videos/{camera}/{name}", []).append(value)
            offset[f] += length / FPS
            video_frames[f] += [
                np.full((SIZE, SIZE, 3), colour(camera_id, e, t), np.uint8) for t in range(length)
            ]
        for f, images in video_frames.items():
            _write_mp4(root / f"videos/{camera}/chunk-000/file-{f:03d}.mp4", images)
    for e, length in enumerate(LENGTHS):
        episodes["episode_index"].append(e)
        episodes["tasks"].append([TASKS[EPISODE_TASKS[e]]])
        episodes["length"].append(length)
        episodes["data/chunk_index"].append(0)
        episodes["data/file_index"].append(FILE_OF_EPISODE[e])
        episodes["dataset_from_index"].append(int(starts[e]))
        episodes["dataset_to_index"].append(int(starts[e + 1]))
        episodes.setdefault("meta/episodes/chunk_index", []).append(0)
        episodes.setdefault("meta/episodes/file_index", []).append(0)
        rows = slice(starts[e], starts[e + 1])
        for stat, value in _describe(actions[rows]).items():
            episodes.setdefault(f"stats/action/{stat}", []).append(value)
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    pq.write_table(pa.table(episodes), root / "meta/episodes/chunk-000/file-000.parquet")
    # LeRobot writes a pandas frame indexed by task; the named index is stored as column "task".
    pq.write_table(
        pa.table({"task_index": pa.array(range(len(TASKS)), pa.int64()), "task": list(TASKS)}),
        root / "meta/tasks.parquet",
    )

    video_feature = {
        "dtype": "video",
        "shape": [SIZE, SIZE, 3],
        "names": ["height", "width", "channels"],
        "info": {
            "video.height": SIZE,
            "video.width": SIZE,
            "video.codec": _encoder(),
            "video.pix_fmt": "yuv420p",
            "video.is_depth_map": False,
            "video.fps": FPS,
            "video.channels": 3,
            "has_audio": False,
        },
    }
    scalar = {"shape": [1], "names": None}
    info = {
        "codebase_version": "v3.0",
        "robot_type": "panda",
        "total_episodes": len(LENGTHS),
        "total_frames": total,
        "total_tasks": len(TASKS),
        "chunks_size": 1000,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200,
        "fps": FPS,
        "splits": {"train": f"0:{len(LENGTHS)}"},
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "features": {
            **{camera: video_feature for camera in CAMERAS},
            "observation.state": {
                "dtype": "float32",
                "shape": [8],
                "names": {"motors": [f"s{i}" for i in range(8)]},
            },
            "action": {
                "dtype": "float32",
                "shape": [7],
                "names": {"motors": [f"a{i}" for i in range(7)]},
            },
            "timestamp": {"dtype": "float32", **scalar},
            "frame_index": {"dtype": "int64", **scalar},
            "episode_index": {"dtype": "int64", **scalar},
            "index": {"dtype": "int64", **scalar},
            "task_index": {"dtype": "int64", **scalar},
        },
    }
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    image_stats = {k: np.full((3, 1, 1), 0.5).tolist() for k in ("min", "max", "mean", "std")}
    stats = {"observation.state": _describe(state), "action": _describe(actions)}
    stats.update({camera: {**image_stats, "count": [total]} for camera in CAMERAS})
    (root / "meta/stats.json").write_text(json.dumps(stats, indent=4))
    return {
        "action": actions,
        "state": state,
        "episode_index": episode_index,
        "frame_index": frame_index,
    }


@pytest.fixture(scope="module")
def v3_folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    root = tmp_path_factory.mktemp("lerobot") / "libero_tiny"
    return root, write_lerobot_v3(root)


@pytest.fixture
def v3_copy(v3_folder: tuple[Path, dict], tmp_path: Path) -> Path:
    """A copy that a test may break."""
    import shutil

    return Path(shutil.copytree(v3_folder[0], tmp_path / "copy"))


def dataset(root: Path, chunk_size: int = 3, **kwargs) -> LeRobotV3Dataset:
    return LeRobotV3Dataset(root, cameras=list(CAMERAS), chunk_size=chunk_size, **kwargs)


def expected_episode_frames(ds: LeRobotV3Dataset) -> list[tuple[int, int]]:
    """(episode_index, frame_index) of every sample, in sample order."""
    return [(e.index, t) for e in ds.episodes for t in range(e.length - ds.chunk_size + 1)]


def test_frames_decode_at_their_timestamp(v3_folder: tuple[Path, dict]) -> None:
    ds = dataset(v3_folder[0])
    where = expected_episode_frames(ds)
    assert len(ds) == len(where) == sum(n - 3 + 1 for n in LENGTHS)
    for i in reversed(range(len(ds))):  # backwards: every query seeks
        episode, frame = where[i]
        images = ds[i][keys.IMAGES]
        assert images.shape == (2, 3, SIZE, SIZE) and images.dtype == torch.float32
        for camera in range(2):
            mean = images[camera].mean(dim=(1, 2))
            expected = torch.tensor(colour(camera, episode, frame), dtype=torch.float32) / 255
            assert torch.allclose(mean, expected, atol=COLOUR_TOLERANCE), (i, camera, mean * 255)


def test_chunks_never_cross_an_episode_end(v3_folder: tuple[Path, dict]) -> None:
    root, raw = v3_folder
    ds = dataset(root, chunk_size=5)  # episode 2 (4 frames) is too short for one chunk
    assert [e.index for e in ds.episodes] == [0, 1]
    assert len(ds) == (9 - 5 + 1) + (6 - 5 + 1)
    for i, (episode, frame) in enumerate(expected_episode_frames(ds)):
        rows = np.flatnonzero(raw["episode_index"] == episode)[frame : frame + 5]
        assert len(rows) == 5 and (raw["episode_index"][rows] == episode).all()
        sample = ds[i]
        expected = ds.normalizer.normalize("action", raw["action"][rows])
        np.testing.assert_allclose(sample[keys.ACTIONS].numpy(), expected, rtol=1e-6)
        state = ds.normalizer.normalize("proprio", raw["state"][rows[0]])
        np.testing.assert_allclose(sample[keys.PROPRIO].numpy(), state, rtol=1e-6)


def test_sample_matches_the_hdf5_reader_format(
    v3_folder: tuple[Path, dict], tmp_path: Path
) -> None:
    hdf5 = HDF5RobotDataset(
        [write_demo_file(tmp_path / "demos.hdf5", image_size=SIZE)],
        cameras=["agentview", "robot0_eye_in_hand"],
        proprio_keys=["robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"],
        chunk_size=3,
    )[0]
    ds = dataset(v3_folder[0])
    sample = ds[0]
    assert set(sample) == set(hdf5)
    for key in (keys.IMAGES, keys.PROPRIO, keys.ACTIONS):
        assert sample[key].shape == hdf5[key].shape and sample[key].dtype == hdf5[key].dtype
    assert isinstance(sample[keys.INSTRUCTION], str)
    assert (ds.action_dim, ds.proprio_dim) == (7, 8)
    assert sample[keys.IMAGES].min() >= 0 and sample[keys.IMAGES].max() <= 1


def test_state_is_optional_and_the_transform_applies(v3_folder: tuple[Path, dict]) -> None:
    plain = dataset(v3_folder[0], state_key=None)
    assert plain.proprio_dim == 0 and plain.statistics["proprio"] == {}
    assert plain[0][keys.PROPRIO].shape == (0,)
    jitter = ImageTransform(
        augment=True, center_crop=False, generator=torch.Generator().manual_seed(0)
    )
    augmented = dataset(v3_folder[0], state_key=None, transform=jitter)
    assert not torch.allclose(augmented[0][keys.IMAGES], plain[0][keys.IMAGES], atol=0.02)


def test_statistics_are_converted_from_stats_json(v3_copy: Path) -> None:
    stats = json.loads((v3_copy / "meta/stats.json").read_text())
    # Shift the file's quantiles so that values recomputed from the data could not match them.
    for key in ("action", "observation.state"):
        stats[key]["q01"] = [v - 0.25 for v in stats[key]["q01"]]
        stats[key]["q99"] = [v + 0.25 for v in stats[key]["q99"]]
    (v3_copy / "meta/stats.json").write_text(json.dumps(stats))
    ds = dataset(v3_copy)
    entry = ds.statistics
    assert set(entry) == {"action", "proprio", "num_transitions", "num_trajectories"}
    assert set(entry["action"]) == {"mean", "std", "max", "min", "q01", "q99", "mask"}
    assert set(entry["proprio"]) == {"mean", "std", "max", "min", "q01", "q99"}
    for ours, theirs in (("action", "action"), ("proprio", "observation.state")):
        for field in ("mean", "std", "max", "min", "q01", "q99"):
            np.testing.assert_allclose(entry[ours][field], stats[theirs][field])
    assert entry["action"]["mask"] == [True] * 6 + [False]  # the gripper stays raw
    assert (entry["num_transitions"], entry["num_trajectories"]) == (sum(LENGTHS), len(LENGTHS))
    json.dumps(entry)  # a dataset_statistics.json entry
    assert statistics_from_lerobot(stats, num_trajectories=3, state_key=None)["proprio"] == {}


def test_statistics_are_recomputed_without_quantiles(
    v3_folder: tuple[Path, dict], v3_copy: Path
) -> None:
    stats = json.loads((v3_copy / "meta/stats.json").read_text())
    for feature in stats.values():
        for q in ("q01", "q10", "q50", "q90", "q99"):
            feature.pop(q, None)
    (v3_copy / "meta/stats.json").write_text(json.dumps(stats))
    assert statistics_from_lerobot(stats, num_trajectories=3) is None
    ds = dataset(v3_copy, chunk_size=5)  # over the episodes that make samples, as the HDF5 reader
    raw = v3_folder[1]
    rows = np.isin(raw["episode_index"], [0, 1])
    expected = compute_statistics(raw["action"][rows], raw["state"][rows], 2)
    for kind in ("action", "proprio"):
        for field in ("q01", "q99", "mean", "min", "max"):
            np.testing.assert_allclose(ds.statistics[kind][field], expected[kind][field], rtol=1e-6)
    assert ds.statistics["num_trajectories"] == 2


def test_given_statistics_are_used_as_is(v3_folder: tuple[Path, dict]) -> None:
    train = dataset(v3_folder[0], episodes=[0, 1])
    val = dataset(v3_folder[0], episodes=[2], statistics=train.statistics)
    assert val.statistics is train.statistics
    assert [e.index for e in val.episodes] == [2]
    raw = v3_folder[1]["action"][np.flatnonzero(v3_folder[1]["episode_index"] == 2)[:3]]
    expected = Normalizer(train.statistics).normalize("action", raw)
    np.testing.assert_allclose(val[0][keys.ACTIONS].numpy(), expected, rtol=1e-6)


def test_instruction_is_the_frames_task(v3_folder: tuple[Path, dict]) -> None:
    ds = dataset(v3_folder[0])
    for i, (episode, _) in enumerate(expected_episode_frames(ds)):
        assert ds[i][keys.INSTRUCTION] == TASKS[EPISODE_TASKS[episode]]


def test_dataloader_workers_decode_with_their_own_containers(v3_folder: tuple[Path, dict]) -> None:
    """A worker forks with its parent's open containers and decodes on its own. With FFmpeg's
    default thread pools a third of such workers hung or crashed: twenty in a row, each given a
    minute, catch that nearly always."""
    ds = dataset(v3_folder[0])
    first = ds[0]  # opens containers in this process before the worker forks
    clone = pickle.loads(pickle.dumps(ds))
    assert clone._videos is None
    for _ in range(20):
        batch = next(iter(DataLoader(ds, batch_size=4, num_workers=1, timeout=60)))
        assert batch[keys.IMAGES].shape == (4, 2, 3, SIZE, SIZE)
        torch.testing.assert_close(batch[keys.IMAGES][0], first[keys.IMAGES])
        assert batch[keys.INSTRUCTION][0] == first[keys.INSTRUCTION]


def test_missing_meta_files_are_named(v3_copy: Path) -> None:
    (v3_copy / "meta/tasks.parquet").unlink()
    with pytest.raises(DatasetError, match="meta/tasks.parquet is missing"):
        dataset(v3_copy)
    (v3_copy / "meta/info.json").unlink()
    with pytest.raises(DatasetError, match="meta/info.json is missing"):
        dataset(v3_copy)
    with pytest.raises(DatasetError, match="does not exist"):
        dataset(v3_copy / "nowhere")


def test_v2_folders_are_sent_to_the_converter(v3_copy: Path) -> None:
    info = json.loads((v3_copy / "meta/info.json").read_text())
    info["codebase_version"] = "v2.1"
    (v3_copy / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError, match="v2 folders must be converted with LeRobot's converter"):
        dataset(v3_copy)


def test_unknown_keys_and_episodes_list_what_exists(v3_folder: tuple[Path, dict]) -> None:
    root = v3_folder[0]
    with pytest.raises(
        DatasetError, match=r"'observation.images.top'.*observation.images.wrist_image"
    ):
        LeRobotV3Dataset(root, cameras=["observation.images.top"], chunk_size=3)
    with pytest.raises(DatasetError, match=r"'observation.joints'.*observation.state"):
        LeRobotV3Dataset(root, cameras=list(CAMERAS), state_key="observation.joints", chunk_size=3)
    with pytest.raises(DatasetError, match=r"episodes \[7\]"):
        dataset(root, episodes=[0, 7])
    with pytest.raises(DatasetError, match="at least chunk_size=20"):
        dataset(root, chunk_size=20)


def test_image_cameras_are_refused_clearly(v3_copy: Path) -> None:
    info = json.loads((v3_copy / "meta/info.json").read_text())
    info["features"][CAMERAS[0]]["dtype"] = "image"
    (v3_copy / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError, match="only video cameras"):
        dataset(v3_copy)


def test_a_frame_missing_from_the_video_is_an_error(v3_copy: Path) -> None:
    import pyarrow.parquet as pq

    path = v3_copy / "meta/episodes/chunk-000/file-000.parquet"
    table = pq.read_table(path)
    column = f"videos/{CAMERAS[1]}/from_timestamp"
    shifted = [v + 5.0 for v in table.column(column).to_pylist()]  # past the end of the file
    pq.write_table(table.set_column(table.column_names.index(column), column, [shifted]), path)
    ds = dataset(v3_copy)
    with pytest.raises(
        DatasetError,
        match=r"camera 'observation.images.wrist_image', episode 0.*no frame within 50.0 ms",
    ):
        ds[0]


def test_missing_extra_names_the_install_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A None entry in sys.modules is what `import pyarrow` sees when the package is absent.
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(
        ImportError,
        match=r"^reading LeRobot datasets needs the lerobot extra: pip install 'capvector\[lerobot\]'",
    ):
        dataset(tmp_path)  # raised before the folder is looked at


def test_a_dataset_recorded_by_lerobot_reads(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    # The case this fixture exists for: the recorder leaves the task index unnamed.
    tasks = pq.read_table(RECORDED / "meta/tasks.parquet")
    assert tasks.column_names == ["task_index", "__index_level_0__"]
    frames = pq.read_table(RECORDED / "data/chunk-000/file-000.parquet").to_pydict()
    states = {
        (e, t): np.array(x, np.float32)
        for e, t, x in zip(
            frames["episode_index"], frames["frame_index"], frames["observation.state"], strict=True
        )
    }
    ds = dataset(RECORDED)
    assert ds.tasks == dict(enumerate(TASKS))
    assert [(e.index, e.length) for e in ds.episodes] == list(enumerate(LENGTHS))
    assert (ds.action_dim, ds.proprio_dim) == (7, 8)
    where = expected_episode_frames(ds)
    assert len(ds) == len(where)
    for i in reversed(range(len(ds))):  # backwards: every query seeks
        episode, frame = where[i]
        sample = ds[i]
        assert sample[keys.INSTRUCTION] == TASKS[EPISODE_TASKS[episode]]
        # The writer's state starts with (episode, frame): the frame row matches the video frame.
        raw = states[(episode, frame)]
        assert tuple(raw[:2]) == (episode, frame)
        state = ds.normalizer.normalize("proprio", raw)
        np.testing.assert_allclose(sample[keys.PROPRIO].numpy(), state, rtol=1e-6)
        for camera in range(2):  # lerobot's default AV1 encoding, CRF 30
            mean = sample[keys.IMAGES][camera].mean(dim=(1, 2))
            expected = torch.tensor(colour(camera, episode, frame), dtype=torch.float32) / 255
            assert torch.allclose(mean, expected, atol=COLOUR_TOLERANCE), (i, camera, mean * 255)
    batch = next(iter(DataLoader(ds, batch_size=4)))
    assert batch[keys.IMAGES].shape == (4, 2, 3, 64, 64)


def test_a_dataset_recorded_by_lerobot_trains(tmp_path: Path) -> None:
    out = tmp_path / "runs"
    assert main([
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=2",
        "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={out}",
        "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={out}", "--trainer.logger.init_args.name=fit",
        "--model.backbone=openvla-oft-tiny", f"--data.lerobot_root={RECORDED}",
        f"--data.cameras=[{','.join(CAMERAS)}]", "--data.proprio_keys=[observation.state]",
        "--data.chunk_size=3", "--data.batch_size=4",
    ]) == 0  # fmt: skip
    (checkpoint,) = (out / "fit/version_0/checkpoints").glob("*.ckpt")
    assert torch.load(checkpoint, weights_only=False)["global_step"] == 2


def test_a_tasks_file_without_task_strings_is_named(v3_copy: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = v3_copy / "meta/tasks.parquet"
    pq.write_table(pa.table({"task_index": [0, 1], "name": list(TASKS)}), path)
    with pytest.raises(DatasetError, match=r"tasks\.parquet has columns \['task_index', 'name'\]"):
        dataset(v3_copy)
