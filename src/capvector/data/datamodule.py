"""The Lightning datamodule over robot demonstration files."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from capvector.data.hdf5 import DatasetError, HDF5RobotDataset
from capvector.data.spec import DataSpec
from capvector.data.transforms import ImageTransform

DEFAULT_CAMERAS = ("agentview", "robot0_eye_in_hand")
DEFAULT_PROPRIO = ("robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos")


class RobotDataModule(L.LightningDataModule):
    """Training samples from HDF5 demos; optional held-out demos for an action-L1 validation."""

    def __init__(
        self,
        train_files: list[str],
        val_files: list[str] | None = None,
        cameras: list[str] = None,
        proprio_keys: list[str] = None,
        chunk_size: int = 8,
        batch_size: int = 8,
        num_workers: int = 0,
        augment: bool = True,
        instruction: str | None = None,
        dataset_name: str = "capvector",
        load_depth: bool = False,
        load_annotations: bool = False,
        seed: int = 0,
    ) -> None:
        """
        Args:
            train_files: HDF5 files in the robomimic/LIBERO layout.
            val_files: held-out files; validation then reports the action L1 on them.
            cameras: camera names (``obs/<camera>_image``), in the order the model sees them.
            proprio_keys: ``obs`` keys concatenated into the proprio vector.
            chunk_size: actions per sample (the model's chunk size follows it).
            augment: OFT's random crop + colour jitter at training time.
            instruction: used when a file carries no language instruction.
            dataset_name: the key of the statistics in ``dataset_statistics.json``.
            load_depth: also load ``obs/<camera>_depth`` (geometric teachers need it).
            load_annotations: also load per-step text (the reasoning objective needs it).
        """
        if proprio_keys is None:
            proprio_keys = list(DEFAULT_PROPRIO)
        if cameras is None:
            cameras = list(DEFAULT_CAMERAS)
        super().__init__()
        self.save_hyperparameters()
        missing = [f for f in [*train_files, *(val_files or [])] if not Path(f).is_file()]
        if missing:
            raise DatasetError(
                f"dataset file(s) not found: {missing}. Generate demos with "
                "`capvector demos --task Lift --episodes 20 --out FILE` or fix data.train_files"
            )
        self.train_dataset = self._dataset(train_files, augment=augment)
        self.val_dataset = self._dataset(val_files, augment=False) if val_files else None

    def _dataset(self, files: list[str], augment: bool) -> HDF5RobotDataset:
        hp = self.hparams
        statistics = None
        if getattr(self, "train_dataset", None) is not None:
            statistics = self.train_dataset.statistics  # validation uses the training statistics
        return HDF5RobotDataset(
            files,
            cameras=hp.cameras,
            proprio_keys=hp.proprio_keys,
            chunk_size=hp.chunk_size,
            statistics=statistics,
            transform=ImageTransform(augment=augment, center_crop=hp.augment and not augment),
            instruction=hp.instruction,
            load_depth=hp.load_depth,
            load_annotations=hp.load_annotations,
        )

    @property
    def spec(self) -> DataSpec:
        ds = self.train_dataset
        return DataSpec(
            cameras=list(self.hparams.cameras),
            proprio_keys=list(self.hparams.proprio_keys),
            proprio_dim=ds.proprio_dim,
            action_dim=ds.action_dim,
            chunk_size=self.hparams.chunk_size,
            dataset_name=self.hparams.dataset_name,
            statistics={self.hparams.dataset_name: ds.statistics},
            center_crop=self.hparams.augment,
        )

    def train_dataloader(self) -> DataLoader:
        generator = torch.Generator().manual_seed(self.hparams.seed)
        return DataLoader(
            self.train_dataset,
            batch_size=self.hparams.batch_size,
            shuffle=True,
            num_workers=self.hparams.num_workers,
            persistent_workers=self.hparams.num_workers > 0,
            generator=generator,
            drop_last=len(self.train_dataset) >= self.hparams.batch_size,
        )

    def val_dataloader(self) -> DataLoader | list:
        if self.val_dataset is None:
            return []
        return DataLoader(
            self.val_dataset,
            batch_size=self.hparams.batch_size,
            num_workers=self.hparams.num_workers,
        )
