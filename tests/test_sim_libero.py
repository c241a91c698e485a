"""LIBERO adapter: the protocol's pure parts, init-state files, and the missing-LIBERO error.

LIBERO itself (robosuite 1.4 + ~200 MB of assets) cannot run here; the episode loop is exercised
against a stand-in that implements the four LIBERO env methods the protocol calls.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from capvector.sim import libero
from capvector.sim.policy import Observation


def test_step_limits_follow_oft() -> None:
    assert libero.LIBERO_MAX_STEPS == {
        "libero_spatial": 220,
        "libero_object": 280,
        "libero_goal": 300,
        "libero_10": 520,
        "libero_90": 400,
    }
    with pytest.raises(KeyError, match="libero_spatial"):
        libero.max_steps("libero_100")


def test_wait_action_is_still_with_the_gripper_open() -> None:
    np.testing.assert_array_equal(libero.WAIT_ACTION, [0, 0, 0, 0, 0, 0, -1])
    assert libero.NUM_WAIT_STEPS == 10


def test_images_are_rotated_180_degrees() -> None:
    img = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    out = libero.flip_image(img)
    np.testing.assert_array_equal(out, np.rot90(img, 2))
    np.testing.assert_array_equal(out[0, 0], img[-1, -1])
    np.testing.assert_array_equal(libero.flip_image(out), img)


def test_gripper_conventions() -> None:
    def grip(g: float, convention: libero.GripperConvention) -> float:
        return libero.to_libero_action(np.array([0.1, 0, 0, 0, 0, 0, g]), convention)[-1]

    # Ours/openpi: -1 open, +1 close, binarised.
    assert grip(0.3, "close_positive") == 1.0 and grip(-0.2, "close_positive") == -1.0
    # OpenVLA/OFT: [0, 1] with 1 = open -> 2g - 1, sign, then inverted for robosuite.
    assert grip(0.9, "open_is_one") == -1.0  # open
    assert grip(0.1, "open_is_one") == 1.0  # close
    assert grip(0.5, "open_is_one") == -1.0  # the threshold opens
    out = libero.to_libero_action(np.array([0.1, 0.2, 0.3, 0, 0, 0, 1.0]), "open_is_one")
    np.testing.assert_array_equal(out[:3], [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="convention"):
        libero.to_libero_action(np.zeros(7), "inverted")  # type: ignore[arg-type]


@pytest.mark.sim
def test_proprio_matches_robosuite_axis_angle() -> None:
    from robosuite.utils.transform_utils import quat2axisangle

    quat = np.array([0.99, 0.05, 0.1, 0.02])
    quat /= np.linalg.norm(quat)
    obs = {
        "robot0_eef_pos": np.array([0.1, 0.2, 1.0]),
        "robot0_eef_quat": quat,
        "robot0_gripper_qpos": np.array([0.02, -0.02]),
    }
    p = libero.libero_proprio(obs)
    assert p.dtype == np.float32 and p.shape == (8,)
    np.testing.assert_allclose(p[3:6], quat2axisangle(quat.copy()), rtol=1e-6)


@pytest.mark.parametrize("zipped", [True, False])
def test_init_states_load_without_torch_load(tmp_path: Path, zipped: bool) -> None:
    import torch

    states = np.random.default_rng(0).normal(size=(50, 92))
    path = tmp_path / "task.pruned_init"
    torch.save(states, path, _use_new_zipfile_serialization=zipped)
    loaded = libero.load_init_states(path)
    np.testing.assert_array_equal(loaded, states)
    assert loaded.dtype == np.float64


def test_init_states_refuse_code(tmp_path: Path) -> None:
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "evil.pruned_init"
    path.write_bytes(pickle.dumps(Evil()))
    with pytest.raises(pickle.UnpicklingError, match="only numpy arrays"):
        libero.load_init_states(path)


class StandInLiberoEnv:
    """The four methods of LIBERO's OffScreenRenderEnv the protocol uses; done after `solve_at`
    policy steps. Observations are bottom-up like LIBERO's (robosuite 1.4, OpenGL convention)."""

    def __init__(self, solve_at: int | None = None, fail_at: int | None = None) -> None:
        self.solve_at, self.fail_at = solve_at, fail_at
        self.actions: list[list[float]] = []
        image = np.zeros((4, 4, 3), dtype=np.uint8)
        image[-1] = 255  # bottom row of the raw array = top of the scene
        self.obs = {
            "agentview_image": image,
            "robot0_eye_in_hand_image": image,
            "robot0_eef_pos": np.zeros(3),
            "robot0_eef_quat": np.array([1.0, 0.0, 0.0, 0.0]),
            "robot0_gripper_qpos": np.zeros(2),
        }

    def reset(self) -> None:
        self.actions.clear()

    def set_init_state(self, state: np.ndarray) -> dict:
        return self.obs

    def step(self, action: list[float]):
        self.actions.append(action)
        policy_steps = len(self.actions) - libero.NUM_WAIT_STEPS
        if self.fail_at is not None and policy_steps == self.fail_at:
            raise RuntimeError("MuJoCo exploded")
        return self.obs, 0.0, self.solve_at is not None and policy_steps >= self.solve_at, {}


def test_episode_protocol_waits_flips_and_maps_the_gripper() -> None:
    env = StandInLiberoEnv(solve_at=12)
    seen: list[Observation] = []

    def policy(obs: Observation) -> np.ndarray:
        seen.append(obs)
        return np.tile([0.5, 0, 0, 0, 0, 0, 0.9], (8, 1))  # OFT: 0.9 -> open

    result = libero.run_libero_episode(
        policy, env, "put the bowl", np.zeros(5), max_steps=220, gripper_convention="open_is_one"
    )
    assert result.success and result.steps == 12 and result.reason is None
    assert env.actions[:10] == [libero.WAIT_ACTION.tolist()] * 10
    assert env.actions[10] == [0.5, 0, 0, 0, 0, 0, -1.0]
    assert len(seen) == 2 and seen[0]["instruction"] == "put the bowl"
    assert seen[0]["images"]["agentview"][0].min() == 255  # rotated: scene top is row 0
    assert seen[0]["proprio"].shape == (8,)


def test_episode_limits_and_simulator_errors() -> None:
    still = libero.run_libero_episode(
        lambda obs: np.zeros((8, 7)), StandInLiberoEnv(), "x", np.zeros(1), max_steps=20
    )
    assert not still.success and still.steps == 20 and still.reason == "step limit (20) reached"
    crash = libero.run_libero_episode(
        lambda obs: np.zeros((5, 7)),
        StandInLiberoEnv(fail_at=7),
        "x",
        np.zeros(1),
        max_steps=20,
        execute_steps=5,
    )
    # the 7th policy step raises: 6 steps completed
    assert not crash.success and crash.steps == 6 and "MuJoCo exploded" in crash.reason
    with pytest.raises(ValueError, match=r"\(T, 7\)"):
        libero.run_libero_episode(
            lambda obs: np.zeros(3), StandInLiberoEnv(), "x", np.zeros(1), max_steps=20
        )
