"""The robomimic/LIBERO HDF5 reader: chunks, normalisation, statistics, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import lightning as L
import numpy as np
import pytest
import torch
from torch import nn

from capvector.data import keys
from capvector.data.datamodule import RobotDataModule, noise_seeds
from capvector.data.hdf5 import DatasetError, HDF5RobotDataset
from capvector.data.statistics import Normalizer, compute_statistics
from capvector.data.transforms import ImageTransform
from conftest import CAMERAS, cpu_trainer, write_demo_file

PROPRIO = ["robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"]


def dataset(path: Path, **kwargs) -> HDF5RobotDataset:
    return HDF5RobotDataset([path], cameras=CAMERAS, proprio_keys=PROPRIO, chunk_size=8, **kwargs)


def test_chunks_never_cross_an_episode_end(demo_file: Path) -> None:
    ds = dataset(demo_file)
    assert len(ds) == (12 - 8 + 1) + (10 - 8 + 1)  # OFT: starts at t <= T - chunk
    with h5py.File(demo_file) as f:
        raw = f["data/demo_1/actions"][()]
    last = ds[len(ds) - 1]
    expected = ds.normalizer.normalize("action", raw[2:10])
    np.testing.assert_allclose(last[keys.ACTIONS].numpy(), expected, rtol=1e-6)
    assert last[keys.IMAGES].shape == (2, 3, 64, 64)
    assert last[keys.PROPRIO].shape == (8,)
    assert last[keys.INSTRUCTION] == "lift the red cube"


def test_q01_q99_normalisation_keeps_the_gripper_raw(demo_file: Path) -> None:
    ds = dataset(demo_file)
    stats = ds.statistics
    assert stats["action"]["mask"] == [True] * 6 + [False]
    norm = Normalizer(stats)
    q01, q99 = np.array(stats["action"]["q01"]), np.array(stats["action"]["q99"])
    np.testing.assert_allclose(norm.normalize("action", q01[None])[0, :6], -1, atol=1e-5)
    np.testing.assert_allclose(norm.normalize("action", q99[None])[0, :6], 1, atol=1e-5)
    beyond = norm.normalize("action", (q99 + 10)[None])[0]
    assert (beyond[:6] == 1).all()  # clipped
    assert beyond[6] == q99[6] + 10  # gripper passes through
    x = np.random.default_rng(0).uniform(q01, q99, size=(5, 7)).astype(np.float32)
    np.testing.assert_allclose(
        norm.unnormalize("action", norm.normalize("action", x)), x, rtol=1e-5, atol=1e-5
    )


def test_statistics_schema_matches_openvla_oft(demo_file: Path) -> None:
    dm = RobotDataModule(train_files=[str(demo_file)], dataset_name="lift_demo")
    spec = dm.spec
    entry = spec.statistics["lift_demo"]
    assert set(entry) == {"action", "proprio", "num_transitions", "num_trajectories"}
    assert set(entry["action"]) == {"mean", "std", "max", "min", "q01", "q99", "mask"}
    assert entry["num_transitions"] == 22 and entry["num_trajectories"] == 2
    assert (spec.action_dim, spec.proprio_dim, spec.chunk_size) == (7, 8, 8)
    json.dumps(spec.statistics)  # must serialise as dataset_statistics.json


def test_constant_dimensions_normalise_to_zero() -> None:
    actions = np.zeros((10, 7), np.float32)
    actions[:, 0] = np.linspace(-1, 1, 10)
    stats = compute_statistics(actions, np.zeros((10, 2), np.float32), 1)
    out = Normalizer(stats).normalize("action", actions)
    assert (out[:, 1:6] == 0).all()


def test_depth_and_annotations_are_optional_fields(demo_file: Path) -> None:
    sample = dataset(demo_file, load_depth=True, load_annotations=True)[0]
    assert sample[keys.DEPTH].shape == (2, 64, 64)
    assert sample[keys.INTRINSICS].shape == (2, 3, 3)
    assert sample[keys.ANNOTATION] == "step 0 of demo 0"


def test_noise_seeds_are_per_sample_and_change_with_epoch_and_seed() -> None:
    index = torch.arange(8)
    seeds = noise_seeds(index, epoch=0, seed=0)
    assert seeds.dtype == torch.int64 and len(set(seeds.tolist())) == 8
    torch.testing.assert_close(noise_seeds(index[4:], 0, 0), seeds[4:])  # not a batch property
    assert not (noise_seeds(index, 1, 0) == seeds).any()
    assert not (noise_seeds(index, 0, 1) == seeds).any()


class SeedRecorder(L.LightningModule):
    """Records what the datamodule's batches carry in training and validation."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.zeros(()))
        self.train_batches: list[tuple[int, dict]] = []
        self.val_batches: list[dict] = []

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        self.train_batches.append((self.current_epoch, batch))
        return self.w**2

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        self.val_batches.append(batch)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_training_batches_carry_their_noise_seeds(demo_file: Path, tmp_path: Path) -> None:
    """The flow-matching noise of a sample depends on (data.seed, epoch, dataset index) only."""
    assert dataset(demo_file)[3][keys.INDEX] == 3
    dm = RobotDataModule(
        train_files=[str(demo_file)], val_files=[str(demo_file)], batch_size=4, seed=7
    )
    module = SeedRecorder()
    trainer = cpu_trainer(4, tmp_path, limit_val_batches=1, num_sanity_val_steps=0)
    trainer.fit(module, dm)
    assert [epoch for epoch, _ in module.train_batches] == [0, 0, 1, 1]  # 8 samples, batch 4
    for epoch, batch in module.train_batches:
        expected = noise_seeds(batch[keys.INDEX], epoch, seed=7)
        torch.testing.assert_close(batch[keys.NOISE_SEED], expected)
    assert module.val_batches and all(keys.NOISE_SEED not in b for b in module.val_batches)


