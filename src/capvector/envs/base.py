"""The contract every benchmark suite meets, and the policy interface they share (no simulator
imports: specs, configs and training code use this module freely).

A suite (:class:`Suite`, one package per benchmark under ``capvector.envs``, registered in
:mod:`capvector.envs.registry`) turns an episode spec into a running episode:

    spec (frozen dataclass, ``SUITE`` names its suite; no simulator import)
      -> ``Suite.start(spec, envs, **settings)``: the env (built once, kept in ``envs``), reset to
         the spec's initial state
      -> ``episode.observe()`` -> policy -> ``episode.execute(chunk)``, until it returns
      -> :class:`EpisodeResult`

A policy is any callable ``policy(observation) -> (T, 7)`` array-like of actions: OSC deltas
(dx, dy, dz, drx, dry, drz) and the gripper, in the convention the caller declares (our demos and
robosuite: -1 open, +1 close). The loop that drives episodes, batched or not, in worker processes
or not, is suite-agnostic: :class:`capvector.eval.rollout.RolloutEvaluator`.

Seeds: an episode's initial state is a function of its seed alone. Evaluation seeds must not be
seeds a training demo used; demos start at ``--seed`` (default 0), evaluation at
``EVAL_SEED_START`` = 1,000,000, and the λ sweep's validation episodes at
``VALIDATION_SEED_START`` = 2,000,000, so choosing λ never looks at the reported episodes.
"""

from __future__ import annotations

import inspect
import logging
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol, TypedDict

import numpy as np

from capvector.errors import CapVectorError

ACTION_DIM = 7
EVAL_SEED_START = 1_000_000
"""First default evaluation seed; keep demo seeds below it."""
VALIDATION_SEED_START = 2_000_000
"""First λ-sweep seed: disjoint from demo seeds and from evaluation seeds."""
DEFAULT_ROBOT = "Panda"
log = logging.getLogger(__name__)


class Observation(TypedDict, total=False):
    """What a policy receives; key names match ``capvector.data.batch.Batch``'s."""

    images: dict[str, np.ndarray]
    """``{camera: (H, W, 3) uint8}``, upright, in the order the caller asked for cameras."""
    proprio: np.ndarray
    """(8,) float32, raw (not normalised): eef pos, eef axis-angle, 2 finger joints."""
    instruction: str
    depth: dict[str, np.ndarray]
    """``{camera: (H, W) float32}`` metres along the optical axis (only when asked for)."""


Policy = Callable[[Observation], Any]
"""``policy(observation) -> (T, 7)`` actions (a single (7,) action counts as a chunk of 1)."""


@dataclass
class DemoSummary:
    """What :meth:`Suite.record_demos` wrote for one task (``capvector demos`` prints it)."""

    path: Path
    task: str
    demos: int = 0
    attempts: int = 0
    samples: int = 0
    seeds: list[int] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    """Steps to success of each demo."""
    seconds: float = 0.0

    @property
    def success_rate(self) -> float:
        return self.demos / max(self.attempts, 1)


@dataclass(frozen=True)
class DemoSettings:
    """What every suite's :meth:`Suite.record_demos` takes (its own options come beside it)."""

    cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
    """Cameras to render; none records low-dim demos only."""
    image_size: int | None = None
    """Image height and width; None: the suite's own (robosuite 64, LIBERO 128 as released)."""
    depth: bool = False
    """Also store each camera's depth in metres and its intrinsics."""
    seed: int = 0
    """Seed of the first attempt; attempts use ``seed``, ``seed + 1``, ..."""
    max_attempts: int | None = None
    """Attempts per file before giving up; None: ``max(2 x episodes, episodes + 20)``."""
    progress: bool = True
    """Show a progress bar."""


DEMO_SETTINGS = DemoSettings()
"""The defaults ``Suite.record_demos`` takes."""


@dataclass
class EpisodeResult:
    success: bool
    steps: int
    """Policy steps executed (the step at which success was reached, when it was)."""
    reason: str | None
    """Why the episode failed (step limit, simulation fault, non-finite action); None on success."""
    frames: list[np.ndarray] | None
    """One (H, N_cam * W, 3) uint8 frame per state (cameras side by side), when video was asked."""
    seed: int
    """The seed of the initial state (robosuite) or the index of the fixed init state (LIBERO)."""
    task: str
    robot: str
    variant: str | None = None
    """The scene variant the episode ran in (``capvector.envs.robosuite.variants``); None: as trained."""
    final_proprio: tuple[float, ...] | None = None
    """The robot's raw proprio after the last step (eef pos, axis-angle, fingers): where it ended,
    comparable across simulators (``capvector evaluate --json``)."""


