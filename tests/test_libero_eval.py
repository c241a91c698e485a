"""LIBERO under the official protocol through the one rollout loop: `capvector evaluate --suite`,
LIBERO entries of the validation loop, and an episode's trajectory against OpenVLA-OFT's own loop.

The tests share LIBERO-Spatial task 0; an evaluation closes the LIBERO envs it built (each
~1.2 GB) when it ends. The policy is an untrained tiny OpenVLA-OFT with one 32 px camera:
rendering dominates a LIBERO step on a CPU, so episodes are cut to a few steps.
"""

from __future__ import annotations

import csv
import json
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

from capvector.cli import main
from capvector.envs.libero import env as libero
from capvector.envs.libero.spec import LiberoEpisodeSpec, libero_specs
from capvector.errors import CapVectorError
from capvector.eval.rollout import RolloutEvaluator, close_envs
from conftest import write_untrained_libero_export

SUITE = "libero_spatial"
PORT = f"port (robosuite {version('robosuite')}, MuJoCo {version('mujoco')})"


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained tiny OpenVLA-OFT export that sees the agentview camera at 32 px."""
    folder = write_untrained_libero_export(tmp_path_factory.mktemp("libero") / "export")
    yield folder
    close_envs()


@pytest.mark.sim
@pytest.mark.slow
def test_evaluate_runs_the_protocol_in_workers_and_here_alike(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Batched in two worker processes, and one at a time in this one."""
    runs = {}
    for workers, batch in (("2", "2"), ("0", "1")):
        out = tmp_path / workers
        code = main([
            "evaluate", "--ckpt", str(export), "--suite", SUITE, "--tasks", "0", "--trials", "2",
            "--max-steps", "3", "--batch-size", batch, "--workers", workers,
            "--json", str(out / "eval.json"), "--video", str(out / "videos"),
        ])  # fmt: skip
        assert code == 0
        runs[workers] = out, capsys.readouterr().out
    # the per-task table: task, instruction, successes/trials with their interval, suite total
    table = runs["0"][1]
    instruction = libero.libero_task(SUITE, 0).instruction
    assert f"| {SUITE}/0 | {instruction[:30]}" in table
    assert "| 0% (0/2; 0%–66%) | 3.0 |" in table and f"| {SUITE} (all) |" in table
    (row,) = json.loads((runs["0"][0] / "eval.json").read_text())
    assert row["instruction"] == instruction and row["episodes"] == 2
    # which stack and renderer made it, in the row and under the table
    assert row["stack"] == PORT
    assert f"\nStack: {row['stack']}, {row['renderer']} renderer." in table
    final = [episode.pop("final_proprio") for episode in row["per_episode"]]
    assert row["per_episode"] == [
        {"suite": SUITE, "task": 0, "trial": trial, "success": False, "steps": 3,
         "reason": "step limit (3) reached"}
        for trial in (0, 1)
    ]  # fmt: skip
    # where each trial left the robot: 8 finite values, the eef above LIBERO's table (z ~ 0.9 m)
    assert np.isfinite(final).all() and np.shape(final) == (2, 8)
    assert all(1.0 < f[2] < 1.3 for f in final) and final[0] != final[1]
    (batched,) = json.loads((runs["2"][0] / "eval.json").read_text())
    # a forward of two observations rounds differently from two of one: the same steps, the
    # final states a float32 rounding apart
    batched_final = [episode.pop("final_proprio") for episode in batched["per_episode"]]
    np.testing.assert_allclose(batched_final, final, atol=1e-5)
    assert batched == row
    # The same images, frame for frame: the same trajectories, whichever process stepped them.
    videos = {w: sorted((out / "videos").glob("*.mp4")) for w, (out, _) in runs.items()}
    assert [v.name for v in videos["0"]] == [f"{SUITE}_0_Panda_seed{t}.mp4" for t in (0, 1)]
    for here, there in zip(videos["0"], videos["2"], strict=True):
        assert here.read_bytes() == there.read_bytes()


