"""The suite contract (``capvector.envs.base.Suite``), checked on every registered suite, as
``test_backbone_contract.py`` checks every preset: specs are data that import no simulator, an
episode's reset is a function of its spec, the observation has the policy's schema, the step limit
ends an episode, the result names the episode it ran, and a demo its expert records reads back
through the data reader as the policy saw it. A new suite is covered by registering
it (docs/adding-a-benchmark.md)."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from dataclasses import FrozenInstanceError, fields, replace
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
import torch

from capvector.data.hdf5 import HDF5RobotDataset
from capvector.envs import recording
from capvector.envs.base import DemoSettings, EpisodeResult
from capvector.envs.recording import write_demo
from capvector.envs.registry import get_suite, registered_suites
from capvector.eval.rollout import EnvCache

SUITES = registered_suites()
RECORDING_SUITES = [name for name in SUITES if get_suite(name).demo_example is not None]
"""The suites whose scripted experts record demos (a suite may have none)."""
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

    # Which simulator stack and renderer made it, with the versions installed (every result row
    # and episodes.csv carry it: a LIBERO port's numbers are not upstream LIBERO's).
    made_by = suite.provenance(first)
    versions = [version(dist) for _, dist in suite.stack_packages]
    assert made_by.renderer and all(v in made_by.stack for v in versions), made_by

    # A fault fails the episode, not the caller.
    episode = _start(name, first, envs)
    episode.observe()
    bad = episode.execute(np.full((1, 7), np.nan))
    assert bad is not None and not bad.success and "non-finite" in bad.reason


@pytest.mark.parametrize("name", RECORDING_SUITES)
def test_a_recorded_demo_reads_back_as_the_policy_saw_it(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One demo by the suite's scripted expert, through the one writer and the data reader: the
    same actions, and the images and proprio the suite's live observation showed (each suite
    stores frames in its own layout and orientation; the reader must undo exactly that)."""
    suite = get_suite(name)
    written: list[recording.Demo] = []

    def write_and_keep(group, demo: recording.Demo) -> None:  # the real writer, watched
        written.append(demo)
        write_demo(group, demo)

    monkeypatch.setattr(recording, "write_demo", write_and_keep)
    options = dict(suite.demo_example)
    settings = DemoSettings(image_size=SIZE, progress=False)
    summaries = suite.record_demos(
        options.pop("task_set"), 1, tmp_path / "demos", settings, **options
    )
    assert [s.demos for s in summaries] == [1] and len(written) == 1
    (demo,) = written
    assert summaries[0].lengths == [demo.length] and summaries[0].seeds == [demo.seed]

    data = HDF5RobotDataset(
        [summaries[0].path], suite.cameras, suite.demo_proprio_keys, chunk_size=1, cache_mb=0
    )
    assert len(data) == demo.num_samples
    # the reader hands out normalised actions and proprio (by statistics of the file it read)
    actions = data.normalizer.normalize("action", np.asarray(demo.steps["actions"], np.float32))
    proprio = data.normalizer.normalize("proprio", demo.proprio)
    for t in range(demo.num_samples):
        sample = data[t]
        np.testing.assert_allclose(sample["actions"][0].numpy(), actions[t], atol=1e-6)
        np.testing.assert_allclose(sample["proprio"].numpy(), proprio[t], atol=1e-5)
        pixels = (sample["images"] * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
        for view, camera in zip(pixels, suite.cameras, strict=True):
            np.testing.assert_array_equal(view, demo.images[camera][t], err_msg=f"{camera} {t}")
