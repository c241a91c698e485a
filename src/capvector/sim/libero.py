"""LIBERO evaluation following the OpenVLA-OFT / openpi protocol.

LIBERO pins robosuite 1.4 (our env uses 1.5.2) and fetches ~200 MB of scene assets on first use,
so it runs in its own environment: install ``libero`` with robosuite 1.4 there, write
``~/.libero/config.yaml`` (or ``$LIBERO_CONFIG_PATH/config.yaml``) pointing at the assets, and run
this module's :func:`run_libero_suite` in that process. Nothing here imports robosuite 1.5 or
torch; the pure helpers (step limits, image flip, gripper mapping, wait action, init-state reader)
work without LIBERO.

Protocol, from OpenVLA-OFT ``experiments/robot/libero/run_libero_eval.py`` + ``libero_utils.py``
and openpi ``examples/libero/main.py``:

- ``OffScreenRenderEnv`` at 256x256 with ``env.seed(0)``; per task, 50 trials, trial i starting
  from the task's i-th fixed init state (``env.reset()`` then ``env.set_init_state``).
- 10 wait steps with ``[0, 0, 0, 0, 0, 0, -1]`` so objects settle, then up to the suite's step limit
  (220 spatial, 280 object, 300 goal, 520 libero_10, 400 libero_90: the longest training demo plus
  ~10%). Success is the env's ``done`` (all BDDL goal predicates hold); an exception fails the trial.
- Both images rotated 180 degrees (``img[::-1, ::-1]``) to match the LIBERO training data;
  proprio = eef pos + axis-angle(eef quat) + 2 gripper joints (8-d).
- Chunks run open loop (OFT: all 8; openpi re-plans every 5: ``execute_steps=5``).
- Gripper: robosuite wants -1 open / +1 close. openpi policies (and ours) output that convention;
  OpenVLA/OFT output [0, 1] with 1 = open, which OFT maps to [-1, 1], binarises and inverts.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import logging
import math
import os
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from capvector.errors import unknown_name
from capvector.sim.policy import EpisodeResult, Observation, Policy, as_chunk

log = logging.getLogger(__name__)

LIBERO_HELP = (
    "LIBERO needs robosuite 1.4 and its assets: see README section 'LIBERO evaluation' "
    "(install `libero` in a separate environment with robosuite==1.4.*, and create its "
    "config.yaml pointing at the downloaded assets)"
)

LIBERO_MAX_STEPS: dict[str, int] = {
    "libero_spatial": 220,  # longest training demo: 193 steps
    "libero_object": 280,  # 254
    "libero_goal": 300,  # 270
    "libero_10": 520,  # 505
    "libero_90": 400,  # 373
}
NUM_WAIT_STEPS = 10
WAIT_ACTION = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])
"""No motion, gripper open: what OFT/openpi send while objects settle (``get_libero_dummy_action``)."""
LIBERO_RESOLUTION = 256
LIBERO_CAMERAS = {"agentview": "agentview_image", "robot0_eye_in_hand": "robot0_eye_in_hand_image"}
"""Our camera name -> LIBERO observation key."""

GripperConvention = Literal["close_positive", "open_is_one"]
"""``close_positive``: -1 open / +1 close (robosuite, LIBERO HDF5, openpi, our demos).
``open_is_one``: [0, 1] with 1 = open (OpenVLA/OFT RLDS datasets)."""


def max_steps(suite: str) -> int:
    try:
        return LIBERO_MAX_STEPS[suite]
    except KeyError:
        raise unknown_name("LIBERO suite", suite, LIBERO_MAX_STEPS) from None


def flip_image(image: np.ndarray) -> np.ndarray:
    """Rotate 180 degrees, as OFT's ``get_libero_image``/openpi do (``img[::-1, ::-1]``)."""
    return np.ascontiguousarray(image[::-1, ::-1])


def to_libero_action(action: np.ndarray, convention: GripperConvention) -> np.ndarray:
    """(7,) policy action -> LIBERO/robosuite action with the gripper at exactly -1 or +1.

    ``open_is_one`` follows OFT's ``normalize_gripper_action(binarize=True)`` (g -> sign(2g - 1))
    then ``invert_gripper_action`` (x -1). A gripper value exactly on the threshold opens (OFT
    would send 0, a half-closed command).
    """
    out = np.array(action, dtype=np.float64, copy=True)
    g = out[-1]
    if convention == "close_positive":
        out[-1] = 1.0 if g > 0 else -1.0
    elif convention == "open_is_one":
        out[-1] = 1.0 if 2.0 * g - 1.0 < 0 else -1.0
    else:
        raise ValueError(f"unknown gripper convention {convention!r}")
    return out


