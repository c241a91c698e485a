"""The Lightning datamodule over robot demonstration files."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from capvector.data.batch import Batch
from capvector.data.episodes import (
    EpisodeDataset,
    EpisodeItem,
    EpisodeSampler,
    EvalTask,
    eval_task,
    is_episode_batch,
)
from capvector.data.hdf5 import DEFAULT_CACHE_MB, DatasetError, HDF5RobotDataset
from capvector.data.lerobot import LeRobotV3Dataset
from capvector.data.resumable import ResumableLoader, ResumableSampler
from capvector.data.spec import DataSpec
from capvector.data.statistics import BOUNDS_Q99, check_normalization
from capvector.data.transforms import ImageTransform
from capvector.envs.base import DemoSettings
from capvector.envs.registry import suite_for_task_set
from capvector.errors import require_extra

DEFAULT_CAMERAS = ("agentview", "robot0_eye_in_hand")
DEFAULT_PROPRIO = ("robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos")


@dataclasses.dataclass
class DemoGeneration:
    """``data.generate``: record the demos the config names when a file does not exist yet, as
    ``capvector demos --task`` would (cameras, depth and annotations follow the data config), with
    the scripted expert of the task's suite (``Suite.record_demos``)."""

    task: str = "Lift"
    robot: str | None = "Panda"
    gripper: str | None = None
    episodes: int = 20
    seed: int = 0
    """Seed of the first attempt; the i-th missing file of train_files + val_files starts at
    seed + 10,000·i, so no two files share an episode."""
    image_size: int = 64


def demo_files(paths: Sequence[str] | None, option: str) -> list[str] | None:
    """``paths`` with each existing folder replaced by its ``*.hdf5`` files, sorted, hidden ones
    left out (``.NAME.tmp-PID-*.hdf5``: what a writer killed mid-file leaves behind); other
    entries (files, or files ``data.generate`` will record) as given."""
    if paths is None:
        return None
    files: list[str] = []
    for path in paths:
        if not Path(path).is_dir():
            files.append(str(path))
            continue
        found = sorted(str(f) for f in Path(path).glob("*.hdf5") if not f.name.startswith("."))
        if not found:
            raise DatasetError(f"{option}: folder {path} holds no *.hdf5 files")
        files.extend(found)
    return files


