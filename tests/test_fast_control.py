"""SimEnv's fast step gives robosuite's full step to the bit, on every arm we simulate.

The referee is robosuite itself: the same actions from the same seed run once through robosuite's
full step (its controller code on every substep, every observable) and once through the fast step
(:mod:`capvector.envs.robosuite.fast_control`, only the observables SimEnv reads), and the simulator states
and observations after every step must be equal, not close: a trajectory that differs in the last
bit anywhere drifts apart within a few steps of contact.
"""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.sim


def _actions(steps: int) -> np.ndarray:
    # Random arm motion with the gripper closing and opening in runs of 10 steps.
    rng = np.random.default_rng(7)
    actions = rng.uniform(-1, 1, size=(steps, 7))
    actions[:, -1] = np.where((np.arange(steps) // 10) % 2 == 0, -1.0, 1.0)
    return actions


def _episodes(sim, actions: np.ndarray) -> list[np.ndarray]:
    """States and observations after every step of two episodes (the second one matters:
    robosuite's reset builds new controller objects)."""
    rows = []
    for seed, episode_actions in ((3, actions), (4, actions[::-1])):
        sim.reset(seed)
        for action in episode_actions:
            sim.step(action)
            observed = [np.ravel(sim.observation[k]) for k in sorted(sim.observation)]
            rows.append(np.concatenate([sim.flat_state(), *observed]))
    return rows


@pytest.mark.parametrize(
    ("task", "robot", "gripper"),
    [("Lift", "Panda", None), ("Lift", "Sawyer", None), ("Lift", "UR5e", "PandaGripper"),
     ("Stack", "Panda", None)],
)  # fmt: skip
def test_the_same_states_and_observations_as_robosuite_s_full_step(task, robot, gripper) -> None:
    from capvector.envs.robosuite.env import SimEnv

    actions = _actions(60)
    runs = []
    for fast_step in (False, True):
        sim = SimEnv(task, robot, gripper=gripper, cameras=(), fast_step=fast_step)
        try:
            assert sim.fast_control is fast_step
            runs.append(np.array(_episodes(sim, actions)))
        finally:
            sim.close()
    full, fast = runs
    assert np.array_equal(fast, full)
    assert np.abs(np.diff(full[:, 1:], axis=0)).max() > 1e-3  # the arm did move


def test_the_fast_step_skips_only_what_sim_env_does_not_read() -> None:
    from capvector.envs.robosuite.env import SimEnv

    fast, full = SimEnv("Lift", cameras=()), SimEnv("Lift", cameras=(), fast_step=False)
    try:
        assert "_pre_action" in vars(fast.env) and "_pre_action" not in vars(full.env)
        enabled = {name for name, o in fast.env._observables.items() if o.is_enabled()}
        assert enabled == {"robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos",
                           "cube_pos", "cube_quat"}  # fmt: skip
        assert all(o.is_enabled() for o in full.env._observables.values())
    finally:
        fast.close()
        full.close()


def test_controllers_it_does_not_cover_keep_robosuite_s_code() -> None:
    import copy

    import robosuite

    from capvector.envs.robosuite import fast_control
    from capvector.envs.robosuite.env import SimEnv

    sim = SimEnv("Lift", cameras=())
    kwargs = copy.deepcopy(sim.env_kwargs)
    sim.close()
    arm = kwargs["controller_configs"]["body_parts"]["right"]
    arm.update(type="JOINT_POSITION", output_max=0.05, output_min=-0.05)
    env = robosuite.make("Lift", **kwargs)
    try:
        assert "JointPositionController" in fast_control.supported(env)
        assert not fast_control.install(env)
        assert "_pre_action" not in vars(env)
    finally:
        env.close()