def _quat2axisangle(quat_xyzw: np.ndarray) -> np.ndarray:
    # robosuite.utils.transform_utils.quat2axisangle (identical in 1.4 and 1.5), used by OFT/openpi.
    w = min(max(float(quat_xyzw[3]), -1.0), 1.0)
    den = math.sqrt(1.0 - w * w)
    if math.isclose(den, 0.0):
        return np.zeros(3)
    return np.asarray(quat_xyzw[:3], dtype=np.float64) * 2.0 * math.acos(w) / den


def libero_proprio(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """(8,) float32: eef pos, axis-angle of the eef quaternion, 2 gripper joints."""
    return np.concatenate(
        [
            np.asarray(obs["robot0_eef_pos"], dtype=np.float64),
            _quat2axisangle(np.asarray(obs["robot0_eef_quat"])),
            np.asarray(obs["robot0_gripper_qpos"], dtype=np.float64),
        ]
    ).astype(np.float32)


def libero_observation(obs: Mapping[str, np.ndarray], instruction: str) -> Observation:
    """A LIBERO env observation as our policy :class:`Observation` (images rotated 180°)."""
    images = {cam: flip_image(obs[key]) for cam, key in LIBERO_CAMERAS.items()}
    return {"images": images, "proprio": libero_proprio(obs), "instruction": instruction}


# --- fixed init states -------------------------------------------------------------------------

_SAFE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("_codecs", "encode"),
}
_TORCH_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and plain Python values, nothing that could run code."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _SAFE_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(
            f"init-state file references {module}.{name}; only numpy arrays are allowed"
        )

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError(
            "init-state file holds torch tensors, not a numpy array; convert it with "
            "torch.load(path, weights_only=False).numpy() in a trusted environment"
        )


