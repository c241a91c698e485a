"""An open registry: a suite from a package outside capvector runs through the one rollout loop and
passes the contract test, found by an installed package's entry point or by a ``module:Suite``
name. Nothing in capvector is edited; the runs are subprocesses, as a user's would be.

The outside suite is a point that a policy drives to the origin: no simulator, so the test shows
what the contract asks of a suite and nothing else.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SUITE = """
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from capvector.envs.base import EpisodeResult, Suite
from capvector.envs.registry import SUITES


@dataclass(frozen=True)
class PointSpec:
    SUITE: ClassVar[str] = "point"
    robot: ClassVar[str] = "point"
    variant: ClassVar[None] = None
    task: str
    seed: int
    max_steps: int | None = None

    @property
    def step_limit(self) -> int:
        return self.max_steps or 20

    def describe(self):
        return {"task": self.task, "seed": self.seed}


class PointEnv:
    pos = np.zeros(3)

    def close(self):
        pass


class PointEpisode:
    def __init__(self, spec, env, image_size):
        self.spec, self.env, self.size, self.steps = spec, env, image_size, 0
        env.pos = np.random.default_rng(spec.seed).uniform(-1, 1, 3)

    def observe(self):
        proprio = np.zeros(8, np.float32)
        proprio[:3] = self.env.pos
        image = np.zeros((self.size, self.size, 3), np.uint8)
        return {"images": {"top": image}, "proprio": proprio, "instruction": "go to the origin"}

    def execute(self, actions):
        for action in np.asarray(actions, dtype=float).reshape(-1, 7):
            if not np.isfinite(action).all():
                return self._result(False, "non-finite action")
            self.env.pos = self.env.pos + 0.5 * action[:3]
            self.steps += 1
            if np.linalg.norm(self.env.pos) < 0.05:
                return self._result(True, None)
            if self.steps >= self.spec.step_limit:
                return self._result(False, f"step limit ({self.spec.step_limit}) reached")
        return None

    def _result(self, success, reason):
        spec = self.spec
        return EpisodeResult(success, self.steps, reason, None, spec.seed, spec.task, spec.robot)


@SUITES.register("point")
class PointSuite(Suite):
    name = "point"
    task_sets = ("reach",)
    cameras = ("top",)
    example = {"task_set": "reach", "episodes": 2}

    def specs(self, task_set, episodes, max_steps=None):
        return [PointSpec(task_set, 1_000_000 + i, max_steps) for i in range(episodes)]

    def start(self, spec, envs, *, cameras, image_size, video=False, execute_steps=None,
              camera_fovy=None):
        return PointEpisode(spec, envs.get(("point",), PointEnv), image_size)
"""

RUN = """
import sys
import numpy as np
from capvector.envs.registry import get_suite, registered_suites
from capvector.eval.rollout import RolloutEvaluator

name = sys.argv[1]
suite = get_suite(name)
print(" ".join(registered_suites()))
specs = suite.specs("reach", 3)
policy = lambda obs: np.concatenate([-2 * obs["proprio"][:3], np.zeros(4)])
for batch_size in (1, 2):
    results = RolloutEvaluator(("top",), 8, batch_size=batch_size, workers=0).run(policy, specs)
    assert [(r.success, r.steps, r.seed) for r in results] == [(True, 1, s.seed) for s in specs]
# a config's data.eval_tasks entry finds the suite by its task set, as `capvector evaluate --suite`
from capvector.data.episodes import EpisodeDataset, eval_task

task = eval_task({"task": "reach", "episodes": 3, "max_steps": 5})
assert task.suite == "point", task
assert [s.step_limit for s in EpisodeDataset([task]).specs] == [5, 5, 5]
"""


@pytest.fixture(scope="module")
def outside(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("outside")
    package = root / "code" / "point_suite"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "suite.py").write_text(SUITE)
    installed = root / "installed"  # what `pip install` of a package with an entry point leaves
    info = installed / "point_suite-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: point-suite\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[capvector.envs]\npoint = point_suite.suite\n")
    return {"code": root / "code", "installed": installed}


def run(args: list[str], *paths: Path) -> subprocess.CompletedProcess:
    entries = [*map(str, paths), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(e for e in entries if e))
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)


def test_an_installed_package_registers_its_suite_by_entry_point(outside) -> None:
    done = run([sys.executable, "-c", RUN, "point"], outside["code"], outside["installed"])
    assert done.returncode == 0, done.stderr[-3000:]
    assert {"point", "robosuite", "libero"} <= set(done.stdout.split())


def test_a_module_path_names_a_suite_without_installing_it(outside) -> None:
    done = run([sys.executable, "-c", RUN, "point_suite.suite:PointSuite"], outside["code"])
    assert done.returncode == 0, done.stderr[-3000:]
    done = run([sys.executable, "-c", RUN, "point"], outside["code"])  # not installed: unknown
    assert done.returncode != 0
    assert "unknown benchmark suite 'point'" in done.stderr and "capvector.envs" in done.stderr


def test_an_installed_suite_passes_the_contract_test(outside) -> None:
    """Registering a suite is all it takes for tests/test_env_contract.py to cover it."""
    contract = Path(__file__).parent / "test_env_contract.py"
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
               str(contract), "-k", "point", "-W", "ignore::DeprecationWarning"]  # fmt: skip
    done = run(command, outside["code"], outside["installed"])
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "3 passed" in done.stdout, done.stdout[-2000:]
