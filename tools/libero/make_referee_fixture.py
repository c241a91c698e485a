"""Write the LIBERO referee fixture: fixed action sequences replayed on upstream LIBERO code with
robosuite 1.4, the simulator LIBERO's data and published results come from.

Runs in its own virtualenv (robosuite 1.4 cannot share one with this project's 1.5), using
LIBERO's API only, nothing of capvector's; see tests/fixtures/libero_referee/PROVENANCE.md::

    python tools/libero/make_referee_fixture.py tests/fixtures/libero_referee

For each task below and initial states 0 and 1: reset, record the fixtures' poses (fixtures have no
joints, so the init state does not hold them: LIBERO draws them from numpy's global RNG at every
reset), load the init state, then 10 wait steps and a 146-step scripted pick-and-place attempt on
the task's first object of interest (P control of the end-effector position in OSC_POSE delta
space, targets computed from the live state here; the actions are stored and are what the test
replays open loop). Recorded every step: eef position and quaternion, gripper joints, the world
position of every movable object, and LIBERO's success predicate.
"""

import json
import sys
from pathlib import Path

import numpy as np
from libero.libero import benchmark
from libero.libero.envs.env_wrapper import ControlEnv

EPISODES = {
    "libero_spatial": (0, 5),
    "libero_object": (0, 5),
    "libero_goal": (0, 8),
    "libero_10": (0, 5),
}
INIT_STATES = (0, 1)
WAIT_STEPS = 10
GAIN = 10.0  # action per metre of end-effector position error, clipped to [-1, 1]
PLAN = (  # (phase, steps) after the wait steps
    ("above", 30),  # to 10 cm above the object, the gripper's orientation wobbling (seeded)
    ("descend", 20),  # to 2 cm above the object's origin: contact with it or its neighbours
    ("close", 8),
    ("lift", 20),  # 15 cm above the grasp point
    ("carry", 30),  # 15 cm above the goal's second argument (or 10 cm sideways, seeded)
    ("lower", 10),
    ("open", 8),
    ("retreat", 10),
)
CLOSED = {"close", "lift", "carry", "lower"}


def position(env, name):
    return np.array(env.env.object_states_dict[name].get_geom_state()["pos"])


def record(env, objects):
    obs = env.env._get_observations(force_update=True)
    return {
        "eef_pos": obs["robot0_eef_pos"],
        "eef_quat": obs["robot0_eef_quat"],
        "gripper_qpos": obs["robot0_gripper_qpos"],
        "object_pos": np.stack([env.sim.data.body_xpos[env.env.obj_body_id[o]] for o in objects]),
    }


def action_for(env, phase, t, grasp, obj, place, wobble):
    eef = env.env._get_observations(force_update=True)["robot0_eef_pos"]
    if phase == "above":
        target = position(env, obj) + [0, 0, 0.10]
    elif phase == "descend":
        target = position(env, obj) + [0, 0, 0.02]
    elif phase in ("close", "open"):
        target = eef
    elif phase == "lift":
        target = grasp + [0, 0, 0.15]
    elif phase == "carry":
        target = place + [0, 0, 0.15]
    elif phase == "lower":
        target = place + [0, 0, 0.08]
    else:
        target = place + [0, 0, 0.20]
    action = np.zeros(7)
    action[:3] = np.clip(GAIN * (target - eef), -1.0, 1.0)
    if phase == "above":
        action[3:6] = 0.15 * np.sin(2 * np.pi * t / 30 + wobble)
    action[6] = 1.0 if phase in CLOSED else -1.0
    return action.astype(np.float32)  # the fixture stores float32: these exact values are replayed


def run_episode(env, suite, task_id, init_index, state):
    env.reset()
    fixtures = sorted(env.env.fixtures_dict)
    ids = [env.env.obj_body_id[f] for f in fixtures]
    fixture_pos, fixture_quat = (
        env.sim.model.body_pos[ids].copy(),
        env.sim.model.body_quat[ids].copy(),
    )
    env.set_init_state(state)
    objects = sorted(env.env.objects_dict)
    obj = env.env.parsed_problem["obj_of_interest"][0]
    goal = env.env.parsed_problem["goal_state"][0]
    rng = np.random.default_rng([EPISODES[suite].index(task_id), init_index, len(suite)])
    wobble = rng.uniform(0, 2 * np.pi, size=3)
    frames, actions, success = [record(env, objects)], [], []

    def step(action):
        _, _, done, _ = env.step(action.astype(np.float64).tolist())
        actions.append(action)
        success.append(bool(done))
        frames.append(record(env, objects))

    for _ in range(WAIT_STEPS):
        step(np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float32))
    if len(goal) == 3 and goal[2] in env.env.object_states_dict:
        place = position(env, goal[2])
    else:  # a unary goal (open, turn on): carry 10 cm sideways
        angle = rng.uniform(0, 2 * np.pi)
        place = position(env, obj) + 0.10 * np.array([np.cos(angle), np.sin(angle), 0.0])
    t, grasp = 0, None
    for phase, n in PLAN:
        if phase == "lift":
            grasp = np.array(frames[-1]["eef_pos"])
        for _ in range(n):
            step(action_for(env, phase, t, grasp, obj, place, wobble))
            t += 1
    out = {k: np.stack([f[k] for f in frames]).astype(np.float32) for k in frames[0]}
    out.update(
        actions=np.stack(actions),
        success=np.array(success),
        init_state=np.asarray(state, dtype=np.float64),
        fixture_pos=fixture_pos,
        fixture_quat=fixture_quat,
    )
    meta = {
        "suite": suite,
        "task_id": task_id,
        "init_state": init_index,
        "goal": goal,
        "target": obj,
        "objects": objects,
        "fixtures": fixtures,
    }
    return out, meta


def replay_difference(env, out, meta):
    """Replay the stored actions with the same fixture poses: robosuite 1.4 against itself."""
    env.reset()
    ids = [env.env.obj_body_id[f] for f in meta["fixtures"]]
    env.sim.model.body_pos[ids], env.sim.model.body_quat[ids] = (
        out["fixture_pos"],
        out["fixture_quat"],
    )
    env.set_init_state(out["init_state"])
    worst = 0.0
    for t, a in enumerate(out["actions"], start=1):
        env.step(a.astype(np.float64).tolist())
        frame = record(env, meta["objects"])
        worst = max(worst, *(float(np.abs(frame[k] - out[k][t]).max()) for k in frame))
    return worst


def main(out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    arrays, index = {}, []
    for suite, task_ids in EPISODES.items():
        bench = benchmark.get_benchmark_dict()[suite]()
        for task_id in task_ids:
            env = ControlEnv(
                bddl_file_name=bench.get_task_bddl_file_path(task_id),
                has_renderer=False,
                has_offscreen_renderer=False,
                use_camera_obs=False,
            )
            env.seed(0)
            states = bench.get_task_init_states(task_id)
            for i in INIT_STATES:
                out, meta = run_episode(env, suite, task_id, i, states[i])
                key = f"{suite}/{task_id}/{i}"
                meta.update(
                    key=key,
                    task=bench.get_task(task_id).name,
                    success=bool(out["success"].any()),
                    replay_max_abs_difference=replay_difference(env, out, meta),
                )
                arrays.update({f"{key}/{k}": v for k, v in out.items()})
                index.append(meta)
                print(
                    key,
                    meta["goal"],
                    "success",
                    meta["success"],
                    "replay difference",
                    meta["replay_max_abs_difference"],
                    flush=True,
                )
            env.close()
    np.savez_compressed(out_dir / "trajectories.npz", **arrays)
    (out_dir / "episodes.json").write_text(json.dumps(index, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1])
