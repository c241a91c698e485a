"""How close each fast-renderer look is to LIBERO's own images, and what it costs (one run, tables).

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/bench_libero_render_look.py \
        [--looks fast fast-close ...] [--steps 20] [--png looks.png]

Scenes: those of ``tests/fixtures/libero_render`` (LIBERO-Spatial tasks 5-9, init state 0, the
fixtures pinned), whose images upstream's stack drew (robosuite 1.4 / MuJoCo 2.3.7: what LIBERO's
data and published policies saw). At each scene, the port's own renderer (``official``: robosuite
1.5's, MuJoCo 3.9) draws the same state here too, so every look is measured against both. Per
camera: the mean absolute difference in grey levels (0-255) and the share of pixels more than 32
levels apart in some channel (:func:`capvector.envs.libero.render.image_difference`).

"vs fast": how far the look is from today's default fast images (what making it the default would
change in every fast-rendered demo). Cost: CPU time of this process per frame of both cameras at the scenes (the renderer alone; the
median of ``--repeats`` draws each), and per env step (LIBERO-Spatial task 5: 10 wait steps, then
``--steps`` steps down and sideways, both cameras at the fixture's size, each look's env in turn:
physics and drawing, as an episode pays), each as a ratio to the official renderer's in this run.
Besides the presets of ``FAST_LOOKS``, each of the fast look's settings can be tried alone:
``smooth``, ``shadows``, ``reflections``, ``msaa``, ``cells=N`` and ``cell_size=METRES``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import mujoco
import numpy as np
from PIL import Image

from capvector.envs.libero.env import (
    NUM_WAIT_STEPS,
    WAIT_ACTION,
    initial_states,
    make_libero_env,
    set_fixture_poses,
)
from capvector.envs.libero.render import FAST_LOOKS, FastLook, image_difference, look_renderer

FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "libero_render"


def look_of(name: str) -> FastLook:
    """A preset by name, or the fast look with one setting changed."""
    if name in FAST_LOOKS:
        return FAST_LOOKS[name]
    base = FAST_LOOKS["fast"]
    if name.startswith("cells="):
        return dataclasses.replace(base, cells=int(name.split("=")[1]))
    if name.startswith("cell_size="):
        return dataclasses.replace(base, cell_size=float(name.split("=")[1]))
    change = {"smooth": "smooth", "shadows": "shadows", "reflections": "reflections"}
    if name in change:
        return dataclasses.replace(base, **{change[name]: True})
    if name == "msaa":
        return dataclasses.replace(base, msaa_samples=4)
    raise SystemExit(f"unknown look {name!r}: {', '.join(FAST_LOOKS)}, smooth, shadows, ...")


def scene_images(meta: dict, looks: list[str], repeats: int) -> tuple[dict, dict]:
    """Images ``{look: {scene: {camera: (H, W, 3)}}}`` (``official``: the port's renderer) and
    CPU ms per frame of both cameras ``{look: [ms per scene]}``."""
    size, cameras = meta["size"], meta["cameras"]
    images: dict[str, dict] = {name: {} for name in ["official", *looks]}
    cost: dict[str, list[float]] = {name: [] for name in images}
    for scene, entry in meta["scenes"].items():
        env = make_libero_env(
            entry["suite"], entry["task"], cameras=cameras, image_size=size, rendering="official"
        )
        env.reset()
        set_fixture_poses(env, {k: np.asarray(v) for k, v in entry["fixtures"].items()})
        state = initial_states(entry["suite"], entry["task"])[entry["init_state"]]
        obs = env.set_init_state(state)
        images["official"][scene] = {c: obs[f"{c}_image"][::-1].copy() for c in cameras}
        spent = []
        for _ in range(repeats):
            start = time.process_time()
            env.regenerate_obs_from_state(env.get_sim_state())
            spent.append(time.process_time() - start)
        cost["official"].append(statistics.median(spent) * 1000)
        model, data = env.sim.model._model, env.sim.data._data
        mujoco.mj_forward(model, data)
        for name in looks:
            renderer = look_renderer(model, cameras, size, look_of(name))
            try:
                renderer.render(data)  # the first draw uploads meshes and textures
                spent = []
                for _ in range(repeats):
                    start = time.process_time()
                    drawn, _ = renderer.render(data)
                    spent.append(time.process_time() - start)
            finally:
                renderer.close()
            images[name][scene] = drawn
            cost[name].append(statistics.median(spent) * 1000)
        env.close()
    return images, cost


def step_cost(name: str, size: int, cameras: list[str], steps: int) -> float:
    """CPU ms per env step (physics and drawing) of one episode of LIBERO-Spatial task 5."""
    rendering = name if name in ("official", *FAST_LOOKS) else None
    if rendering is None:
        return float("nan")  # single settings are measured as renderers only
    env = make_libero_env(
        "libero_spatial", 5, cameras=cameras, image_size=size, rendering=rendering
    )
    try:
        np.random.seed(0)
        env.reset()
        env.set_init_state(initial_states("libero_spatial", 5)[0])
        moves = np.zeros((steps, 7))
        moves[:, 0] = 0.4 * np.sin(np.linspace(0, 2 * np.pi, steps))
        moves[:, 2] = -0.6
        moves[:, 6] = -1.0
        actions = np.concatenate([np.tile(WAIT_ACTION, (NUM_WAIT_STEPS, 1)), moves])
        start = time.process_time()
        for action in actions:
            env.step(action.tolist())
        return (time.process_time() - start) / len(actions) * 1000
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--looks", nargs="+", default=list(FAST_LOOKS))
    parser.add_argument("--repeats", type=int, default=5, help="draws per scene and look")
    parser.add_argument("--steps", type=int, default=20, help="moving steps for the step cost")
    parser.add_argument("--png", default=None, help="upstream | official | each look, per scene")
    args = parser.parse_args()
    meta = json.loads((FIXTURE / "scenes.json").read_text())
    cameras = meta["cameras"]
    upstream = {
        scene: {c: np.asarray(Image.open(FIXTURE / f"{scene}_{c}.png")) for c in cameras}
        for scene in meta["scenes"]
    }
    images, cost = scene_images(meta, args.looks, args.repeats)
    step = {name: step_cost(name, meta["size"], cameras, args.steps) for name in images}
    print(
        f"{len(meta['scenes'])} scenes ({', '.join(meta['scenes'])}), {meta['size']} px; "
        f"reference: robosuite {meta['robosuite']} / MuJoCo {meta['mujoco']} (upstream) and the "
        f"port's renderer; load average {__import__('os').getloadavg()[0]:.1f}\n"
    )
    header = " | ".join(f"{c}: vs upstream | vs official | vs fast" for c in cameras)
    print(f"| look | {header} | CPU ms/frame | ratio | CPU ms/step | ratio |")
    print("|---|" + "---:|" * (3 * len(cameras) + 4))
    for name, drawn in images.items():
        cells = []
        for c in cameras:
            for ref in (upstream, images["official"], images.get("fast", drawn)):
                pairs = [image_difference(ref[s][c], drawn[s][c]) for s in meta["scenes"]]
                mad = np.mean([p[0] for p in pairs])
                share = np.mean([p[1] for p in pairs]) * 100
                cells.append(f"{mad:.2f} / {share:.1f}%")
        frame = statistics.mean(cost[name])
        official = statistics.mean(cost["official"])
        print(
            f"| {name} | " + " | ".join(cells) + f" | {frame:.1f} | {frame / official:.3f} | "
            f"{step[name]:.1f} | {step[name] / step['official']:.3f} |"
        )
    print("\ncells: mean abs diff (grey levels) / pixels > 32 levels apart")
    if args.png:
        rows = []
        for scene in meta["scenes"]:
            columns = [upstream[scene]] + [images[n][scene] for n in images]
            rows.append(
                np.concatenate([np.concatenate([col[c] for c in cameras]) for col in columns], 1)
            )
        Image.fromarray(np.concatenate(rows)).save(args.png)
        print(f"wrote {args.png}: columns upstream, {', '.join(images)}")


if __name__ == "__main__":
    main()
