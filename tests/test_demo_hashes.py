"""tools/libero/demo_hashes.py: demos recorded again hash alike; recomputed on another CPU (the same
lengths, values off in their last bits) they are told apart from changed demos."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

TOOL = Path(__file__).resolve().parents[1] / "tools" / "libero" / "demo_hashes.py"


def write_demo(
    path: Path,
    bddl_path: str,
    action: float = 0.0,
    proprio_offset: float = 0.0,
    steps: int = 3,
    gripper_offset: float = 0.0,
) -> None:
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["bddl_file_name"] = bddl_path  # the recording machine's path: not hashed
        demo = data.create_group("demo_0")
        demo.attrs["seed"] = 300000
        demo.create_dataset("actions", data=np.full((steps, 7), action, np.float32))
        proprio = np.linspace(0.5, 1.5, steps * 8).reshape(steps, 8) + proprio_offset
        demo.create_dataset("obs/ee_states", data=proprio)
        # fingers' opening: mean ~0 (as LIBERO's gripper_states), spread 0.026
        fingers = np.array([[0.026, -0.026]] * steps) + 1.7e-7 + gripper_offset
        demo.create_dataset("obs/gripper_states", data=fingers)
        demo.create_dataset(
            "annotations", data=["bowl left of plate"] * steps, dtype=h5py.string_dtype()
        )


def tool(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(TOOL), *args], capture_output=True, text=True)


def test_check_passes_for_the_same_demos_and_names_a_changed_file(tmp_path: Path) -> None:
    first, again = tmp_path / "first", tmp_path / "again"
    first.mkdir()
    again.mkdir()
    write_demo(first / "task_demo.hdf5", "/machine/a/task.bddl")
    write_demo(again / "task_demo.hdf5", "/machine/b/task.bddl")
    prints = json.loads(tool(str(first), str(again)).stdout)
    assert len({p["hash"] for p in prints.values()}) == 1  # same demos, other machine's paths

    recorded = tmp_path / "hashes.json"
    recorded.write_text(tool(str(first)).stdout)
    same = tool("--check", str(recorded))
    assert (
        same.returncode == 0 and "1 of 1 demo files as recorded before: 1 identical" in same.stdout
    )

    # another CPU's rounding: proprio off by 7e-8 (as measured between two machines)
    write_demo(first / "task_demo.hdf5", "/machine/a/task.bddl", proprio_offset=7e-8)
    recomputed = tool("--check", str(recorded))
    assert recomputed.returncode == 0, recomputed.stderr
    assert "0 identical, 1 recomputed" in recomputed.stdout
    # ... and a mean near 0 off in its last bits (measured on a third machine: 1.8e-10 of the
    # fingers' mean of 1.7e-7, 1e-3 of itself but 7e-9 of their spread)
    write_demo(first / "task_demo.hdf5", "/machine/a/task.bddl", gripper_offset=1.8e-10)
    near_zero = tool("--check", str(recorded))
    assert near_zero.returncode == 0, near_zero.stderr

    changes = ({"action": 0.5}, {"proprio_offset": 1e-3}, {"steps": 4}, {"gripper_offset": 1e-3})
    for changed in changes:
        write_demo(first / "task_demo.hdf5", "/machine/a/task.bddl", **changed)
        result = tool("--check", str(recorded))
        assert result.returncode == 1, changed
        assert f"differs: {first / 'task_demo.hdf5'}" in result.stderr
        lengths = "other lengths" if "steps" in changed else "the same seeds and lengths"
        assert f"({lengths}; moments differ by up to" in result.stderr, changed
    (first / "task_demo.hdf5").unlink()
    assert f"missing: {first / 'task_demo.hdf5'}" in tool("--check", str(recorded)).stderr
