"""Cost of a LIBERO step with two cameras, robosuite's rendering vs the fast one (one run, one table).

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/bench_libero_render.py \
        [--suite libero_spatial --task 0 --size 128 --episodes 2 --steps 40 --png sidebyside.png]

Every row replays the same actions from the same initial states (the task's official init states
0, 1, ...: 10 wait steps, then a fixed seeded arm motion that reaches down to the table, so the
wrist camera sees the objects close up), so rows differ only in how a step is computed:

(a) LIBERO as shipped: ``OffScreenRenderEnv``, robosuite's renderer (4x MSAA, shadows,
    reflections), robosuite's controller code on every substep (``rendering="official",
    fast_step=False``); the reference of every ratio
(b) robosuite's renderer, fast controller substeps (:mod:`capvector.envs.robosuite.fast_control`)
(c) no cameras, robosuite's controller; (d) no cameras, fast substeps: the physics share
(e) the fast renderer (:mod:`capvector.envs.libero.render`) and fast substeps: the default on a
    machine without a GPU renderer
(f) as (e), with depth in metres too (``camera_depths=True``: ``capvector demos --suite --depth``)

The states after every step of (b)-(e) are checked against (a) (equal to the bit), and the
images of (e) against those of (a) at the same states. Then the renderers alone, per frame of
both cameras at the recorded states, setting by setting, with their image difference to (a).
Wall and CPU time (this process, every thread) are both given: the machine is shared, and the
1-minute load average is printed with the table. ``--png`` writes default | fast | 4x difference
for a few frames, upright.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import mujoco
import numpy as np

from capvector.envs.libero.env import NUM_WAIT_STEPS, WAIT_ACTION, initial_states, make_libero_env
from capvector.envs.libero.render import DRAWN_GROUPS, FAST_CELLS, render_model
from capvector.envs.robosuite.env import CameraRenderer

CAMERAS = ("agentview", "robot0_eye_in_hand")


def motion(steps: int, seed: int) -> np.ndarray:
    """A smooth seeded arm motion: down towards the table, sideways, up again; the gripper
    closes halfway."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, steps)[:, None]
    actions = np.zeros((steps, 7))
    actions[:, :2] = 0.4 * np.sin(2 * np.pi * (t * rng.uniform(0.5, 1.5, 2) + rng.uniform(0, 1, 2)))
    actions[:, 2] = np.where(t[:, 0] < 0.6, -0.8, 0.8)
    actions[:, 3:6] = 0.1 * rng.standard_normal(3)
    actions[:, 6] = np.where(t[:, 0] < 0.5, -1.0, 1.0)
    return np.concatenate([np.tile(WAIT_ACTION, (NUM_WAIT_STEPS, 1)), actions])


