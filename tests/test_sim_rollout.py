"""run_episode: honest replay of recorded demos, failures and faults, env reuse, videos."""

from __future__ import annotations

from pathlib import Path

import h5py
import imageio.v2 as imageio
import numpy as np
import pytest

from capvector.envs.base import EVAL_SEED_START
from capvector.envs.robosuite.demos import record_demos
from capvector.envs.robosuite.episode import Episode, robosuite_env, to_env_action
from capvector.envs.robosuite.spec import EpisodeSpec, eval_specs
from capvector.eval.rollout import EnvCache, Observation, run_episode
from capvector.eval.video import write_video

SIZE = 32
CAMERAS = ["agentview", "robot0_eye_in_hand"]


@pytest.fixture(scope="module")
def envs() -> EnvCache:
    cache = EnvCache()
    yield cache
    cache.close()


@pytest.fixture(scope="module")
def demos(tmp_path_factory: pytest.TempPathFactory) -> list[dict]:
    """Two noisy Lift demos recorded in their own env (the replays below use another one)."""
    out = tmp_path_factory.mktemp("rollout") / "lift.hdf5"
    record_demos("Lift", 2, out, image_size=SIZE, cameras=CAMERAS, seed=70, progress=False)
    with h5py.File(out) as f:
        return [
            {
                "seed": int(g.attrs["seed"]),
                "first_success": int(g.attrs["first_success"]),
                "executed": g["executed_actions"][:],
                "clean": g["actions"][:],
                "proprio0": np.concatenate(
                    [
                        g["obs/robot0_eef_pos"][0],
                        g["obs/robot0_eef_axis_angle"][0],
                        g["obs/robot0_gripper_qpos"][0],
                    ]
                ),
                "image0": g["obs/agentview_image"][0],
            }
            for g in (f["data/demo_0"], f["data/demo_1"])
        ]


class Replay:
    """Returns a recorded action sequence in chunks of 8, whatever it observes."""

    def __init__(self, actions: np.ndarray, chunk: int = 8) -> None:
        self.actions, self.chunk, self.t, self.calls = actions, chunk, 0, []

    def __call__(self, obs: Observation) -> np.ndarray:
        self.calls.append(obs)
        out = self.actions[self.t : self.t + self.chunk]
        self.t += self.chunk
        return out


def _run(policy, spec: EpisodeSpec, envs: EnvCache, **kwargs):
    return run_episode(policy, Episode(spec, envs, cameras=CAMERAS, image_size=SIZE, **kwargs))