def end_episode(
    spec: Spec,
    success: bool,
    steps: int,
    reason: str | None,
    frames: list[np.ndarray] | None,
    final_proprio: np.ndarray | None,
) -> EpisodeResult:
    """The :class:`EpisodeResult` every suite's episode returns: a failure other than the step
    limit (a fault, a non-finite action) is logged as a warning naming the episode, and a final
    proprio with a non-finite entry (after a simulation fault) is no position (None)."""
    if reason is not None and not reason.startswith("step limit"):
        log.warning("%s seed %d (%s): %s", spec.task, spec.seed, spec.robot, reason)
    final = None
    if final_proprio is not None and np.isfinite(final_proprio).all():
        final = tuple(np.asarray(final_proprio).tolist())
    return EpisodeResult(
        success, steps, reason, frames, spec.seed, spec.task, spec.robot, spec.variant, final
    )


def side_by_side(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """One video frame: the cameras' (H, W, 3) images side by side, in their order."""
    return np.concatenate(list(images.values()), axis=1)


def as_chunk(actions: Any) -> np.ndarray:
    """A policy's output as a (T, 7) float64 array; raises on any other shape."""
    chunk = np.asarray(actions, dtype=np.float64)
    if chunk.ndim == 1:
        chunk = chunk[None]
    if chunk.ndim != 2 or chunk.shape[1] != ACTION_DIM or chunk.shape[0] == 0:
        raise ValueError(f"policy must return (T, {ACTION_DIM}) actions, got shape {chunk.shape}")
    return chunk


def check_options(
    method: Callable[..., Any],
    options: Mapping[str, Any],
    where: str,
    spell: Callable[[str], str] = str,
) -> None:
    """Refuse, in one line, ``options`` that ``method`` (a suite's ``specs`` or ``record_demos``,
    whose options are its parameters with a default) does not take; ``spell`` names an option as
    the caller knows it (``--start-seed`` on a command line)."""
    params = inspect.signature(method).parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return
    named = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    own = [p.name for p in params if p.kind in named and p.default is not p.empty]
    bad = [spell(name) for name in options if name not in own]
    if bad:
        verb = "does" if len(bad) == 1 else "do"
        takes = ", ".join(spell(name) for name in own) or "none"
        raise CapVectorError(f"{', '.join(bad)} {verb} not apply to {where}; its options: {takes}")


class Spec(Protocol):
    """One evaluation episode as data: a frozen, picklable dataclass of its suite's spec module,
    which imports no simulator (specs travel to worker processes and through the validation
    dataset). ``SUITE`` is the registered name of the suite that runs it."""

    SUITE: ClassVar[str]

    @property
    def task(self) -> str:
        """How results, metrics and ``episodes.csv`` name the task."""
        ...

    @property
    def seed(self) -> int:
        """What fixes the initial state (a seed, or the index of a fixed initial state)."""
        ...

    @property
    def robot(self) -> str: ...

    @property
    def variant(self) -> str | None: ...

    @property
    def step_limit(self) -> int:
        """Policy steps after which the episode fails."""
        ...

    def describe(self) -> dict[str, Any]:
        """Which episode it is, as JSON fields (``capvector evaluate --json``)."""
        ...


class Episode(Protocol):
    """One episode in progress, reset to its spec's initial state. The loop calls :meth:`observe`
    for the policy's next chunk, then :meth:`execute` with it, until :meth:`execute` returns the
    result. Simulator faults and non-finite actions fail the episode (a result with a
    ``reason``), never the caller."""

    def observe(self) -> Observation: ...

    def execute(self, actions: Any) -> EpisodeResult | None:
        """Run the chunk open loop; the result when the episode ended, else None."""
        ...


class EnvPool(Protocol):
    """Where episodes get their environments: :class:`capvector.eval.rollout.EnvCache`, which
    keeps built environments for reuse (building one costs seconds) and closes them."""

    fast_step: bool
    """Whether suites that have a fast step and a reference one use the fast one."""

    def get(
        self, key: tuple[Hashable, ...], build: Callable[[], Any], *, alone: bool = False
    ) -> Any:
        """The env cached under ``key``, else ``build()``'s (kept). ``key[0]`` names the suite;
        ``alone``: close the suite's other cached envs first (envs that hold gigabytes)."""
        ...


@dataclass(frozen=True)
class Provenance:
    """What produced a result: the simulator stack (packages and versions) and the renderer."""

    stack: str
    renderer: str

    def to_dict(self) -> dict[str, str]:
        return {"stack": self.stack, "renderer": self.renderer}


def stack_label(packages: Sequence[tuple[str, str]]) -> str:
    """``robosuite 1.5.2, MuJoCo 3.9.0``: each (name, distribution) with its installed version."""
    from importlib.metadata import PackageNotFoundError, version

    def installed(distribution: str) -> str:
        try:
            return version(distribution)
        except PackageNotFoundError:
            return "not installed"

    return ", ".join(f"{name} {installed(dist)}" for name, dist in packages)


class Suite(ABC):
    """A benchmark: its episode specs, environments and episodes. Subclass it in the suite's own
    package, register it in :data:`capvector.envs.registry.SUITES` (a built-in, a
    ``capvector.envs`` entry point, or a ``module:Suite`` name), and the evaluation loop, the
    validation loop, ``capvector evaluate`` and ``tests/test_env_contract.py`` run it.

    The contract (docs/adding-a-benchmark.md):

    - :meth:`specs`: the evaluation protocol of a task set: which tasks, which initial states
      (seeds), which step limits, as specs (no simulator import).
    - :meth:`start`: a spec to a running :class:`Episode` (reset deterministically from the spec),
      its env taken from the pool.
    - :meth:`check`: refuse bad specs before any episode runs (a missing file, ...).
    - :meth:`instruction`: the task's instruction, for result tables (optional).
    - :meth:`record_demos`: scripted-expert demos of a task set, through the one attempt loop and
      HDF5 writer of :mod:`capvector.envs.recording` (optional).
    - ``task_sets``: the names the registry finds the suite by (``capvector evaluate --suite``).
    - ``release_envs``: close the envs after an evaluation (envs that hold gigabytes).
    """

    name: ClassVar[str]
    """The registered name, the ``SUITE`` of its specs."""
    task_sets: ClassVar[tuple[str, ...]] = ()
    """The names :meth:`specs` and :meth:`record_demos` take (a task, or a named set of tasks):
    how ``capvector evaluate``/``demos`` and ``data.eval_tasks`` find the suite of a name
    (:func:`capvector.envs.registry.suite_for_task_set`). Unique across registered suites."""
    seeded: ClassVar[bool] = True
    """Initial states are drawn from seeds, :meth:`specs`' ``start_seed`` option: the λ sweep
    validates on seeds from ``VALIDATION_SEED_START``, disjoint from evaluation's. False: the
    protocol's initial states are fixed (LIBERO's official ones), and the sweep refuses them (it
    would choose λ on the reported episodes)."""
    eval_episodes: ClassVar[int] = 20
    """Episodes per task under the suite's evaluation protocol (``capvector evaluate``'s default)."""
    release_envs: ClassVar[bool] = False
    """Close the cached envs (and worker processes) after each evaluation that ran this suite."""
    cameras: ClassVar[tuple[str, ...]]
    """Camera names its envs render (the policy's data spec picks among them)."""
    example: ClassVar[dict[str, Any]]
    """``specs`` arguments of a small task set: what ``tests/test_env_contract.py`` runs."""
    demo_proprio_keys: ClassVar[tuple[str, ...]] = ()
    """The ``obs`` keys of its demo files whose concatenation is the observation's proprio: what
    ``data.proprio_keys`` names to train on them."""
    demo_example: ClassVar[dict[str, Any] | None] = None
    """:meth:`record_demos` arguments (``task_set`` and the suite's options) of one cheap demo,
    which ``tests/test_env_contract.py`` records and reads back; None: it records no demos."""

    @abstractmethod
    def specs(self, task_set: str, episodes: int, **options: Any) -> list[Spec]:
        """``episodes`` evaluation episodes of each task of ``task_set`` under the suite's protocol
        (a task, or a named set of tasks); ``options`` are the suite's own (e.g. ``max_steps``)."""

    @abstractmethod
    def start(
        self,
        spec: Spec,
        envs: EnvPool,
        *,
        cameras: Sequence[str],
        image_size: int,
        video: bool = False,
        execute_steps: int | None = None,
        camera_fovy: Mapping[str, float] | None = None,
    ) -> Episode:
        """The episode of ``spec``, reset to its initial state. ``cameras``, ``image_size`` and
        ``camera_fovy`` are the policy's (its data spec); ``video`` records a frame per state;
        ``execute_steps`` executes only the first k actions of each chunk."""

    def record_demos(
        self,
        task_set: str,
        episodes: int,
        out: str | os.PathLike[str],
        settings: DemoSettings = DEMO_SETTINGS,
        /,
        **options: Any,
    ) -> list[DemoSummary]:
        """Record ``episodes`` successful scripted-expert demos of each task of ``task_set`` into
        ``out`` (a file, or a folder of one file per task), written atomically by
        :func:`capvector.envs.recording.record_file` in the HDF5 layout
        :class:`capvector.data.hdf5.HDF5RobotDataset` reads. ``settings`` are every suite's;
        ``options`` the suite's own, keyword-only (``capvector demos`` passes those given and
        refuses the rest by flag: :func:`check_options`). A suite without experts keeps this
        default, which refuses."""
        raise CapVectorError(f"the {self.name} suite records no demos (it has no scripted expert)")

    def instruction(self, spec: Spec) -> str | None:
        """The language instruction of ``spec``'s task, for result tables (None: not shown)."""
        return None

    stack_packages: ClassVar[tuple[tuple[str, str], ...]] = (("MuJoCo", "mujoco"),)
    """(name, distribution) of what simulates the suite, for :meth:`provenance`."""

    def provenance(self, spec: Spec) -> Provenance:
        """Which simulator stack and renderer produce ``spec``'s results: every row of
        ``capvector evaluate --json`` and ``episodes.csv`` says, so no number is read as another
        stack's (a LIBERO port's against upstream LIBERO's published ones)."""
        return Provenance(stack_label(self.stack_packages), "MuJoCo")

    def check(self, specs: Sequence[Spec]) -> None:
        """Raise ``CapVectorError`` for specs that cannot run, before any episode does."""
        return None