@pytest.mark.sim
def test_the_validation_loop_logs_libero_success_per_task(export: Path, tmp_path: Path) -> None:
    code = main([
        "validate", "--model.pretrained", str(export), "--trainer.accelerator=cpu",
        f"--data.eval_tasks=[{{suite: {SUITE}, tasks: [0], trials: 2, max_steps: 3}}]",
        "--model.rollout.batch_size=1", "--model.rollout.videos=0",
        f"--trainer.default_root_dir={tmp_path}",
        "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={tmp_path}", "--trainer.enable_progress_bar=false",
    ])  # fmt: skip
    assert code == 0
    version = tmp_path / "lightning_logs" / "version_0"
    with (version / "metrics.csv").open() as f:
        (metrics,) = list(csv.DictReader(f))
    assert metrics["val/episodes"] == "2.0"
    assert metrics["val/success_rate"] == metrics[f"val/success_rate_by_task/{SUITE}/0"] == "0.0"
    with (version / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    episodes = [(e["task"], e["seed"], e["success"]) for e in rows]
    assert episodes == [(f"{SUITE}/0", "0", "0"), (f"{SUITE}/0", "1", "0")]
    # the port, never to be read as upstream LIBERO's robosuite 1.4 (evaluate --backend upstream)
    assert {e["stack"] for e in rows} == {PORT}
    assert {e["renderer"] for e in rows} <= {"fast", "official"} and len(rows) == 2


def press_down(observation: dict) -> np.ndarray:
    """Over a point of the table, down, closing the gripper on the way: a function of proprio
    alone, so it can be run without the evaluator, and into contact, where a trajectory shows
    the smallest difference."""
    p = observation["proprio"]
    move = np.clip([-5 * (p[0] + 0.05), -5 * p[1], -0.8], -1, 1)
    return np.tile([*move, 0.01, 0.0, 0.0, 1.0 if p[2] < 1.0 else -1.0], (4, 1))


class Recording:
    """``press_down`` for a batch, recording what each slot observed (the evaluator calls it with
    its slots' observations in slot order; slot s runs trial s here)."""

    def __init__(self) -> None:
        self.seen: dict[int, list[np.ndarray]] = {0: [], 1: []}

    def act_batch(self, observations: list[dict]) -> list[np.ndarray]:
        assert len(observations) == 2  # both trials run to the step limit
        for slot, observation in enumerate(observations):
            self.seen[slot].append(observation["proprio"])
        return [press_down(o) for o in observations]

    def __call__(self, observation: dict) -> np.ndarray:
        raise AssertionError("the batched loop calls act_batch")


@pytest.mark.sim
def test_an_episode_is_oft_loop_whatever_the_batching() -> None:
    """Two trials batched (state only: no camera) against OpenVLA-OFT's loop on an env reset the
    way OFT's is (hard resets) with the fixtures seeded as the evaluator seeds them."""
    limit = 40
    specs = libero_specs(SUITE, [0], trials=2, max_steps=limit)
    policy = Recording()
    results = RolloutEvaluator((), 0, batch_size=2, workers=0).run(policy, specs)
    assert [(r.success, r.steps) for r in results] == [(False, limit)] * 2
    close_envs()

    env = libero.make_libero_env(SUITE, 0, render=False)  # hard_reset=True, as OFT's
    states = libero.initial_states(SUITE, 0)
    for spec in specs:
        np.random.seed(spec.fixture_seed)
        env.seed(spec.fixture_seed)
        env.reset()
        obs = env.set_init_state(states[spec.trial])
        for _ in range(libero.NUM_WAIT_STEPS):
            obs, _, _, _ = env.step(libero.WAIT_ACTION.tolist())
        seen, steps = [], 0
        while steps < limit:
            proprio = libero.libero_proprio(obs)
            seen.append(proprio)
            for action in press_down({"proprio": proprio}):
                command = libero.to_libero_action(action, "close_positive")
                obs, _, done, _ = env.step(command.tolist())
                steps += 1
                assert not done
        np.testing.assert_array_equal(np.stack(seen), np.stack(policy.seen[spec.trial]))
        assert seen[-1][2] < 0.92  # it came down onto the table, the fingers closing
    env.close()
    # the trials' init states differ, and so do their trajectories once the fingers touch
    assert not np.array_equal(policy.seen[0], policy.seen[1])


@pytest.mark.sim
def test_a_non_finite_action_fails_only_its_trial() -> None:
    spec = LiberoEpisodeSpec(SUITE, 0, 3, max_steps=4)
    (result,) = RolloutEvaluator((), 0, batch_size=1).run(lambda o: np.full((4, 7), np.nan), [spec])
    assert not result.success and result.steps == 0
    assert result.reason.startswith("non-finite action at step 0")
    assert (result.task, result.seed) == (f"{SUITE}/0", 3)
    close_envs()


@pytest.mark.sim
def test_no_libero_env_outlives_its_evaluation() -> None:
    """A stepped LIBERO env holds ~1.1 GB and a fit trains between its validations: a run closes
    the envs it cached, one at a time (an evaluator's own cache too) and batched."""
    from capvector.eval import rollout

    specs = libero_specs(SUITE, [0], trials=2, max_steps=2)
    cache = rollout.EnvCache()
    results = RolloutEvaluator((), 0, envs=cache, batch_size=1).run(press_down, specs[:1])
    assert results[0].steps == 2 and len(cache) == 0
    results = RolloutEvaluator((), 0, batch_size=2, workers=0).run(press_down, specs)
    assert [r.steps for r in results] == [2, 2] and not rollout._local_slots._envs


@pytest.mark.sim
def test_rendering_is_one_option_away_from_the_official_renderer() -> None:
    """`rendering` reaches the env: official is LIBERO's own renderer, fast ours; a typo is named."""
    from capvector.envs.libero.episode import build_libero_env
    from capvector.envs.libero.render import FastRenderEnv

    for rendering, fast in (("official", False), ("fast", True)):
        env = build_libero_env(SUITE, 0, ("agentview",), 32, rendering)
        try:
            assert isinstance(env, FastRenderEnv) is fast
            assert env.reset()["agentview_image"].shape == (32, 32, 3)
        finally:
            env.close()
    with pytest.raises(CapVectorError, match="official"):
        libero_specs(SUITE, [0], 1, rendering="offical")


@pytest.mark.sim
def test_suites_have_the_sizes_checked_before_loading() -> None:
    """`libero_specs` checks task ids and trials against constants; LIBERO agrees with them."""
    for suite in libero.LIBERO_SUITES:
        assert len(libero._suite_tasks(suite)) == libero.LIBERO_NUM_TASKS[suite]
        assert len(libero.initial_states(suite, 0)) == libero.LIBERO_TRIALS


def test_observations_rotate_the_policys_cameras() -> None:
    image = np.arange(4 * 4 * 3, dtype=np.uint8).reshape(4, 4, 3)
    obs = {
        "agentview_image": image,
        "robot0_eye_in_hand_image": image + 1,
        "robot0_eef_pos": np.zeros(3),
        "robot0_eef_quat": np.array([0.0, 0.0, 0.0, 1.0]),
        "robot0_gripper_qpos": np.zeros(2),
    }
    observation = libero.libero_observation(obs, "put the bowl", ["robot0_eye_in_hand"])
    assert list(observation["images"]) == ["robot0_eye_in_hand"]
    np.testing.assert_array_equal(
        observation["images"]["robot0_eye_in_hand"], image[::-1, ::-1] + 1
    )
    assert observation["proprio"].shape == (8,) and observation["instruction"] == "put the bowl"
