"""Write LIBERO's own camera images of a few scenes: the reference the fast renderer's looks are
measured against. LIBERO's API only, nothing of capvector's: it runs in upstream's stack
(robosuite 1.4 / MuJoCo 2.3.7, the renderer LIBERO's data and published policies saw; the port's
own renderer draws the same scenes in benchmarks/bench_libero_render_look.py); see
tests/fixtures/libero_render/PROVENANCE.md::

    MUJOCO_GL=egl python tools/libero/make_render_reference.py OUT_DIR [SIZE]

Per scene (LIBERO-Spatial tasks 5-9, the study's downstream tasks, init state 0): an
``OffScreenRenderEnv`` with both cameras at SIZE px (default 128, LIBERO's), ``env.seed(0)``,
``np.random.seed(0)`` then ``reset`` (LIBERO draws its fixtures' placement from numpy's global
generator; their poses are recorded, the test pins them), ``set_init_state`` (which renders the
observation at that state), images written upright as PNG, scenes.json beside them.
"""

import json
import os
import sys

import numpy as np
from libero.libero import benchmark
from libero.libero.envs import OffScreenRenderEnv
from PIL import Image

SCENES = [("libero_spatial", task, 0) for task in (5, 6, 7, 8, 9)]
CAMERAS = ("agentview", "robot0_eye_in_hand")


def main(out, size):
    import libero.libero as package
    import mujoco
    import robosuite

    root = os.path.dirname(package.__file__)
    os.makedirs(out, exist_ok=True)
    scenes = {}
    for suite, task_id, init in SCENES:
        task = benchmark.get_benchmark_dict()[suite]().tasks[task_id]
        bddl = os.path.join(root, "bddl_files", task.problem_folder, task.bddl_file)
        path = os.path.join(root, "init_files", task.problem_folder, task.init_states_file)
        states = np.load(path + ".npz")["states"] if os.path.exists(path + ".npz") else None
        if states is None:
            import torch

            states = torch.load(path, weights_only=False)
        env = OffScreenRenderEnv(
            bddl_file_name=bddl,
            camera_names=list(CAMERAS),
            camera_heights=size,
            camera_widths=size,
        )
        env.seed(0)
        np.random.seed(0)
        env.reset()
        model = env.sim.model._model
        fixtures = {
            f: np.concatenate(
                [model.body_pos[env.env.obj_body_id[f]], model.body_quat[env.env.obj_body_id[f]]]
            ).tolist()
            for f in sorted(env.env.fixtures_dict)
        }
        obs = env.set_init_state(states[init])
        name = f"{suite}_{task_id}_{init}"
        for camera in CAMERAS:
            image = np.asarray(obs[f"{camera}_image"])[::-1]  # OpenGL rows: bottom-up
            tmp = os.path.join(out, f".{name}_{camera}.png.tmp")
            Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG")
            os.replace(tmp, os.path.join(out, f"{name}_{camera}.png"))
        scenes[name] = {"suite": suite, "task": task_id, "init_state": init, "fixtures": fixtures}
        env.close()
        print(name, flush=True)
    meta = {
        "size": size,
        "cameras": list(CAMERAS),
        "robosuite": robosuite.__version__,
        "mujoco": mujoco.__version__,
        "scenes": scenes,
    }
    tmp = os.path.join(out, ".scenes.json.tmp")
    with open(tmp, "w") as fh:
        json.dump(meta, fh, indent=1, sort_keys=True)
    os.replace(tmp, os.path.join(out, "scenes.json"))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 128)