def test_augmentation_is_per_camera_and_eval_crop_is_deterministic() -> None:
    image = torch.randint(0, 255, (3, 64, 64), dtype=torch.uint8)
    train = ImageTransform(
        augment=True, center_crop=False, generator=torch.Generator().manual_seed(0)
    )
    a = train(image)[0]
    b = train(image)[0]
    assert a.shape == (3, 64, 64) and a.min() >= 0 and a.max() <= 1
    assert not torch.allclose(a, b)  # fresh randomness per call, so per camera
    evaluate = ImageTransform(augment=False, center_crop=True)
    torch.testing.assert_close(evaluate(image)[0], evaluate(image)[0])
    # The crop moves the principal point and scales the focal length with the resize.
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    _, _, cropped = evaluate(image, torch.ones(64, 64), K)
    scale = 64 / 61  # round(64 * sqrt(0.9)) = 61 pixels resized back to 64
    torch.testing.assert_close(cropped[0, 0], torch.tensor(50.0 * scale))
    torch.testing.assert_close(cropped[0, 2], torch.tensor((32.0 - 1) * scale))
    plain = ImageTransform(augment=False, center_crop=False)
    torch.testing.assert_close(plain(image)[0], image.float() / 255)


def test_missing_camera_names_what_the_file_has(demo_file: Path) -> None:
    with pytest.raises(
        DatasetError, match=r"lacks \['frontview_image'\].*agentview_image.*data.cameras"
    ):
        HDF5RobotDataset([demo_file], cameras=["frontview"], proprio_keys=PROPRIO, chunk_size=8)


