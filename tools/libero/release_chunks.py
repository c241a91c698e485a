"""Does a policy let go? Its gripper predictions on held-out demos, where the demo releases.

Exploratory, for LIBERO lever 2 (docs/results.md), whose aux-SFT fits never release the bowl.
The experts' demos end a few steps after the gripper opens, and a training window starts only
where a whole action chunk fits (as OpenVLA-OFT's ``chunk_act_obs``: ``capvector.data.hdf5``), so
the release is never a chunk's first action: it is seen only in the tail of the chunks that start
just before it, the *release chunks* (the target's first action closed, a later one open). A chunk
runs open loop in a rollout, so an opening that a policy puts in a chunk's tail is executed.

Per export, teacher-forced on the held-out demos with its own data spec (statistics, cameras,
centre crop): the action L1 per dimension, and in the release chunks the share of open target
steps predicted open (gripper < 0) and the share of release chunks with any step predicted open.

    python tools/libero/release_chunks.py runs/libero_study/demos_heldout/demos \\
        runs/libero_study/steps16k_*_s*/fit/version_0/export
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import DataLoader

from capvector.backbones.base import OutputRequest
from capvector.data.datamodule import demo_files
from capvector.data.hdf5 import HDF5RobotDataset
from capvector.data.transforms import ImageTransform
from capvector.module import load_module


def release_counts(predicted: Tensor, target: Tensor) -> tuple[int, int, int, int]:
    """Of (B, T, A) action chunks: (release chunks, those with a step predicted open, their open
    target steps, those predicted open). LIBERO's gripper action: +1 closes, -1 opens (OFT leaves
    it unnormalised), so open is a gripper value below 0."""
    target_open, predicted_open = target[..., -1] < 0, predicted[..., -1] < 0
    release = ~target_open[:, 0] & target_open.any(dim=1)
    return (
        int(release.sum()),
        int(predicted_open[release].any(dim=1).sum()),
        int(target_open[release].sum()),
        int((predicted_open & target_open)[release].sum()),
    )


def release_row(export: Path, heldout: Sequence[str], batch_size: int = 64) -> dict[str, float]:
    module = load_module(export).eval()
    spec = module.data_spec
    dataset = HDF5RobotDataset(
        heldout,
        cameras=spec.cameras,
        proprio_keys=spec.proprio_keys,
        chunk_size=spec.chunk_size,
        statistics=spec.stats_entry,
        transform=ImageTransform(augment=False, center_crop=spec.center_crop),
    )
    l1_sum = torch.zeros(spec.action_dim)
    counts = torch.zeros(4, dtype=torch.long)
    with torch.no_grad():
        for batch in DataLoader(dataset, batch_size=batch_size):
            predicted = module.backbone(batch, OutputRequest(actions=True)).actions.float()
            target = batch["actions"].float()
            l1_sum += (predicted - target).abs().mean(dim=1).sum(dim=0)
            counts += torch.tensor(release_counts(predicted, target))
    chunks, chunks_opened, open_targets, open_predicted = counts.tolist()
    l1 = (l1_sum / len(dataset)).tolist()
    return {
        "samples": len(dataset),
        "release_chunks": chunks,
        "open_steps_predicted_open": open_predicted / max(open_targets, 1),
        "release_chunks_with_an_opening": chunks_opened / max(chunks, 1),
        "l1_xyz": sum(l1[:3]) / 3,
        "l1_rotation": sum(l1[3:6]) / 3,
        "l1_gripper": l1[-1],
    }


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("heldout", help="held-out demos: a folder of HDF5 files or one file")
    parser.add_argument("exports", nargs="+", type=Path, help="export folders of the fits")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # beside a running study; the model is tiny
    heldout = demo_files([args.heldout], "heldout")
    print("| export | release chunks | open steps predicted open | release chunks with an "
          "opening | L1 xyz | L1 rotation | L1 gripper |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for export in args.exports:
        row = release_row(export, heldout)
        print(
            f"| {export} | {row['release_chunks']} of {row['samples']} | "
            f"{row['open_steps_predicted_open']:.0%} | {row['release_chunks_with_an_opening']:.0%} | "
            f"{row['l1_xyz']:.4f} | {row['l1_rotation']:.4f} | {row['l1_gripper']:.4f} |"
        )


if __name__ == "__main__":
    main()
