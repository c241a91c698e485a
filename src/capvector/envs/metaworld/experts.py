"""Meta-World's own scripted policies (``metaworld.policies``, one per task) as our experts: they
read the env's (39,) state observation (hand, gripper, objects, goal) and act in Meta-World's 4-D
action space; :func:`~capvector.envs.metaworld.env.from_env_action` gives the 7-D label."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from capvector.envs.metaworld.env import MetaWorldEnv, from_env_action, missing_metaworld
from capvector.envs.metaworld.spec import CAMERAS

try:
    from metaworld.policies import ENV_POLICY_MAP
except ImportError as err:
    raise missing_metaworld(err) from err

# metaworld.policies.policy.move warns on every call whose P gain overshoots [-1, 1], i.e. on
# most steps of most experts; the env clips, as Meta-World intends (and act() clips too).
warnings.filterwarnings("ignore", "Constant\\(s\\) may be too high", UserWarning)


@dataclass
class ExpertRun:
    """One expert episode: solved or not, and the step of the first success (or the limit)."""

    task: str
    seed: int
    success: bool
    steps: int
    fault: bool = False


class MetaWorldExpert:
    """The scripted policy of one task; stateless (Meta-World's policies read only the state)."""

    def __init__(self, task: str) -> None:
        self.task = task
        self.policy = ENV_POLICY_MAP[task]()

    def act(self, state: np.ndarray) -> np.ndarray:
        """Meta-World's (4,) action for ``state``, clipped to its [-1, 1] box (the policies' P
        gains overshoot it; the env would clip the xyz dims the same way)."""
        return np.clip(np.asarray(self.policy.get_action(state), dtype=np.float64), -1.0, 1.0)

    def label(self, state: np.ndarray) -> np.ndarray:
        """The (7,) action of our convention for ``state``."""
        return from_env_action(self.act(state))


def run_expert(env: MetaWorldEnv, seed: int, max_steps: int, *, render: bool = False) -> ExpertRun:
    """The expert from ``seed``'s initial state until the first success or ``max_steps``: the
    protocol's episode (the experts read the state; ``render`` draws the cameras anyway)."""
    expert = MetaWorldExpert(env.task)
    state = env.reset(seed, max_steps)
    for t in range(max_steps):
        if render:
            env.render()
        if env.step_env(expert.act(state)):
            return ExpertRun(env.task, seed, True, t + 1)
        if env.faulted:
            return ExpertRun(env.task, seed, False, t + 1, fault=True)
        state = env.state
    return ExpertRun(env.task, seed, False, max_steps)


def evaluate_experts(
    tasks: list[str],
    episodes: int,
    *,
    start_seed: int,
    max_steps: int,
    image_size: int = 0,
    on_task: Callable[[str, list[ExpertRun]], None] | None = None,
) -> dict[str, list[ExpertRun]]:
    """Each task's expert on ``episodes`` seeds from ``start_seed``. ``image_size`` > 0 also
    renders the protocol's camera at every step (the experts do not look: this measures what
    rendering costs, and that it changes nothing)."""
    results: dict[str, list[ExpertRun]] = {}
    for task in tasks:
        cameras = CAMERAS if image_size > 0 else ()
        env = MetaWorldEnv(task, cameras=cameras, image_size=max(image_size, 1))
        try:
            runs = [
                run_expert(env, start_seed + i, max_steps, render=image_size > 0)
                for i in range(episodes)
            ]
        finally:
            env.close()
        results[task] = runs
        if on_task is not None:
            on_task(task, runs)
    return results


def success_table(results: Mapping[str, Sequence[ExpertRun]]) -> str:
    """A Markdown table: per task, successes, rate and mean steps to success."""
    rows = ["| task | success | rate | mean steps (solved) |", "|---|---|---|---|"]
    for task, runs in results.items():
        wins = [r for r in runs if r.success]
        steps = f"{np.mean([r.steps for r in wins]):.0f}" if wins else "-"
        rows.append(f"| {task} | {len(wins)}/{len(runs)} | {len(wins) / len(runs):.0%} | {steps} |")
    return "\n".join(rows)
