"""Cost of simulating and rendering a Lift evaluation step on this machine (one run, one table).

    MUJOCO_GL=egl python benchmarks/bench_render.py [--episodes 4] [--size 64]

Every row replays the same action sequences (the scripted expert's executed actions from fixed
seeds), so the rows differ only in what is rendered:

(a) physics only: ``SimEnv`` without cameras: robosuite's full step (its OSC controller code on
    every substep, every observable), then ``SimEnv``'s fast step (the default; the same states)
(b) evaluation step with 2 cameras at ``--size`` px through our ``CameraRenderer``, rendered at
    every step, or once per 8-step chunk (what ``run_episode`` does: the policy needs images only
    when it is asked for a new chunk)
(c) robosuite's own camera observations (``use_camera_obs=True``, its offscreen renderer, same
    cameras and size), rendered at every step as robosuite does

Then the throughput of whole evaluation episodes through ``run_episode`` (policy cost excluded:
the policy replays recorded actions). The machine is shared: the 1-minute load average is printed
with the table, and the numbers are medians over episodes.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import time
from collections.abc import Callable

import numpy as np

from capvector.envs.robosuite.annotations import Annotator
from capvector.envs.robosuite.demos import record_episode
from capvector.envs.robosuite.env import SimEnv, suite
from capvector.envs.robosuite.episode import Episode, robosuite_env
from capvector.envs.robosuite.experts import make_expert
from capvector.envs.robosuite.spec import EpisodeSpec
from capvector.eval.rollout import EnvCache, run_episode

CAMERAS = ["agentview", "robot0_eye_in_hand"]
CHUNK = 8
SEEDS_FROM = 500_000


def expert_actions(episodes: int) -> list[tuple[int, np.ndarray]]:
    sim = SimEnv("Lift", cameras=())
    expert, notes = make_expert(sim), Annotator("Lift", sim.spec)
    out = []
    seed = SEEDS_FROM
    while len(out) < episodes:
        ep = record_episode(sim, expert, notes, seed, render=False, extra_steps=0)
        if ep is not None:
            out.append((seed, ep.executed_actions))
        seed += 1
    sim.close()
    return out


def per_step_ms(
    reset: Callable[[int], None],
    step: Callable[[np.ndarray], None],
    render: Callable[[], None] | None,
    every: int,
    episodes: list[tuple[int, np.ndarray]],
) -> float:
    """Median over episodes of the mean wall time per step (reset excluded)."""
    times = []
    for seed, actions in episodes:
        reset(seed)
        start = time.perf_counter()
        for t, action in enumerate(actions):
            if render is not None and t % every == 0:
                render()
            step(action)
        times.append((time.perf_counter() - start) / len(actions) * 1000)
    return statistics.median(times)


def robosuite_camera_env(sim: SimEnv):
    """robosuite rendering ``sim``'s cameras itself, as its camera observables."""
    size = sim.image_size
    kwargs = {**sim.env_kwargs, "has_offscreen_renderer": True, "use_camera_obs": True}
    env = suite.make("Lift", **copy.deepcopy(kwargs))

    def reset(seed: int) -> None:
        env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
        env.reset()

    def step(action: np.ndarray) -> None:
        obs = env.step(action)[0]
        assert obs["agentview_image"].shape == (size, size, 3)

    return env, reset, step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=4, help="Lift episodes per row")
    parser.add_argument("--size", type=int, default=64, help="image size in pixels")
    args = parser.parse_args()
    size = args.size
    episodes = expert_actions(args.episodes)
    steps = sum(len(a) for _, a in episodes)

    full_step = SimEnv("Lift", cameras=(), fast_step=False)
    physics = SimEnv("Lift", cameras=())
    camera = SimEnv("Lift", cameras=CAMERAS, image_size=size)
    msaa = SimEnv("Lift", cameras=CAMERAS, image_size=size, msaa_samples=4)
    rs_env, rs_reset, rs_step = robosuite_camera_env(camera)
    for sim in (full_step, physics, camera, msaa):  # warm up: numba JIT, GL contexts, caches
        sim.reset(0)
        sim.step(np.zeros(7))
        if sim.cameras:
            sim.render()
    rs_reset(0)
    rs_step(np.zeros(7))

    rows: list[tuple[str, float]] = []
    a = per_step_ms(full_step.reset, full_step.step, None, 1, episodes)
    rows.append(("(a) physics only (no cameras), robosuite's full step", a))
    rows.append(
        (
            "(a) physics only (no cameras), fast step (the default)",
            per_step_ms(physics.reset, physics.step, None, 1, episodes),
        )
    )
    rows.append(
        (
            f"(b) + 2 cameras {size}px, rendered every step",
            per_step_ms(camera.reset, camera.step, camera.render, 1, episodes),
        )
    )
    rows.append(
        (
            f"(b) + 2 cameras {size}px, rendered once per {CHUNK}-step chunk",
            per_step_ms(camera.reset, camera.step, camera.render, CHUNK, episodes),
        )
    )
    rows.append(
        (
            "(b') same, 4x MSAA, rendered every step (not the default)",
            per_step_ms(msaa.reset, msaa.step, msaa.render, 1, episodes),
        )
    )
    rows.append(
        (
            f"(c) robosuite camera obs (use_camera_obs=True), 2 cameras {size}px",
            per_step_ms(rs_reset, rs_step, None, 1, episodes),
        )
    )

    # Whole evaluation episodes through run_episode (env cached, reset included).
    envs = EnvCache()
    robosuite_env(envs, "Lift", cameras=CAMERAS, image_size=size).render()
    durations, lengths = [], []
    for seed, actions in episodes:
        cursor = {"t": 0}

        def replay(obs, actions=actions, cursor=cursor):
            t = cursor["t"]
            cursor["t"] += CHUNK
            return actions[t : t + CHUNK]

        start = time.perf_counter()
        episode = Episode(EpisodeSpec("Lift", seed), envs, cameras=CAMERAS, image_size=size)
        result = run_episode(replay, episode)
        durations.append(time.perf_counter() - start)
        lengths.append(result.steps)
        assert result.success
    start = time.perf_counter()
    episode = Episode(EpisodeSpec("Lift", SEEDS_FROM), envs, cameras=CAMERAS, image_size=size)
    limit = run_episode(lambda obs: np.zeros((CHUNK, 7)), episode)
    full = time.perf_counter() - start
    envs.close()

    print(
        f"Lift, Panda, OSC_POSE at 20 Hz, {len(episodes)} episodes ({steps} steps) per row; "
        f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}; load average {os.getloadavg()[0]:.2f} "
        f"on {os.cpu_count()} CPUs\n"
    )
    print("| setting | ms/step | ratio to (a) |")
    print("|---|---:|---:|")
    for name, ms in rows:
        print(f"| {name} | {ms:.1f} | {ms / a:.2f} |")
    med = statistics.median(durations)
    print()
    print(
        "| evaluation episode (run_episode, replayed actions, no policy cost) | s/episode | episodes/min |"
    )
    print("|---|---:|---:|")
    print(
        f"| success after {statistics.median(lengths):.0f} steps (expert length) "
        f"| {med:.2f} | {60 / med:.0f} |"
    )
    print(f"| failure at the {limit.steps}-step limit | {full:.2f} | {60 / full:.0f} |")
    for sim in (full_step, physics, camera, msaa):
        sim.close()
    rs_env.close()


if __name__ == "__main__":
    main()