class Run:
    """One env's replay: per-step wall/CPU ms (median over episodes), reset s, states, images."""

    def __init__(self, env: Any, episodes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.wall, self.cpu, self.reset, self.states, self.images = [], [], [], [], []
        for seed, (init, actions) in enumerate(episodes):
            start = time.perf_counter()
            # LIBERO places fixtures (cabinet, stove, ...) with the global numpy generator on
            # every reset, and the init state does not hold them: the same seed, the same scene.
            np.random.seed(seed)
            env.reset()
            obs = env.set_init_state(init)
            self.reset.append(time.perf_counter() - start)
            wall, cpu = time.perf_counter(), time.process_time()
            for action in actions:
                obs, _, _, _ = env.step(action.tolist())
                self.states.append(env.get_sim_state().copy())
                if "agentview_image" in obs:
                    self.images.append([obs[f"{c}_image"][::-1].copy() for c in CAMERAS])
            self.wall.append((time.perf_counter() - wall) / len(actions) * 1000)
            self.cpu.append((time.process_time() - cpu) / len(actions) * 1000)
        env.close()

    @property
    def ms(self) -> tuple[float, float]:
        return statistics.median(self.wall), statistics.median(self.cpu)


def image_diff(a: list[list[np.ndarray]], b: list[list[np.ndarray]]) -> float:
    """Mean absolute difference in grey levels (0-255) over every pixel, channel, camera, frame."""
    return float(
        np.mean(
            [
                np.abs(x.astype(np.int16) - y).mean()
                for xs, ys in zip(a, b, strict=True)
                for x, y in zip(xs, ys, strict=True)
            ]
        )
    )


def time_renderer(
    renderer: CameraRenderer, data: mujoco.MjData, load: Callable[[np.ndarray], None], states
) -> tuple[float, float, list[list[np.ndarray]]]:
    """Median wall/CPU ms per frame (both cameras) over ``states``, and the frames."""
    frames, wall, cpu = [], [], []
    renderer.render(data)  # warm up (shader compilation, first upload)
    for state in states:
        load(state)
        w, c = time.perf_counter(), time.process_time()
        images, _ = renderer.render(data)
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
        frames.append([images[name] for name in CAMERAS])
    return statistics.median(wall) * 1000, statistics.median(cpu) * 1000, frames


def robosuite_like(renderer: CameraRenderer) -> None:
    """robosuite's offscreen settings on a CameraRenderer: the flags ``mujoco.MjvScene`` starts
    with (shadows, reflections, skybox, haze on); MSAA and culling are set at construction."""
    for flag in ("SHADOW", "REFLECTION", "SKYBOX", "HAZE"):
        renderer._scene.flags[getattr(mujoco.mjtRndFlag, f"mjRND_{flag}")] = 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--suite", default="libero_spatial")
    parser.add_argument("--task", type=int, default=0)
    parser.add_argument("--size", type=int, default=128, help="image size in pixels")
    parser.add_argument("--episodes", type=int, default=2, help="init states 0..N-1")
    parser.add_argument("--steps", type=int, default=40, help="moving steps after the wait")
    parser.add_argument("--png", default=None, help="side-by-side image: default | fast | diff")
    args = parser.parse_args()
    inits = initial_states(args.suite, args.task)
    episodes = [(inits[i], motion(args.steps, i)) for i in range(args.episodes)]
    make = dict(suite=args.suite, task_id=args.task, image_size=args.size, cameras=CAMERAS)

    # One env at a time (a LIBERO env holds ~2.4 GB).
    runs = {
        "a": Run(make_libero_env(**make, rendering="official", fast_step=False), episodes),
        "b": Run(make_libero_env(**make, rendering="official", fast_step=True), episodes),
        "c": Run(make_libero_env(**make, render=False, fast_step=False), episodes),
        "d": Run(make_libero_env(**make, render=False, fast_step=True), episodes),
        "e": Run(make_libero_env(**make, rendering="fast", fast_step=True), episodes),
        "f": Run(make_libero_env(**make, rendering="fast", camera_depths=True), episodes),
    }
    reference = np.array(runs["a"].states)
    same = all(np.array_equal(np.array(r.states), reference) for r in runs.values())
    a_wall, a_cpu = runs["a"].ms
    names = {
        "a": f"(a) LIBERO as shipped: robosuite's renderer + controller, 2 cameras {args.size}px",
        "b": "(b) robosuite's renderer, fast controller substeps",
        "c": "(c) no cameras, robosuite's controller",
        "d": "(d) no cameras, fast controller substeps",
        "e": f"(e) fast renderer (cells={FAST_CELLS}) + fast substeps, 2 cameras {args.size}px",
        "f": "(f) as (e), with depth",
    }
    steps = sum(len(actions) for _, actions in episodes)
    print(
        f"{args.suite} task {args.task}, {len(episodes)} episodes ({steps} steps) per row; "
        f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}; load average {os.getloadavg()[0]:.2f} "
        f"on {os.cpu_count()} CPUs; states of every row equal to (a) bit for bit: "
        f"{'yes' if same else 'NO'}\n"
    )
    print("| step | wall ms | speed-up | CPU ms | speed-up | reset s |")
    print("|---|---:|---:|---:|---:|---:|")
    for key, run in runs.items():
        wall, cpu = run.ms
        print(
            f"| {names[key]} | {wall:.1f} | {a_wall / wall:.1f}x | {cpu:.1f} | "
            f"{a_cpu / cpu:.1f}x | {statistics.median(run.reset):.1f} |"
        )

    # The renderers alone, at the states of (a)'s first episode, on a physics-only env's model
    # and data (its scene built from the same seed).
    env = make_libero_env(**make, render=False)
    np.random.seed(0)
    env.reset()
    env.set_init_state(episodes[0][0])
    model, data = env.env.sim.model._model, env.env.sim.data._data
    first = len(episodes[0][1])
    states, default_frames = runs["a"].states[:first:2], runs["a"].images[:first:2]

    def load(state: np.ndarray) -> None:
        env.set_state(state)
        mujoco.mj_forward(model, data)

    # (name, cells or None for the full meshes, MSAA samples, robosuite's flags, culling)
    settings: list[tuple[str, int | None, int, bool, bool]] = [
        (
            "robosuite's settings (4x MSAA, shadows, reflections, skybox, haze)",
            None,
            4,
            True,
            False,
        ),
        ("no MSAA", None, 0, True, False),
        ("no MSAA, no shadows/reflections/skybox/haze", None, 0, False, False),
        ("same + geoms outside the view skipped", None, 0, False, True),
    ]
    for cells in (24, 16, 12, 8):
        mark = " (the fast mode)" if cells == FAST_CELLS else ""
        settings.append((f"same + decimated meshes, cells={cells}{mark}", cells, 0, False, True))
    print()
    print(f"| renderer alone, 2 cameras {args.size}px | wall ms/frame | CPU ms/frame | "
          "mean abs diff to (a) |")  # fmt: skip
    print("|---|---:|---:|---:|")
    for name, cells, msaa, flags, cull in settings:
        drawn = copy.copy(model) if cells is None else render_model(model, cells)
        renderer = CameraRenderer(
            drawn, CAMERAS, args.size, msaa_samples=msaa, cull=cull, geom_groups=DRAWN_GROUPS
        )
        if flags:
            robosuite_like(renderer)
        wall, cpu, frames = time_renderer(renderer, data, load, states)
        renderer.close()
        print(f"| {name} | {wall:.1f} | {cpu:.1f} | {image_diff(frames, default_frames):.2f} |")
    env.close()
    print()
    print(
        f"fast (e) vs (a), every step: mean abs diff {image_diff(runs['e'].images, runs['a'].images):.2f} "
        "grey levels (0-255)"
    )
    if args.png:
        from PIL import Image

        picks = np.linspace(0, len(runs["a"].images) - 1, 4).astype(int)
        rows = []
        for i in picks:
            default = np.concatenate(runs["a"].images[i], axis=1)
            fast = np.concatenate(runs["e"].images[i], axis=1)
            diff = np.clip(np.abs(default.astype(np.int16) - fast) * 4, 0, 255).astype(np.uint8)
            rows.append(np.concatenate([default, fast, diff], axis=1))
        Image.fromarray(np.concatenate(rows, axis=0)).save(args.png)
        print(f"wrote {args.png}: rows = steps {picks.tolist()}; default | fast | 4x |diff|")


if __name__ == "__main__":
    main()
