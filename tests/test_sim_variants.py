"""Zero-shot robustness variants on the real simulator: fixed per seed, only the picture changes."""

from __future__ import annotations

import numpy as np
import pytest

from capvector.envs.robosuite.variants import VARIANTS, get_variant, variant_seed

pytestmark = pytest.mark.sim

SEED = 1_000_000


@pytest.fixture(scope="module")
def sim():
    from capvector.envs.robosuite.env import SimEnv

    env = SimEnv("Lift", cameras=("agentview", "robot0_eye_in_hand"), image_size=48)
    yield env
    env.close()


def _frame(sim) -> np.ndarray:
    images, _ = sim.render()
    return np.concatenate(list(images.values()), axis=1).astype(np.int16)


@pytest.mark.parametrize("name", [n for n, v in VARIANTS.items() if v.visual])
def test_visual_variant_is_fixed_by_seed_and_changes_only_the_picture(sim, name: str) -> None:
    from capvector.envs.robosuite.variants import SceneRandomizer

    sim.reset(SEED)
    base, state = _frame(sim), sim.flat_state()
    randomizer = SceneRandomizer(sim, get_variant(name))
    sim.reset(SEED)
    randomizer.apply(SEED)
    first = _frame(sim)
    assert np.abs(first - base).mean() > 1.0  # the policy sees a different scene
    np.testing.assert_array_equal(sim.flat_state(), state)  # from the same initial state
    randomizer.apply(SEED + 1)
    other = _frame(sim)
    assert np.abs(other - first).mean() > 0.5  # each episode draws its own perturbation
    sim.reset(SEED)
    randomizer.apply(SEED)
    np.testing.assert_array_equal(_frame(sim), first)  # the same seed, the same perturbation
    randomizer.restore()
    np.testing.assert_array_equal(_frame(sim), base)


def test_variant_seed_depends_on_name_and_seed_only() -> None:
    assert variant_seed("camera", SEED) == variant_seed("camera", SEED)
    assert variant_seed("camera", SEED) != variant_seed("lighting", SEED)
    assert variant_seed("camera", SEED) != variant_seed("camera", SEED + 1)


def test_unknown_variant_names_the_known_ones() -> None:
    with pytest.raises(KeyError, match="known: camera, camera-strong"):
        get_variant("fog")


def test_the_evaluator_runs_variants_and_names_them_in_rows_and_videos(tmp_path) -> None:
    from capvector.envs.robosuite.spec import eval_specs
    from capvector.eval.results import format_success_table, success_rows
    from capvector.eval.rollout import RolloutEvaluator, close_envs

    def still(observation):
        return np.zeros((4, 7))

    specs = eval_specs("Lift", 1, max_steps=4) + eval_specs("Lift", 1, max_steps=4, variant="all")
    arm = eval_specs("Lift", 1, max_steps=4, variant="ur5e")
    assert (arm[0].robot, arm[0].gripper, arm[0].variant) == ("UR5e", "PandaGripper", None)
    evaluator = RolloutEvaluator(("agentview",), 32, videos=2, video_dir=tmp_path)  # batched
    try:
        plain, varied = evaluator.run(still, specs)
    finally:
        close_envs()
    assert (plain.variant, varied.variant) == (None, "all") and plain.seed == varied.seed
    assert np.abs(plain.frames[0].astype(int) - varied.frames[0].astype(int)).mean() > 1.0
    assert sorted(p.name for p in tmp_path.glob("*.mp4")) == [
        f"Lift_Panda_all_seed{SEED}.mp4",
        f"Lift_Panda_seed{SEED}.mp4",
    ]
    rows = success_rows([plain, varied])
    assert [r.variant for r in rows] == [None, "all"]
    assert rows[1].outcomes == ((SEED, False),)
    assert "| Lift | Panda | all | 0% (0/1; 0%–79%) | 4.0 |" in format_success_table(rows)
