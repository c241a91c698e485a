"""Batched evaluation: many episodes in flight, simulators in worker processes, one policy call
per chunk for all of them, with the same outcomes as the one-at-a-time loop."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from capvector.envs.robosuite.spec import eval_specs
from capvector.eval.rollout import RolloutEvaluator, act, close_envs

CAMERAS = ("agentview", "robot0_eye_in_hand")


def blind_lift(observation: dict) -> np.ndarray:
    """Open, descend over the table centre, close, lift (and retry from high up): a function of
    proprio alone, so calls from interleaved episodes cannot leak into each other. It lifts the
    cube in some episodes and not in others, which makes outcomes a sharp check."""
    p = observation["proprio"]
    z, gap = p[2], p[6] - p[7]
    if gap < 0.05 and z < 0.95:
        action = [0, 0, 0.5, 0, 0, 0, 1]  # closed: lift
    elif gap < 0.07 and z >= 0.95:
        action = [0, 0, 0, 0, 0, 0, -1]  # high and not open: open
    elif gap >= 0.07 and (z > 0.83 or abs(p[0]) + abs(p[1]) > 0.01):
        move = np.clip([-10 * p[0], -10 * p[1], -10 * (z - 0.82)], -1, 1)
        action = [*move, 0, 0, 0, -1]  # open: go down over the centre
    else:
        action = [0, 0, 0, 0, 0, 0, 1]  # low and over the centre: close
    return np.tile(np.asarray(action, float), (8, 1))


@pytest.fixture
def fresh_envs():
    yield
    close_envs()


@pytest.mark.sim
@pytest.mark.slow
def test_batched_evaluation_gives_the_one_at_a_time_outcomes(tmp_path: Path, fresh_envs) -> None:
    # 5 episodes over 3 slots: slots take new episodes as others end; one scene variant.
    specs = eval_specs("Lift", 4) + eval_specs("Lift", 1, variant="lighting")
    runs = {}
    for name, batch_size, workers in [("serial", 1, 0), ("here", 3, 0), ("workers", 3, 2)]:
        evaluator = RolloutEvaluator(
            CAMERAS, 32, batch_size=batch_size, workers=workers, videos=1,
            video_dir=tmp_path / name,
        )  # fmt: skip
        runs[name] = evaluator.run(blind_lift, specs)
    outcomes = {
        name: [(r.seed, r.variant, r.success, r.steps, r.reason) for r in results]
        for name, results in runs.items()
    }
    assert outcomes["here"] == outcomes["serial"] == outcomes["workers"]
    successes = [r.success for r in runs["serial"]]
    assert any(successes) and not all(successes)  # a policy that sometimes fails: a sharp check
    # The first episode's video, frame for frame, whichever loop ran it.
    frames = [runs[name][0].frames for name in runs]
    assert all(len(f) == len(frames[0]) and np.array_equal(f[-1], frames[0][-1]) for f in frames)
    assert all(len(list((tmp_path / name).glob("*.mp4"))) == 1 for name in runs)


@pytest.mark.sim
def test_a_failing_worker_names_the_cause(fresh_envs) -> None:
    (spec,) = eval_specs("Lift", 1, robot="NoSuchArm")
    evaluator = RolloutEvaluator(CAMERAS, 32, batch_size=2, workers=2)
    with pytest.raises(RuntimeError, match="simulator worker failed(.|\n)*NoSuchArm"):
        evaluator.run(blind_lift, [spec])
    # The pool was closed with its lost episodes; the next evaluation starts a fresh one.
    (ok,) = evaluator.run(blind_lift, eval_specs("Lift", 1, max_steps=8))
    assert ok.steps == 8


def test_policy_output_is_checked_before_it_reaches_a_simulator() -> None:
    with pytest.raises(ValueError, match=r"policy must return \(T, 7\) actions"):
        act(lambda observation: np.zeros((8, 6)), [{}])


def test_the_vla_policy_batched_forward_matches_one_observation_at_a_time() -> None:
    from capvector.backbones.base import build_backbone
    from capvector.data.spec import DataSpec
    from capvector.data.statistics import compute_statistics
    from capvector.policy import VLAPolicy

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    statistics = compute_statistics(rng.normal(size=(100, 7)), rng.normal(size=(100, 8)), 4)
    spec = DataSpec(statistics={"capvector": statistics})
    backbone = build_backbone("openvla-oft-tiny", **spec.backbone_overrides()).eval()
    policy = VLAPolicy(backbone, spec)
    observations = [
        {
            "images": {c: rng.integers(0, 255, (64, 64, 3), dtype=np.uint8) for c in spec.cameras},
            "proprio": rng.normal(size=8).astype(np.float32),
            "instruction": instruction,
        }
        for instruction in ("lift the cube", "lift the red cube", "pick up the cube")
    ]
    batched = policy.act_batch(observations)
    one_by_one = [policy(o) for o in observations]
    assert all(b.shape == (8, 7) for b in batched)
    for b, o in zip(batched, one_by_one, strict=True):
        np.testing.assert_allclose(b, o, rtol=1e-4, atol=1e-5)