def load_init_states(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a LIBERO ``.pruned_init`` file: (N, D) float64 flattened sim states, one per trial.

    The files are ``torch.save`` d numpy arrays. Upstream LIBERO calls ``torch.load``, which
    refuses them on torch >= 2.6 (weights_only=True by default). This reads both torch formats
    (zip and legacy) without torch, through an unpickler that only admits numpy arrays.
    """
    path = Path(path)
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if n.endswith("data.pkl")]
            if not names:
                raise ValueError(f"{path} is a zip but not a torch.save file (no data.pkl)")
            with zf.open(names[0]) as fh:
                value = _NumpyOnlyUnpickler(fh).load()
    else:
        with open(path, "rb") as fh:
            value = _NumpyOnlyUnpickler(fh).load()
            if isinstance(value, int) and value == _TORCH_LEGACY_MAGIC:
                _NumpyOnlyUnpickler(fh).load()  # protocol version
                _NumpyOnlyUnpickler(fh).load()  # sys info
                value = _NumpyOnlyUnpickler(fh).load()
    states = np.asarray(value)
    if states.ndim != 2:
        raise ValueError(f"{path}: expected (trials, state_dim) init states, got {states.shape}")
    return states


# --- everything below needs LIBERO -------------------------------------------------------------


def libero_config_file() -> Path:
    """Where LIBERO reads its paths from (it prompts with input() when the file is missing)."""
    root = os.environ.get("LIBERO_CONFIG_PATH", os.path.expanduser("~/.libero"))
    return Path(root) / "config.yaml"


def import_libero() -> tuple[Any, Any, Any]:
    """``(benchmark, get_libero_path, OffScreenRenderEnv)`` from LIBERO, or an ImportError that
    says what is missing. Checks before importing, because importing LIBERO without its config
    blocks on an interactive prompt."""
    if importlib.util.find_spec("libero") is None:
        raise ImportError(f"{LIBERO_HELP}; the `libero` package is not installed")
    try:
        version = importlib.metadata.version("robosuite")
    except importlib.metadata.PackageNotFoundError:
        version = "none"
    if not version.startswith("1.4"):
        raise ImportError(f"{LIBERO_HELP}; found robosuite {version}")
    config = libero_config_file()
    if not config.is_file():
        raise ImportError(f"{LIBERO_HELP}; no LIBERO config at {config}")
    try:
        from libero.libero import benchmark, get_libero_path
        from libero.libero.envs import OffScreenRenderEnv
    except ImportError as e:
        raise ImportError(f"{LIBERO_HELP}; importing it failed: {e}") from e
    return benchmark, get_libero_path, OffScreenRenderEnv


class LiberoSuite:
    """A LIBERO task suite: its tasks, their envs (256 px, seeded 0) and fixed init states."""

    def __init__(self, suite: str, *, resolution: int = LIBERO_RESOLUTION, env_seed: int = 0):
        self.name = suite
        self.max_steps = max_steps(suite)
        self.resolution = resolution
        self.env_seed = env_seed
        benchmark, self._get_path, self._env_cls = import_libero()
        self._suite = benchmark.get_benchmark_dict()[suite]()

    @property
    def num_tasks(self) -> int:
        return int(self._suite.n_tasks)

    def instruction(self, task_id: int) -> str:
        return str(self._suite.get_task(task_id).language)

    def make_env(self, task_id: int) -> Any:
        task = self._suite.get_task(task_id)
        bddl = os.path.join(self._get_path("bddl_files"), task.problem_folder, task.bddl_file)
        env = self._env_cls(
            bddl_file_name=bddl, camera_heights=self.resolution, camera_widths=self.resolution
        )
        # OFT: "seed seems to affect object positions even when using fixed initial state".
        env.seed(self.env_seed)
        return env

    def init_states(self, task_id: int) -> np.ndarray:
        task = self._suite.get_task(task_id)
        return load_init_states(
            os.path.join(self._get_path("init_states"), task.problem_folder, task.init_states_file)
        )


def run_libero_episode(
    policy: Policy,
    env: Any,
    instruction: str,
    init_state: np.ndarray,
    *,
    max_steps: int,
    gripper_convention: GripperConvention = "close_positive",
    execute_steps: int | None = None,
    video: bool = False,
    trial: int = 0,
    task: str = "",
) -> EpisodeResult:
    """One trial: reset, load ``init_state``, wait 10 steps, then run chunks until done/limit.

    Simulator exceptions fail the trial (as in OFT/openpi); a policy returning a wrong shape
    raises, since that is a bug rather than a failed trial.
    """
    frames: list[np.ndarray] | None = [] if video else None
    steps = 0

    def finish(success: bool, reason: str | None) -> EpisodeResult:
        if reason is not None and not reason.startswith("step limit"):
            log.warning("LIBERO %s trial %d: %s", task, trial, reason)
        return EpisodeResult(success, steps, reason, frames, trial, task, "Panda")

    try:
        env.reset()
        obs = env.set_init_state(init_state)
        for _ in range(NUM_WAIT_STEPS):
            obs, _, _, _ = env.step(WAIT_ACTION.tolist())
    except Exception as e:
        return finish(False, f"{type(e).__name__} during reset: {e}")
    while steps < max_steps:
        observation = libero_observation(obs, instruction)
        if frames is not None:
            frames.append(np.concatenate(list(observation["images"].values()), axis=1))
        chunk = as_chunk(policy(observation))
        if execute_steps is not None:
            chunk = chunk[:execute_steps]
        for action in chunk:
            if not np.all(np.isfinite(action)):
                return finish(False, f"non-finite action at step {steps}: {action.tolist()}")
            try:
                obs, _, done, _ = env.step(to_libero_action(action, gripper_convention).tolist())
            except Exception as e:
                return finish(False, f"{type(e).__name__} at step {steps}: {e}")
            steps += 1
            if done:
                return finish(True, None)
            if steps >= max_steps:
                break
    return finish(False, f"step limit ({max_steps}) reached")


def run_libero_suite(
    policy: Policy,
    suite: str,
    *,
    trials_per_task: int = 50,
    tasks: list[int] | None = None,
    gripper_convention: GripperConvention = "close_positive",
    execute_steps: int | None = None,
    videos_per_task: int = 0,
) -> list[EpisodeResult]:
    """The OFT/openpi protocol over a suite: ``trials_per_task`` fixed init states per task."""
    libero = LiberoSuite(suite)
    results = []
    for task_id in tasks if tasks is not None else range(libero.num_tasks):
        env = libero.make_env(task_id)
        instruction = libero.instruction(task_id)
        states = libero.init_states(task_id)
        if trials_per_task > len(states):
            raise ValueError(
                f"{suite} task {task_id} has {len(states)} init states, {trials_per_task} asked"
            )
        for trial in range(trials_per_task):
            results.append(
                run_libero_episode(
                    policy,
                    env,
                    instruction,
                    states[trial],
                    max_steps=libero.max_steps,
                    gripper_convention=gripper_convention,
                    execute_steps=execute_steps,
                    video=trial < videos_per_task,
                    trial=trial,
                    task=f"{suite}/{task_id}",
                )
            )
        env.close()
    return results
