"""What a model needs to know about its data, saved with every checkpoint and export."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class DataSpec:
    """Shapes, camera order and normalisation of the data a model is trained on.

    The datamodule computes it and the CLI hands it to the model (``link_arguments``), so nothing is
    typed twice; evaluation reads it back from the checkpoint instead of re-typing preprocessing.
    """

    cameras: list[str] = field(default_factory=lambda: ["agentview", "robot0_eye_in_hand"])
    proprio_keys: list[str] = field(
        default_factory=lambda: ["robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"]
    )
    proprio_dim: int = 8
    action_dim: int = 7
    chunk_size: int = 8
    dataset_name: str = "capvector"
    statistics: dict[str, Any] = field(default_factory=dict)
    """The ``dataset_statistics.json`` content: {dataset_name: entry}."""
    center_crop: bool = False
    """Evaluation images get OFT's 90%-area centre crop (True when training used random crops)."""
    image_size: int = 64
    """Side of the stored square images; rollouts render at this size."""
    camera_fovy: dict[str, float] | None = None
    """Vertical field of view per camera the demos were rendered with (None: the task default)."""

    @property
    def stats_entry(self) -> dict[str, Any]:
        return self.statistics.get(self.dataset_name, {})

    def backbone_overrides(self) -> dict[str, Any]:
        return {
            "action_dim": self.action_dim,
            "chunk_size": self.chunk_size,
            "proprio_dim": self.proprio_dim,
            "num_images": len(self.cameras),
        }
