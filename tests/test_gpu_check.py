"""tools/gpu_check.py's path on a machine without CUDA: one line, exit 0; its table lines."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

TOOL = Path(__file__).resolve().parents[1] / "tools" / "gpu_check.py"


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CUDA path runs on a GPU node")
def test_without_cuda_one_line_and_exit_zero() -> None:
    out = subprocess.run([sys.executable, str(TOOL)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        f"gpu_check: no CUDA device (torch {torch.__version__}); nothing to check here"
    ]


def test_row_lines_up_with_the_header() -> None:
    sys.path.insert(0, str(TOOL.parent))
    from gpu_check import HEADER, Row

    line = Row("pi05-3b", 1.5, 2.0, 30.0, 28.0, 4.0, 0.35).line()
    assert len(line) == len(HEADER) and "1.07" in line and "35.0%" in line


@pytest.mark.sim
def test_libero_episode_runs_the_evaluate_path_at_the_recipes_settings() -> None:
    """The GPU check's LIBERO episode, on the CPU with the tiny preset: LIBERO's real scene, the
    policy built as the check builds it (frozen bf16, LoRA r 32) under bf16 autocast."""
    sys.path.insert(0, str(TOOL.parent))
    from gpu_check import libero_episode

    line = libero_episode("openvla-oft-tiny", "cpu", max_steps=16)
    assert line.startswith("LIBERO-Spatial task 0, initial state 0, openvla-oft-tiny on cpu")
    assert " 16 steps in " in line and "(bf16-mixed)" in line
