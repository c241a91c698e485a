"""Meta-World's suite beyond the contract (tests/test_env_contract.py runs its episodes): the
protocol's task sets and limits, the 4-D action map (the rotation dims do nothing, xyz move the
hand), and a recorded expert demo read back by the HDF5 reader and replayed from its seed."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from capvector.envs.metaworld.spec import (
    INSTRUCTIONS,
    MAX_STEPS,
    MT10,
    TASK_SETS,
    metaworld_specs,
)
from capvector.errors import CapVectorError


def test_the_task_sets_are_meta_worlds() -> None:
    assert len(INSTRUCTIONS) == 50 and set(MT10) < set(INSTRUCTIONS)
    assert TASK_SETS["metaworld_mt50"] == tuple(INSTRUCTIONS)
    specs = metaworld_specs("metaworld_mt10", 3, start_seed=7)
    assert [s.task for s in specs[::3]] == list(MT10)
    assert [s.seed for s in specs[:3]] == [7, 8, 9] and specs[0].step_limit == MAX_STEPS
    # data.eval_tasks and capvector evaluate --suite find the suite by the task set's name
    from capvector.data.episodes import EvalTask, eval_task

    assert EvalTask("metaworld_mt10", 2).suite == "metaworld"  # as a config's entry is parsed

    entry = eval_task({"task": "metaworld_mt10", "episodes": 2, "start_seed": 7})
    assert entry.suite == "metaworld" and entry.specs() == metaworld_specs(
        "metaworld_mt10", 2, start_seed=7
    )
    with pytest.raises(CapVectorError, match="did you mean reach-v3"):
        metaworld_specs("reach-v2", 1)
    with pytest.raises(CapVectorError, match="max_steps must be 1..500"):
        metaworld_specs("reach-v3", 1, max_steps=600)


@pytest.fixture(scope="module")
def env():
    os.environ.setdefault("MUJOCO_GL", "egl")
    from capvector.envs.metaworld.env import MetaWorldEnv

    env = MetaWorldEnv("reach-v3", image_size=32)
    yield env
    env.close()


def _hand_after(env, actions: np.ndarray, seed: int = 5) -> np.ndarray:
    env.reset(seed)
    for action in actions:
        env.step(action)
    return env.proprio()


@pytest.mark.sim
def test_the_rotation_dims_change_nothing_and_xyz_move_the_hand(env) -> None:
    actions = np.zeros((6, 7))
    actions[:, 0] = 1.0  # +x, 1 cm a step
    plain = _hand_after(env, actions)
    turned = actions.copy()
    turned[:, 3:6] = np.random.default_rng(0).uniform(-1, 1, (6, 3))
    np.testing.assert_array_equal(_hand_after(env, turned), plain)
    start = _hand_after(env, actions[:0])
    moved = plain[:3] - start[:3]
    assert moved[0] > 0.02 and abs(moved[1]) < 0.01, moved  # 6 cm asked; the hand lags the mocap


@pytest.mark.sim
def test_capvector_demos_records_the_suites_camera_and_the_demo_replays(
    env, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``capvector demos --suite`` finds Meta-World by its task set and records its own camera
    (corner2, not the robosuite default); the reader reads the file; its executed actions
    replayed from its seed give its states."""
    from capvector.data.datamodule import DEFAULT_PROPRIO
    from capvector.data.hdf5 import HDF5RobotDataset
    from capvector.workflows.demos import main

    argv = ["--suite", "reach-v3", "--episodes", "1", "--image-size", "32", "--seed", "3"]
    assert main([*argv, "--out", str(tmp_path), "--no-progress"]) == 0
    assert "wrote 1 reach-v3 demos" in capsys.readouterr().out
    out = tmp_path / "reach-v3.hdf5"
    data = HDF5RobotDataset([out], ["corner2"], DEFAULT_PROPRIO, chunk_size=4)
    assert data[0]["instruction"] == INSTRUCTIONS["reach-v3"]
    assert data.action_dim == 7 and data.proprio_dim == 8 and data.image_size == 32
    with h5py.File(out) as f:
        demo = f["data/demo_0"]
        assert demo.attrs["seed"] == 3
        labels, executed = demo["actions"][:], demo["executed_actions"][:]
        states = demo["states"][:]
        assert not labels[:, 3:6].any()  # Meta-World controls no rotation
        assert (demo["dones"][:] == 1).any() and demo["rewards"][-1] == 1
        first_image = demo["obs/corner2_image"][0]
        first_pos = demo["obs/robot0_eef_pos"][0]
    env.reset(3, MAX_STEPS + 6)
    # what an evaluation episode shows the policy at the demo's first state is what training read
    np.testing.assert_array_equal(env.render()["corner2"], first_image)
    np.testing.assert_array_equal(env.proprio()[:3], first_pos)
    for t, action in enumerate(executed):
        np.testing.assert_array_equal(env.flat_state(), states[t])
        env.step(action)