class RobotDataModule(L.LightningDataModule):
    """Training samples from HDF5 demos or a LeRobot v3 folder; optional held-out demos (files, or
    episodes of the folder) for an action-L1 validation. With ``eval_tasks`` alone it only
    validates, by rollouts (no training data, no ``spec``: the model keeps its own)."""

    def __init__(
        self,
        train_files: list[str] | None = None,
        val_files: list[str] | None = None,
        eval_tasks: list[dict[str, Any]] | list[EvalTask] | None = None,
        cameras: Sequence[str] = DEFAULT_CAMERAS,
        proprio_keys: Sequence[str] = DEFAULT_PROPRIO,
        chunk_size: int = 8,
        batch_size: int = 8,
        num_workers: int = 0,
        augment: bool = True,
        instruction: str | None = None,
        dataset_name: str = "capvector",
        load_depth: bool = False,
        load_annotations: bool = False,
        seed: int = 0,
        shuffle: bool = True,
        lerobot_root: str | None = None,
        train_episodes: list[int] | None = None,
        val_episodes: list[int] | None = None,
        normalization: str | None = None,
        generate: DemoGeneration | None = None,
        cache_mb: float = DEFAULT_CACHE_MB,
    ) -> None:
        """
        Args:
            train_files: HDF5 files in the robomimic/LIBERO layout; a folder stands for every
                ``*.hdf5`` in it but hidden ones (a LIBERO suite's released datasets: one file
                per task).
            val_files: held-out files (or folders); validation then reports the action L1 on them.
            eval_tasks: rollout episodes for the validation loop (success rates), each a task
                set of a registered suite under its protocol (``capvector.data.episodes.EvalTask``):
                ``{task: Lift, episodes: 20, options: {robot: Sawyer}}``, or flat as before,
                ``{task: Lift, robot: Sawyer}``, ``{suite: libero_spatial, tasks: [0, 1], trials: 5}``.
            cameras: camera names (``obs/<camera>_image``), in the order the model sees them.
            proprio_keys: ``obs`` keys concatenated into the proprio vector.
            chunk_size: actions per sample (the model's chunk size follows it).
            augment: OFT's random crop + colour jitter at training time.
            instruction: used when a file carries no language instruction.
            dataset_name: the key of the statistics in ``dataset_statistics.json``.
            load_depth: also load ``obs/<camera>_depth`` (geometric teachers need it).
            load_annotations: also load per-step text (the reasoning objective needs it).
            seed: the shuffling seed, also mixed into the flow-matching training noise
                (``batch["noise_seed"]``).
            shuffle: shuffle training samples (off gives the same global batches on any number of
                devices, which parity tests use).
            lerobot_root: a LeRobotDataset v3.0 folder, read instead of ``train_files``. Then
                ``cameras`` are video feature keys (``observation.images.image``),
                ``proprio_keys`` is ``[<state feature>]`` or ``[]``, the instruction is the task.
            train_episodes: LeRobot ``episode_index`` values to train on (None: all).
            val_episodes: LeRobot episodes for validation; leave them out of ``train_episodes``.
            normalization: how states and actions are normalised, a per-family choice that follows
                the family's upstream: ``bounds_q99`` (OpenVLA-OFT: clipped to [-1, 1], gripper
                raw), ``bounds`` (OpenVLA-OFT's ALOHA recipe: the same with min/max) or
                ``quantiles`` (Pi0.5 as openpi and LeRobot: not clipped, every dimension).
                See ``capvector.data.statistics``. Unset, ``capvector fit`` sets the model's
                backbone family's (``normalization`` in its ``configuration.py``); a data module
                built alone takes ``bounds_q99``.
            generate: record missing HDF5 files with the robosuite experts (``prepare_data``, once
                per node, with a progress bar) instead of stopping; ``configs/debug.yaml`` turns it
                on so a fresh checkout trains.
            cache_mb: memory (MiB) for HDF5 demo frames kept after their first read, shared out
                among the ``num_workers`` workers (each keeps its own); episodes beyond it are read
                frame by frame from the files. 0 reads every frame from the files.
        """
        normalization = normalization or BOUNDS_Q99
        check_normalization(normalization)
        super().__init__()
        self.save_hyperparameters()
        self.hparams["normalization"] = normalization
        self.hparams["train_files"] = demo_files(train_files, "data.train_files")
        self.hparams["val_files"] = demo_files(val_files, "data.val_files")
        self.eval_tasks = [eval_task(t) for t in eval_tasks or []]
        if self.eval_tasks:  # rollouts need the simulator: say so before the run starts
            require_extra("rollout validation (data.eval_tasks)", "sim", "mujoco", "robosuite")
        # Plain data in checkpoints, so they load with torch.load(weights_only=True).
        self.hparams["eval_tasks"] = [dataclasses.asdict(t) for t in self.eval_tasks] or None
        self.generate = DemoGeneration(**generate) if isinstance(generate, Mapping) else generate
        self.hparams["generate"] = dataclasses.asdict(self.generate) if self.generate else None
        self.train_dataset: HDF5RobotDataset | LeRobotV3Dataset | None = None
        self.val_dataset: HDF5RobotDataset | LeRobotV3Dataset | None = None
        if lerobot_root is not None and train_files:
            raise DatasetError(
                "set one of data.train_files (HDF5 files) and data.lerobot_root (a LeRobot v3 "
                "folder), not both"
            )
        if not self.has_training_data and (val_files or not eval_tasks):
            raise DatasetError(
                "set data.train_files (HDF5 files) or data.lerobot_root (a LeRobot v3 folder); "
                "only rollouts (data.eval_tasks) validate without training data, whose "
                "statistics held-out files would need"
            )
        if lerobot_root is not None:
            if (
                len(proprio_keys) > 1
                or load_depth
                or load_annotations
                or instruction
                or val_files
                or generate
            ):
                raise DatasetError(
                    "with data.lerobot_root, proprio_keys is one state feature (e.g. "
                    "['observation.state']) or [], validation uses data.val_episodes, and "
                    "instruction, load_depth, load_annotations, val_files and generate are not "
                    "available"
                )
            self._load_datasets()
            return
        missing = self._missing_files()
        if missing and self.generate is None:
            raise DatasetError(
                f"dataset file(s) not found: {missing}. Generate demos with "
                "`capvector demos --task Lift --episodes 20 --out FILE`, set data.generate to "
                "record them at the start of fit, or fix data.train_files"
            )
        if not missing:
            self._load_datasets()

    @property
    def has_training_data(self) -> bool:
        return bool(self.hparams.train_files) or self.hparams.lerobot_root is not None

    def _missing_files(self) -> list[str]:
        files = [*(self.hparams.train_files or []), *(self.hparams.val_files or [])]
        return [f for f in files if not Path(f).is_file()]

    def prepare_data(self) -> None:
        """Record the missing demo files (``data.generate``). Lightning calls it once per node."""
        if self.generate is None:
            return
        hp, gen = self.hparams, self.generate
        suite = suite_for_task_set(gen.task)  # its simulator loads only when recording
        own = {k: v for k, v in {"robot": gen.robot, "gripper": gen.gripper}.items() if v}
        files = [*(hp.train_files or []), *(hp.val_files or [])]
        for i, file in enumerate(files):
            if Path(file).is_file():
                continue
            try:
                settings = DemoSettings(
                    tuple(hp.cameras), gen.image_size, hp.load_depth, gen.seed + 10_000 * i
                )
                suite.record_demos(gen.task, gen.episodes, file, settings, **own)
            except (RuntimeError, ValueError, KeyError) as exc:  # as `capvector demos` reports them
                raise DatasetError(f"data.generate could not record {file}: {exc}") from exc

    def setup(self, stage: str) -> None:
        self._load_datasets()

    def _load_datasets(self) -> None:
        if self.train_dataset is not None or not self.has_training_data:
            return
        if self._missing_files():  # first needed before the trainer ran prepare_data (CLI links)
            self.prepare_data()
        hp = self.hparams
        self.train_dataset = self._dataset(
            hp.train_files, augment=hp.augment, episodes=hp.train_episodes
        )
        held_out = hp.val_episodes if hp.lerobot_root is not None else hp.val_files
        if held_out:
            self.val_dataset = self._dataset(hp.val_files, augment=False, episodes=hp.val_episodes)

    def _dataset(
        self, files: list[str] | None, augment: bool, episodes: list[int] | None = None
    ) -> HDF5RobotDataset | LeRobotV3Dataset:
        hp = self.hparams
        statistics = None
        if getattr(self, "train_dataset", None) is not None:
            statistics = self.train_dataset.statistics  # validation uses the training statistics
        transform = ImageTransform(augment=augment, center_crop=hp.augment and not augment)
        if hp.lerobot_root is not None:
            return LeRobotV3Dataset(
                hp.lerobot_root,
                cameras=list(hp.cameras),
                state_key=hp.proprio_keys[0] if hp.proprio_keys else None,
                chunk_size=hp.chunk_size,
                statistics=statistics,
                transform=transform,
                episodes=episodes,
                normalization=hp.normalization,
            )
        return HDF5RobotDataset(
            files,
            cameras=list(hp.cameras),
            proprio_keys=list(hp.proprio_keys),
            chunk_size=hp.chunk_size,
            statistics=statistics,
            transform=transform,
            instruction=hp.instruction,
            load_depth=hp.load_depth,
            load_annotations=hp.load_annotations,
            normalization=hp.normalization,
            cache_mb=hp.cache_mb / max(1, hp.num_workers),
        )

    @property
    def spec(self) -> DataSpec | None:
        """What the model needs to know about this data; None without training data."""
        self._load_datasets()
        ds = self.train_dataset
        if ds is None:
            return None
        return DataSpec(
            cameras=list(self.hparams.cameras),
            proprio_keys=list(self.hparams.proprio_keys),
            proprio_dim=ds.proprio_dim,
            action_dim=ds.action_dim,
            chunk_size=self.hparams.chunk_size,
            dataset_name=self.hparams.dataset_name,
            statistics={self.hparams.dataset_name: ds.statistics},
            center_crop=self.hparams.augment,
            image_size=getattr(ds, "image_size", 64),
            camera_fovy=getattr(ds, "camera_fovy", None),
        )

    def train_dataloader(self) -> DataLoader:
        hp = self.hparams
        self._load_datasets()
        dataset = self.train_dataset
        if dataset is None:
            raise DatasetError("training needs data.train_files or data.lerobot_root")
        drop_last = len(dataset) >= hp.batch_size
        trainer = self.trainer
        world, rank = (trainer.world_size, trainer.global_rank) if trainer is not None else (1, 0)
        # Our own sampler on any number of processes: Lightning's replacement always shuffles
        # training data (`shuffle=false` would mean nothing on several devices), and ours resumes.
        sampler = ResumableSampler(
            dataset, num_replicas=world, rank=rank, shuffle=hp.shuffle, seed=hp.seed,
            drop_last=drop_last,
        )  # fmt: skip
        return ResumableLoader(
            dataset, sampler, batch_size=hp.batch_size, num_workers=hp.num_workers,
            persistent_workers=hp.num_workers > 0, drop_last=drop_last,
            generator=torch.Generator().manual_seed(hp.seed),  # the workers' seeds
        )  # fmt: skip

    def on_before_batch_transfer(
        self, batch: Batch | list[EpisodeItem], dataloader_idx: int
    ) -> Batch | list[EpisodeItem]:
        """While training, give each sample its noise seed (``batch["noise_seed"]``)."""
        trainer = self.trainer
        training = trainer is not None and trainer.training
        if training and isinstance(batch, dict) and "index" in batch:
            batch["noise_seed"] = noise_seeds(
                batch["index"], trainer.current_epoch, self.hparams.seed
            )
        return batch

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        if is_episode_batch(batch):
            return batch  # episode specs: the policy moves its own inputs
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    def val_dataloader(self) -> DataLoader | list[DataLoader]:
        """Rollout episodes (``eval_tasks``) and/or held-out demos (``val_files``)."""
        loaders = []
        if self.eval_tasks:
            episodes = EpisodeDataset(self.eval_tasks)
            trainer = self.trainer
            world, rank = (
                (trainer.world_size, trainer.global_rank) if trainer is not None else (1, 0)
            )
            sampler = EpisodeSampler(episodes, num_replicas=world, rank=rank)
            # One batch per rank: the module runs its episodes at once (batched evaluation).
            loaders.append(
                DataLoader(episodes, batch_size=len(sampler), sampler=sampler, collate_fn=list)
            )
        if self.val_dataset is not None:
            loaders.append(
                DataLoader(
                    self.val_dataset,
                    batch_size=self.hparams.batch_size,
                    num_workers=self.hparams.num_workers,
                )
            )
        if len(loaders) == 1:
            return loaders[0]
        return loaders


def noise_seeds(index: torch.Tensor, epoch: int, seed: int) -> torch.Tensor:
    """(B,) int64 seeds, one per sample, from (``seed``, ``epoch``, dataset index): the same on
    every rank and after a resume, new each epoch. NumPy's ``SeedSequence`` spreads them over
    32 bits (the torch CPU generator keeps only the low 32 bits of a seed)."""
    return torch.tensor(
        [
            int(np.random.SeedSequence([seed, epoch, i]).generate_state(1)[0])
            for i in index.tolist()
        ],
        dtype=torch.int64,
    )
