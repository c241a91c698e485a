"""Write the LIBERO settle referee: where upstream LIBERO on robosuite 1.4 / MuJoCo 2.3.7 puts every
object after the evaluation protocol's 10 wait steps, and the inertial properties MuJoCo 2.3.7
compiles for every object body. Runs in the robosuite 1.4 virtualenv (LIBERO's API only, nothing of
capvector's); see tests/fixtures/libero_settle/PROVENANCE.md::

    python tools/libero/make_settle_fixture.py OUT_DIR [INIT_STATES]
"""

import json
import os
import re
import sys

import mujoco
import numpy as np
from libero.libero import benchmark
from libero.libero.envs.env_wrapper import ControlEnv

SUITES = ("libero_spatial", "libero_goal", "libero_object")
WAIT_ACTION = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]


def main(out, n_init):
    import libero.libero as package

    root = os.path.dirname(package.__file__)
    poses, inertia = {}, {}
    if os.path.exists(os.path.join(out, "settle.json")):  # resume: tasks done stay done
        with open(os.path.join(out, "settle.json")) as fh:
            poses = json.load(fh)
        with open(os.path.join(out, "inertia_mujoco237.json")) as fh:
            inertia = json.load(fh)
    for suite in SUITES:
        for task_id, task in enumerate(benchmark.get_benchmark_dict()[suite]().tasks):
            if f"{suite}/{task_id}/0" in poses:
                continue
            bddl = os.path.join(root, "bddl_files", task.problem_folder, task.bddl_file)
            init = os.path.join(root, "init_files", task.problem_folder, task.init_states_file)
            states = np.load(init + ".npz")["states"]
            env = ControlEnv(
                bddl_file_name=bddl,
                has_renderer=False,
                has_offscreen_renderer=False,
                use_camera_obs=False,
            )
            env.seed(0)
            model = env.sim.model._model
            objects = sorted(env.env.objects_dict)
            for name in objects:  # movable objects: their inertia decides how they fall and rest
                category = re.sub(r"_\d+$", "", name)  # LIBERO names instances <category>_<n>
                for body in range(model.nbody):
                    body_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
                    if body_name.startswith(name + "_"):
                        key = category + body_name[len(name) :]
                        inertia[key] = [
                            float(model.body_mass[body]),
                            *map(float, model.body_inertia[body]),
                            *map(float, model.body_ipos[body]),
                            *map(float, model.body_iquat[body]),
                        ]
            for i in range(n_init):
                env.reset()
                fixtures = {
                    f: np.concatenate(
                        [
                            model.body_pos[env.env.obj_body_id[f]],
                            model.body_quat[env.env.obj_body_id[f]],
                        ]
                    ).tolist()
                    for f in sorted(env.env.fixtures_dict)
                }
                env.set_init_state(states[i])
                for _ in range(10):
                    env.step(WAIT_ACTION)
                data = env.sim.data._data
                ids = [env.env.obj_body_id[o] for o in objects]
                poses[f"{suite}/{task_id}/{i}"] = {
                    "fixtures": fixtures,
                    "objects": objects,
                    "pos": np.asarray(data.xpos[ids]).tolist(),
                    "quat": np.asarray(data.xquat[ids]).tolist(),
                }
                print(suite, task_id, i, __import__("time").strftime("%H:%M:%S"), flush=True)
            env.close()
            write(out, poses, inertia)  # after every task: a long run can be resumed


def write(out, poses, inertia):
    os.makedirs(out, exist_ok=True)
    for name, value in (("settle.json", poses), ("inertia_mujoco237.json", inertia)):
        tmp = os.path.join(out, f".{name}.tmp")
        with open(tmp, "w") as fh:
            json.dump(value, fh, indent=0, sort_keys=True)
        os.replace(tmp, os.path.join(out, name))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 1)
