"""tools/libero/release_chunks.py: which chunks hold the demo's release, and whether a policy puts
an opening in them; its action L1 is the validation loop's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import h5py
import pytest
import torch

from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule, held_out_action_l1
from conftest import write_demo_file

TOOL = Path(__file__).resolve().parents[1] / "tools" / "libero" / "release_chunks.py"
spec = importlib.util.spec_from_file_location("release_chunks", TOOL)
release_chunks = importlib.util.module_from_spec(spec)
spec.loader.exec_module(release_chunks)


def chunks(*grippers: str) -> torch.Tensor:
    """(B, T, 7) chunks whose gripper actions are spelled ``x`` (close, +1) and ``o`` (open, -1),
    LIBERO's convention."""
    out = torch.zeros(len(grippers), len(grippers[0]), 7)
    out[..., -1] = torch.tensor([[1.0 if g == "x" else -1.0 for g in chunk] for chunk in grippers])
    return out


def test_release_chunks_start_closed_and_open_later() -> None:
    target = chunks("xxoo", "xxxo", "oooo", "xxxx", "oxxx")
    predicted = chunks("xxxo", "oxxx", "oooo", "xxxo", "oooo")
    # Release chunks: the first two. Both have a step predicted open (the second's is not where
    # the target opens); of their three open target steps one is predicted open.
    assert release_chunks.release_counts(predicted, target) == (2, 2, 3, 1)


def test_an_export_is_scored_on_the_windows_a_fit_trains_on(tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(14, 11))
    dm = RobotDataModule(train_files=[str(data)], val_files=[str(data)], batch_size=4)
    torch.manual_seed(0)
    module = VLAModule(backbone="openvla-oft-tiny", data_spec=dm.spec)
    module.export(tmp_path / "export")

    row = release_chunks.release_row(tmp_path / "export", [str(data)], batch_size=5)

    chunk = dm.spec.chunk_size
    expected = windows = 0
    with h5py.File(data) as f:
        for demo in f["data"].values():
            gripper = demo["actions"][:, -1]
            for t in range(len(gripper) - chunk + 1):
                windows += 1
                expected += bool(gripper[t] > 0 and (gripper[t : t + chunk] < 0).any())
    assert expected > 0 and (row["samples"], row["release_chunks"]) == (windows, expected)
    # The per-dimension L1, weighted back to all seven, is what the validation loop logs.
    dm.setup("fit")
    module.eval()
    with torch.no_grad():
        batches = list(dm.val_dataloader())
        logged = sum(
            held_out_action_l1(module.backbone, b) * len(b["instruction"]) for b in batches
        ) / sum(len(b["instruction"]) for b in batches)
    mean = (3 * row["l1_xyz"] + 3 * row["l1_rotation"] + row["l1_gripper"]) / 7
    assert mean == pytest.approx(float(logged), rel=1e-5)
