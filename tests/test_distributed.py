"""2 CPU processes (gloo) under DDP and FSDP2 (ModelParallelStrategy) against one process."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from conftest import run_fit_script, write_demo_file

pytestmark = pytest.mark.distributed


run = run_fit_script


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_demo_file(tmp_path_factory.mktemp("data") / "demos.hdf5", lengths=(20, 20))


@pytest.fixture(scope="module")
def single(tmp_path_factory: pytest.TempPathFactory, data: Path) -> tuple[list[float], Path]:
    out = tmp_path_factory.mktemp("single")
    return run(out, data, "--devices", "1"), out


@pytest.mark.parametrize("strategy", ["ddp", "fsdp2"])
def test_two_processes_match_one_on_the_same_global_batch(
    strategy: str, tmp_path: Path, data: Path, single: tuple[list[float], Path]
) -> None:
    losses, out = run(tmp_path, data, "--devices", "2", "--strategy", strategy), tmp_path
    reference, reference_out = single
    assert len(losses) == len(reference) == 4
    torch.testing.assert_close(torch.tensor(losses), torch.tensor(reference), rtol=1e-5, atol=1e-6)
    ours = load_file(out / "export" / "model.safetensors")
    theirs = load_file(reference_out / "export" / "model.safetensors")
    assert ours.keys() == theirs.keys()
    assert not any("lora_" in k or "base_layer" in k for k in ours)  # gathered and merged
    for key in theirs:
        torch.testing.assert_close(ours[key], theirs[key], rtol=1e-4, atol=1e-5, msg=key)


def test_activation_checkpointing_changes_nothing_but_memory(
    tmp_path: Path, data: Path, single: tuple[list[float], Path]
) -> None:
    losses = run(tmp_path, data, "--devices", "1", "--activation-checkpointing")
    torch.testing.assert_close(torch.tensor(losses), torch.tensor(single[0]), rtol=1e-6, atol=1e-7)
