"""Replay the port's scripted-expert demos in upstream LIBERO on robosuite 1.4 / MuJoCo 2.3.7 and
write what happens there: the demo-replay referee (tests/fixtures/libero_demo_replay). Runs in the
robosuite 1.4 virtualenv (LIBERO's API only, nothing of capvector's); see that folder's
PROVENANCE.md::

    python tools/libero/make_demo_fixture.py INPUT_DIR OUT_DIR

INPUT_DIR holds ``inputs.npz`` and ``episodes.json`` from ``tools/libero/demo_replay_inputs.py``
(in the port). Per episode: ``reset``, the fixtures pinned where the port's placement put them,
``set_init_state(start)``, every action stepped open loop (the 10 wait steps, then the demo's).
Recorded: LIBERO's success predicate after every step (as the steps where it holds), every movable
object's world position after the wait steps and at the end, and the end effector's at the end.
OUT_DIR gets ``inputs.npz`` and ``episodes.json`` with an ``upstream`` entry per episode, after
every task (a run stopped early keeps the tasks it finished). Episodes
already in OUT_DIR that INPUT_DIR does not hold are kept as they are (their arrays too), so a suite
can be added to the fixture without replaying the others; episodes of INPUT_DIR that have an
``upstream`` entry already (another run's OUT_DIR) are taken as they are, so two runs made side by
side merge into one fixture.
"""

import json
import os
import sys

import numpy as np
from libero.libero import benchmark, get_libero_path
from libero.libero.envs.env_wrapper import ControlEnv

WAIT_STEPS = 10


def run(env, episode, start, actions, fixtures):
    env.reset()
    for name, pose in zip(episode["fixtures"], fixtures, strict=True):
        body = env.env.obj_body_id[name]
        env.sim.model.body_pos[body], env.sim.model.body_quat[body] = pose[:3], pose[3:]
    env.set_init_state(start)
    ids = [env.env.obj_body_id[o] for o in episode["objects"]]
    success, settled = [], None
    for t, action in enumerate(actions):
        _, _, done, _ = env.step(action.astype(np.float64).tolist())
        success.append(bool(done))
        if t + 1 == WAIT_STEPS:
            settled = np.array(env.sim.data.body_xpos[ids])
    obs = env.env._get_observations(force_update=True)
    return {
        "success_steps": [int(t) for t in np.flatnonzero(success)],
        "settled_pos": settled.tolist(),
        "final_pos": np.array(env.sim.data.body_xpos[ids]).tolist(),
        "final_eef": np.asarray(obs["robot0_eef_pos"]).tolist(),
    }


def main(inputs, out):
    with open(os.path.join(inputs, "episodes.json")) as fh:
        episodes = json.load(fh)
    npz = np.load(os.path.join(inputs, "inputs.npz"))
    # episodes that carry an `upstream` entry already (another run's output) are taken as they are
    done = [e for e in episodes if "upstream" in e]
    if done:
        write(out, done, npz)
    tasks = sorted({(e["suite"], e["task_id"]) for e in episodes if "upstream" not in e})
    for suite, task_id in tasks:
        task = benchmark.get_benchmark_dict()[suite]().get_task(task_id)
        bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
        env = ControlEnv(
            bddl_file_name=bddl,
            has_renderer=False,
            has_offscreen_renderer=False,
            use_camera_obs=False,
        )
        env.seed(0)
        todo = [
            e
            for e in episodes
            if (e["suite"], e["task_id"]) == (suite, task_id) and "upstream" not in e
        ]
        for episode in todo:
            key = episode["key"]
            assert sorted(env.env.objects_dict) == episode["objects"], key
            episode["upstream"] = run(
                env, episode, npz[key + "/start"], npz[key + "/actions"], npz[key + "/fixtures"]
            )
            print(key, episode["upstream"]["success_steps"][:1], flush=True)
        env.close()
        write(out, todo, npz)  # after every task: a run stopped early keeps the tasks it did


def write(out, episodes, npz):
    """Merge ``episodes`` (their arrays from ``npz``) into the fixture in ``out``: the npz, then the
    json (a json naming keys the npz lacks fails loudly; the other way round, silently), each
    written beside its target and renamed."""
    os.makedirs(out, exist_ok=True)
    names = ("start", "actions", "fixtures")
    arrays = {f"{e['key']}/{n}": npz[f"{e['key']}/{n}"] for e in episodes for n in names}
    keys = {e["key"] for e in episodes}
    if os.path.exists(os.path.join(out, "episodes.json")):
        with open(os.path.join(out, "episodes.json")) as fh:
            kept = [e for e in json.load(fh) if e["key"] not in keys]
        with np.load(os.path.join(out, "inputs.npz")) as old:
            arrays.update({f"{e['key']}/{n}": old[f"{e['key']}/{n}"] for e in kept for n in names})
        episodes = kept + episodes
    episodes = sorted(
        episodes, key=lambda e: (e["suite"], e["task_id"], int(e["key"].rsplit("/", 1)[1]))
    )
    with open(os.path.join(out, ".inputs.npz.tmp"), "wb") as fh:
        np.savez_compressed(fh, **{k: arrays[k] for k in sorted(arrays)})
    os.replace(os.path.join(out, ".inputs.npz.tmp"), os.path.join(out, "inputs.npz"))
    tmp = os.path.join(out, ".episodes.json.tmp")
    with open(tmp, "w") as fh:
        json.dump(episodes, fh, indent=1)
        fh.write("\n")
    os.replace(tmp, os.path.join(out, "episodes.json"))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