@pytest.mark.sim
def test_replaying_executed_actions_succeeds_where_the_demo_did(demos, envs) -> None:
    # Demo 1 first: the env's history (episodes before) must not matter, only the seed.
    for demo in reversed(demos):
        policy = Replay(demo["executed"])
        result = _run(policy, EpisodeSpec("Lift", demo["seed"]), envs)
        assert result.success and result.reason is None
        assert result.steps == demo["first_success"] + 1
        assert result.seed == demo["seed"]
        first = policy.calls[0]
        np.testing.assert_array_equal(first["images"]["agentview"], demo["image0"])
        np.testing.assert_allclose(first["proprio"], demo["proprio0"], rtol=1e-6)
        assert first["proprio"].dtype == np.float32
        assert first["instruction"] == "lift the red cube"
        assert len(policy.calls) == -(-result.steps // 8)  # one render + query per chunk


@pytest.mark.sim
def test_zero_policy_fails_at_the_step_limit(demos, envs) -> None:
    result = _run(lambda obs: np.zeros((8, 7)), EpisodeSpec("Lift", demos[0]["seed"]), envs)
    assert not result.success
    assert result.steps == 150 and result.reason == "step limit (150) reached"
    # where the episode left the robot: the arm's proprio, the end effector above the table
    assert result.final_proprio is not None and len(result.final_proprio) == 8
    assert 0.8 < result.final_proprio[2] < 1.2


@pytest.mark.sim
def test_execute_steps_replans_more_often(demos, envs) -> None:
    demo = demos[0]
    policy = Replay(demo["executed"], chunk=4)
    result = _run(policy, EpisodeSpec("Lift", demo["seed"]), envs, execute_steps=4)
    assert result.success and len(policy.calls) == -(-result.steps // 4)


@pytest.mark.sim
def test_bad_actions_and_sim_faults_fail_only_their_episode(
    demos, envs, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # MuJoCo appends its warnings to ./MUJOCO_LOG.TXT
    spec = EpisodeSpec("Lift", demos[0]["seed"], max_steps=20)
    nan = _run(lambda obs: np.full((8, 7), np.nan), spec, envs)
    assert not nan.success and nan.steps == 0 and "non-finite action" in nan.reason
    # Huge values are clipped by robosuite's controller to the ±1 action range: no fault.
    huge = _run(lambda obs: np.full((8, 7), 1e30), spec, envs)
    assert not huge.success and huge.reason == "step limit (20) reached"
    # A real MuJoCo blow-up: the policy kicks the arm to absurd joint velocities mid-episode.
    sim = robosuite_env(envs, "Lift", cameras=CAMERAS, image_size=SIZE)
    calls = []

    def kick(obs: Observation) -> np.ndarray:
        calls.append(obs)
        if len(calls) == 2:
            sim.env.sim.data.qvel[:] = 1e12
        return np.zeros((8, 7))

    fault = _run(kick, spec, envs)
    assert not fault.success and fault.steps == 8
    assert "simulation fault" in fault.reason and "mjWARN_BAD" in fault.reason
    assert fault.final_proprio is None or np.isfinite(fault.final_proprio).all()
    # ... and the same env runs the next episode normally.
    demo = demos[1]
    again = _run(Replay(demo["executed"]), EpisodeSpec("Lift", demo["seed"]), envs)
    assert again.success and again.steps == demo["first_success"] + 1


@pytest.mark.sim
def test_wrong_action_shape_is_a_bug_not_a_failure(envs) -> None:
    with pytest.raises(ValueError, match=r"\(T, 7\)"):
        _run(lambda obs: np.zeros((8, 6)), EpisodeSpec("Lift", 1), envs)


@pytest.mark.sim
def test_envs_are_reused_per_configuration(demos, envs) -> None:
    before = len(envs)
    sim = robosuite_env(envs, "Lift", cameras=CAMERAS, image_size=SIZE)
    assert robosuite_env(envs, "Lift", cameras=CAMERAS, image_size=SIZE) is sim
    assert len(envs) == before
    small = EnvCache(max_envs=1)
    try:
        a = robosuite_env(small, "Lift", cameras=["agentview"], image_size=16)
        robosuite_env(small, "Lift", cameras=["agentview"], image_size=24)
        assert len(small) == 1 and a._renderer is None  # evicted and closed
    finally:
        small.close()


@pytest.mark.sim
def test_video_frames_and_files(demos, envs, tmp_path: Path) -> None:
    demo = demos[0]
    result = _run(Replay(demo["executed"]), EpisodeSpec("Lift", demo["seed"]), envs, video=True)
    assert result.frames is not None and len(result.frames) == result.steps + 1
    assert result.frames[0].shape == (SIZE, 2 * SIZE, 3)
    mp4 = write_video(result.frames, tmp_path / "ep.mp4", scale=2)
    with imageio.get_reader(mp4) as reader:
        frames = [frame for frame in reader]  # list() trusts the reader's inf length
    assert len(frames) == len(result.frames) and frames[0].shape == (2 * SIZE, 4 * SIZE, 3)
    gif = write_video(result.frames[:5], tmp_path / "ep.gif")
    assert len(imageio.mimread(gif)) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ep.gif", "ep.mp4"]
    with pytest.raises(ValueError, match=".mp4 or .gif"):
        write_video(result.frames, tmp_path / "ep.avi")


def test_gripper_is_binarised_in_the_demo_convention() -> None:
    out = to_env_action(np.array([0.3, -2.0, 0.0, 0.1, 0.0, 0.0, 0.2]))
    assert out[-1] == 1.0 and out[1] == -2.0  # arm dims untouched (robosuite clips them)
    assert to_env_action(np.array([0, 0, 0, 0, 0, 0, -0.7]))[-1] == -1.0
    assert to_env_action(np.zeros(7))[-1] == -1.0  # undecided means open


def test_eval_seeds_are_disjoint_from_demo_seeds() -> None:
    specs = eval_specs("Lift", 3, robot="IIWA", gripper="PandaGripper")
    assert [s.seed for s in specs] == [EVAL_SEED_START, EVAL_SEED_START + 1, EVAL_SEED_START + 2]
    assert specs[0].step_limit == 150 and EpisodeSpec("Stack", 0).step_limit == 300
    assert EpisodeSpec("Lift", 0, max_steps=10).step_limit == 10