def test_missing_actions_and_malformed_files(tmp_path: Path) -> None:
    broken = write_demo_file(tmp_path / "broken.hdf5")
    with h5py.File(broken, "a") as f:
        del f["data/demo_1/actions"]
    with pytest.raises(DatasetError, match=r"data/demo_1 has no `actions`"):
        dataset(broken)
    not_robomimic = tmp_path / "other.hdf5"
    with h5py.File(not_robomimic, "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(DatasetError, match="no `data` group"):
        dataset(not_robomimic)
    with pytest.raises(DatasetError, match="does not exist"):
        dataset(tmp_path / "missing.hdf5")


def test_missing_instruction_is_a_clear_error_unless_given(tmp_path: Path) -> None:
    path = write_demo_file(tmp_path / "noinstr.hdf5")
    with h5py.File(path, "a") as f:
        del f["data"].attrs["language_instruction"]
    with pytest.raises(DatasetError, match="no language instruction"):
        dataset(path)
    assert dataset(path, instruction="open the door")[0][keys.INSTRUCTION] == "open the door"


def test_libero_problem_info_instruction(tmp_path: Path) -> None:
    path = write_demo_file(tmp_path / "libero.hdf5")
    with h5py.File(path, "a") as f:
        del f["data"].attrs["language_instruction"]
        f["data"].attrs["problem_info"] = json.dumps(
            {"language_instruction": "put the bowl on the plate"}
        )
    assert dataset(path)[0][keys.INSTRUCTION] == "put the bowl on the plate"


def test_libero_layout_reads_its_image_keys_upright_and_problem_info(tmp_path: Path) -> None:
    """LIBERO's released files (scripts/create_dataset.py): `*_rgb` image keys as rendered
    (OpenGL convention), the instruction in `problem_info`, 8-d proprio from two keys."""
    path = tmp_path / "task_demo.hdf5"
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (6, 16, 16, 3), dtype=np.uint8)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps(
            {"problem_name": "p", "domain_name": "robosuite", "language_instruction": "put it"}
        )
        data.attrs["macros_image_convention"] = "opengl"
        demo = data.create_group("demo_0")
        demo.create_dataset("actions", data=rng.normal(size=(6, 7)))
        demo.create_dataset("obs/agentview_rgb", data=frames)
        demo.create_dataset("obs/eye_in_hand_rgb", data=frames[:, ::-1])
        demo.create_dataset("obs/ee_states", data=rng.normal(size=(6, 6)))
        demo.create_dataset("obs/gripper_states", data=rng.normal(size=(6, 2)))
    ds = HDF5RobotDataset(
        [path], cameras=["agentview", "robot0_eye_in_hand"],
        proprio_keys=["ee_states", "gripper_states"], chunk_size=2,
    )  # fmt: skip
    sample = ds[1]
    assert sample[keys.INSTRUCTION] == "put it" and sample[keys.PROPRIO].shape == (8,)
    # rotated 180 degrees, as the LIBERO evaluation rotates the live images
    expected = np.rot90(frames[1], 2).transpose(2, 0, 1) / 255.0
    np.testing.assert_allclose(sample[keys.IMAGES][0].numpy(), expected, atol=1e-6)
    robomimic = tmp_path / "robomimic.hdf5"  # files without the convention are read as stored
    with h5py.File(path, "r") as src, h5py.File(robomimic, "w") as dst:
        src.copy("data", dst)
        del dst["data"].attrs["macros_image_convention"]
    upright = HDF5RobotDataset(
        [robomimic], cameras=["agentview"], proprio_keys=["ee_states"], chunk_size=2
    )[1]
    np.testing.assert_allclose(
        upright[keys.IMAGES][0].numpy(), frames[1].transpose(2, 0, 1) / 255.0, atol=1e-6
    )


def test_a_folder_in_train_files_stands_for_its_hdf5_files(tmp_path: Path) -> None:
    """A LIBERO suite comes as a folder of per-task files: data.train_files takes the folder."""
    folder = tmp_path / "suite"
    folder.mkdir()
    for name in ("b_task_demo.hdf5", "a_task_demo.hdf5"):
        write_demo_file(folder / name)
    (folder / "notes.txt").write_text("not a demo file")
    # what `capvector demos` killed mid-file leaves (io.outputs.atomic_write_file's temporary)
    (folder / ".c_task_demo.hdf5.tmp-4242-x1y2.hdf5").write_bytes(b"half an HDF5 file")
    dm = RobotDataModule(train_files=[str(folder)], cameras=CAMERAS, proprio_keys=PROPRIO)
    assert dm.hparams.train_files == [
        str(folder / "a_task_demo.hdf5"),
        str(folder / "b_task_demo.hdf5"),
    ]
    dm.setup("fit")
    single = RobotDataModule(
        train_files=[str(folder / "a_task_demo.hdf5")], cameras=CAMERAS, proprio_keys=PROPRIO
    )
    single.setup("fit")
    assert len(dm.train_dataset) == 2 * len(single.train_dataset)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match=r"data.val_files: folder .*empty holds no \*.hdf5"):
        RobotDataModule(train_files=[str(folder)], val_files=[str(empty)])
