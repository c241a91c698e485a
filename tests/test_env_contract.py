"""The suite contract (``capvector.envs.base.Suite``), checked on every registered suite, as
``test_backbone_contract.py`` checks every preset: specs are data that import no simulator, an
episode's reset is a function of its spec, the observation has the policy's schema, the step limit
ends an episode, and the result names the episode it ran. A new suite is covered by registering
it (docs/adding-a-benchmark.md)."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from dataclasses import FrozenInstanceError, fields, replace

import numpy as np
import pytest

from capvector.envs.base import EpisodeResult
from capvector.envs.registry import get_suite, registered_suites
from capvector.eval.rollout import EnvCache

SUITES = registered_suites()
SIZE = 32


def test_the_built_in_suites_are_registered() -> None:
    assert {"robosuite", "libero"} <= set(SUITES)


@pytest.mark.parametrize("name", SUITES)
def test_specs_are_frozen_picklable_data_of_their_suite(name: str) -> None:
    suite = get_suite(name)
    specs = suite.specs(**suite.example)
    assert specs and len({(s.task, s.seed) for s in specs}) == len(specs)
    for spec in specs:
        assert type(spec).SUITE == suite.name == name
        assert isinstance(spec.step_limit, int) and spec.step_limit > 0
        assert pickle.loads(pickle.dumps(spec)) == spec  # specs travel to worker processes
        json.dumps(spec.describe())
        with pytest.raises(FrozenInstanceError):
            setattr(spec, fields(spec)[0].name, None)


@pytest.mark.parametrize("name", SUITES)
def test_specs_import_no_simulator(name: str) -> None:
    """Configs, the validation dataset and training code build specs freely."""
    code = (
        "import sys\n"
        "from capvector.envs.registry import get_suite\n"
        f"suite = get_suite({name!r})\n"
        "suite.specs(**suite.example)\n"
        "heavy = sorted(m for m in ('robosuite', 'mujoco', 'libero') if m in sys.modules)\n"
        "assert not heavy, f'building specs loaded {heavy}'\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.fixture(scope="module")
def envs():
    cache = EnvCache(max_envs=2)
    yield cache
    cache.close()


def _start(name: str, spec, envs: EnvCache):
    suite = get_suite(name)
    return suite.start(spec, envs, cameras=suite.cameras[:1], image_size=SIZE)


@pytest.mark.sim
@pytest.mark.parametrize("name", SUITES)
def test_an_episode_meets_the_contract(name: str, envs: EnvCache) -> None:
    suite = get_suite(name)
    first, second = suite.specs(**suite.example)[:2]
    camera = suite.cameras[0]

    # The observation's schema: what the policy and the training data share.
    episode = _start(name, first, envs)
    obs = episode.observe()
    assert set(obs["images"]) == {camera}
    image = obs["images"][camera]
    assert image.shape == (SIZE, SIZE, 3) and image.dtype == np.uint8
    assert obs["proprio"].shape == (8,) and obs["proprio"].dtype == np.float32
    assert isinstance(obs["instruction"], str) and obs["instruction"]

    # The reset is a function of the spec alone: again, after another episode ran in the env.
    _start(name, second, envs).observe()
    again = _start(name, first, envs).observe()
    np.testing.assert_array_equal(again["proprio"], obs["proprio"])
    np.testing.assert_array_equal(again["images"][camera], image)

    # The step limit ends the episode, mid-chunk; the result names the episode.
    limited = replace(first, max_steps=3)
    episode = _start(name, limited, envs)
    episode.observe()
    result = episode.execute(np.zeros((8, 7)))
    assert isinstance(result, EpisodeResult)
    assert not result.success and result.steps == 3 and result.reason.startswith("step limit")
    assert (result.task, result.seed, result.robot) == (first.task, first.seed, first.robot)
    assert result.variant == first.variant

    # A fault fails the episode, not the caller.
    episode = _start(name, first, envs)
    episode.observe()
    bad = episode.execute(np.full((1, 7), np.nan))
    assert bad is not None and not bad.success and "non-finite" in bad.reason
