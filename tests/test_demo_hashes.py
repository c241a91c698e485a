"""tools/libero/demo_hashes.py: demos recorded again hash alike, a changed value does not."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

TOOL = Path(__file__).resolve().parents[1] / "tools" / "libero" / "demo_hashes.py"


def write_demo(path: Path, bddl_path: str, action: float = 0.0) -> None:
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["bddl_file_name"] = bddl_path  # the recording machine's path: not hashed
        demo = data.create_group("demo_0")
        demo.attrs["seed"] = 300000
        demo.create_dataset("actions", data=np.full((3, 7), action, np.float32))
        demo.create_dataset(
            "annotations", data=["bowl left of plate"] * 3, dtype=h5py.string_dtype()
        )


def tool(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(TOOL), *args], capture_output=True, text=True)


def test_check_passes_for_the_same_demos_and_names_a_changed_file(tmp_path: Path) -> None:
    first, again = tmp_path / "first", tmp_path / "again"
    first.mkdir()
    again.mkdir()
    write_demo(first / "task_demo.hdf5", "/machine/a/task.bddl")
    write_demo(again / "task_demo.hdf5", "/machine/b/task.bddl")
    hashes = json.loads(tool(str(first), str(again)).stdout)
    assert len(set(hashes.values())) == 1  # same demos, other machine's paths

    recorded = tmp_path / "hashes.json"
    recorded.write_text(tool(str(first)).stdout)
    assert tool("--check", str(recorded)).returncode == 0
    write_demo(first / "task_demo.hdf5", "/machine/a/task.bddl", action=0.5)
    changed = tool("--check", str(recorded))
    assert changed.returncode == 1
    assert f"differs or is missing: {first / 'task_demo.hdf5'}" in changed.stderr
