"""robosuite 1.5 environments: the task table, env construction, observations and fast rendering.

Facts this module relies on (measured on the project's 2-core CPU machines, see
``research/toy_benchmark_feasibility.md`` and ``research/merging_orth_eval.md`` §C1):

- The env is built with ``has_offscreen_renderer=False, use_camera_obs=False, ignore_done=True``;
  images come from our own :class:`CameraRenderer` on the env's raw ``MjModel``/``MjData``. It
  costs a fraction of robosuite's camera observables and only runs when a caller asks for pixels.
- ``hard_reset=False``: a reset reuses the compiled model (no XML rebuild, no new GL context),
  so one env and one renderer serve any number of episodes. Model-construction randomness (Lift
  draws its cube size when the model is built) is fixed by ``seed=0`` in the make kwargs; episode
  randomness (object placement, joint noise) is reseeded on every :meth:`SimEnv.reset`.
- Success is ``env._check_success()`` after every step: robosuite's ``done`` only marks the horizon.
- ``fast_step`` (the default) leaves out of robosuite's step what changes nothing we read: the
  controller substeps between policy actions run through :mod:`capvector.envs.robosuite.fast_control`
  (robosuite's arithmetic without its per-call overhead: identical controls), and only the
  observables :class:`SimEnv` reads are computed. States and observations are identical to
  robosuite's full step (``tests/test_fast_control.py``); ``fast_step=False`` runs the full step.
"""

from __future__ import annotations

import atexit
import contextlib
import copy
import logging
import math
import os
import weakref
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import Any

# MuJoCo picks its OpenGL backend from MUJOCO_GL when `mujoco` is first imported and defaults to
# GLFW, which needs a display. Our machines are headless (and may have no GPU: EGL then runs on
# Mesa's software rasteriser), so default to EGL before mujoco is imported here. robosuite forces
# EGL too, but only at its own import and only when the variable is not osmesa/glx; a user who
# exports MUJOCO_GL=osmesa keeps it. Set here, not at package import, so that only code that
# builds a simulator changes the process environment.
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from capvector.errors import CapVectorError, missing_extra, unknown_name  # noqa: E402

try:
    import mujoco
except ImportError as err:  # training from files needs no simulator; this module does
    raise missing_extra("the simulator", "sim", err) from err
from capvector.envs.robosuite.tasks import TASKS, TaskSpec, get_task  # noqa: E402,F401 (re-exported)

# robosuite logs five notices at import and one per controller load; none applies to us (no
# private macro file is needed, robosuite_models and mink only matter for GR1/humanoids).
_ROBOSUITE_NOISE = (
    "No private macro file found",
    "It is recommended to use a private macro file",
    "To setup, run:",
    "Could not import robosuite_models",
    "Could not load the mink-based whole-body IK",
    "Loading controller configuration from",
)


class _DropRobosuiteNoise(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(_ROBOSUITE_NOISE)


def _import_robosuite() -> ModuleType:
    # The filter must sit on robosuite's logger before `import robosuite` emits the notices.
    logger = logging.getLogger("robosuite_logs")
    if not any(isinstance(f, _DropRobosuiteNoise) for f in logger.filters):
        logger.addFilter(_DropRobosuiteNoise())
    try:
        import robosuite
    except ImportError as err:
        raise missing_extra("the simulator", "sim", err) from err

    return robosuite


suite = _import_robosuite()
from robosuite.utils.transform_utils import quat2axisangle  # noqa: E402  (needs the filter first)

from capvector.envs.robosuite.fast_control import install as install_fast_control  # noqa: E402

log = logging.getLogger(__name__)

DEFAULT_CAMERAS: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
DEFAULT_IMAGE_SIZE = 64
ACTION_DIM = 7
"""OSC_POSE delta (dx, dy, dz, drx, dry, drz) in [-1, 1] + gripper (-1 open, +1 close)."""

PROPRIO_KEYS: tuple[str, ...] = ("robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos")
"""The 8-d proprio, as in OpenVLA-OFT/openpi LIBERO: eef position, axis-angle, 2 finger joints."""


# Model bugs of robosuite 1.5.2 that stop our controllers, patched after the model is built
# (and recorded in the demo files' `model_fixes` attr): robot -> [(geom, what was done and why)].
MODEL_FIXES: dict[str, list[tuple[str, str]]] = {
    "Sawyer": [
        (
            "robot0_base_col",
            "contacts disabled: at rest it touches robot0_link0_collision, which joint 0 turns; "
            "the contact's friction stalls the arm's sideways (y) motion ~1 cm short of the goal",
        )
    ],
}


def _check_robot(robot: str, gripper: str | None) -> None:
    """A robot and gripper robosuite knows, the robot with one arm (robosuite's own failures are
    an assertion and a KeyError deep in ``suite.make``)."""
    from robosuite.models.grippers import GRIPPER_MAPPING
    from robosuite.models.robots.robot_model import REGISTERED_ROBOTS
    from robosuite.robots import ROBOT_CLASS_MAPPING

    def one_arm(name: str) -> bool:
        return name in REGISTERED_ROBOTS and list(REGISTERED_ROBOTS[name]().arms) == ["right"]

    if robot not in ROBOT_CLASS_MAPPING or not one_arm(robot):
        known = [name for name in ROBOT_CLASS_MAPPING if one_arm(name)]
        if robot in ROBOT_CLASS_MAPPING:
            raise CapVectorError(
                f"robot {robot!r} has more than one arm; use one of {', '.join(known)}"
            )
        raise unknown_name("one-arm robot", robot, known)
    if gripper is not None and gripper not in GRIPPER_MAPPING:
        raise unknown_name("gripper", gripper, [name for name in GRIPPER_MAPPING if name])


def camera_intrinsics(fovy_degrees: float, height: int, width: int | None = None) -> np.ndarray:
    """(3, 3) pinhole intrinsics in pixels for a MuJoCo camera with vertical field of view ``fovy``.

    Same convention as robosuite's ``camera_utils.get_camera_intrinsic_matrix``: square pixels
    (MuJoCo's fovy is vertical), principal point at (W/2, H/2) in continuous pixel coordinates
    where pixel (i, j) covers [j, j+1) x [i, i+1), rows counted from the top of the upright image.
    """
    width = height if width is None else width
    f = 0.5 * height / math.tan(math.radians(fovy_degrees) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


class SimulationFault(RuntimeError):
    """The simulator went wrong in this episode (instability, NaN, exception); the env survives."""


# MuJoCo's own instability signals; it auto-resets the data after BADQACC, so a finite state alone
# does not prove the step was fine.
_FAULT_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADCTRL,
)


def _gl_context_class() -> type:
    # mujoco.gl_context binds its backend when mujoco is first imported, which may have happened
    # before capvector.envs set MUJOCO_GL (e.g. `import mujoco` at the top of a script): it then
    # picks GLFW and fails without a display. Choosing the backend here, from the variable as it
    # is now, makes rendering independent of import order.
    backend = os.environ.get("MUJOCO_GL", "egl").lower()
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    elif backend in ("glfw", "glx"):
        from mujoco.glfw import GLContext
    else:
        raise CapVectorError(
            f"MUJOCO_GL={backend!r}: CameraRenderer supports egl (default), osmesa and glfw"
        )
    return GLContext


_live_renderers: weakref.WeakSet[CameraRenderer] = weakref.WeakSet()


def _close_renderers() -> None:
    for renderer in list(_live_renderers):
        renderer.close()


def _track(renderer: CameraRenderer) -> None:
    # mujoco.egl registers eglTerminate with atexit when it creates the first context; contexts
    # still alive after that make PyOpenGL raise from __del__ at exit. atexit runs the last
    # registered hook first, so registering ours after the first context frees them in time.
    if not _live_renderers:
        atexit.unregister(_close_renderers)
        atexit.register(_close_renderers)
    _live_renderers.add(renderer)


class CameraRenderer:
    """Renders fixed cameras of a MuJoCo model, upright, at the cost of one GPU/llvmpipe readback.

    All cameras are drawn side by side into one offscreen buffer and read back with a single
    ``mjr_readPixels``; depth, when asked, comes from the same pass (no second render as
    ``mujoco.Renderer`` needs). Shadows and reflections are off and only geom group 1 (robosuite's
    visual meshes) is drawn: group 0 holds the collision geoms, which would paint the robot blue.
    Multisampling is off (MuJoCo's default is 4 samples): it renders ~35% faster on llvmpipe, and
    depth read back from a multisampled buffer comes out ~0.35% short (3 mm at 0.8 m), whereas
    without it depth equals ray-cast distances to 1e-7 m. With ``msaa_samples=4`` edges are
    anti-aliased, at that price.

    On Mesa's software rasteriser a 64 px frame costs what its triangles cost: robosuite's arm
    meshes hold ~170k of them, most outside a given camera's view (the wrist camera sees two
    fingers; the zoomed agentview misses the upper arm and the pedestal). ``cull=True`` drops every
    geom whose bounding sphere lies wholly outside the camera's view frustum before drawing; the
    picture is unchanged (no shadows or reflections are drawn that could come from such a geom).
    Skybox and haze are off too: no default camera of our tasks sees the sky. ``geom_groups``
    are the geom groups drawn (LIBERO's fast rendering adds robosuite's marker group 2).
    ``shadows`` and ``reflections`` turn MuJoCo's on (each light's shadow map, mirrors drawn with
    the scene a second time); a culled geom casts no shadow and shows in no mirror.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        cameras: Sequence[str],
        size: int,
        *,
        depth: bool = False,
        msaa_samples: int = 0,
        cull: bool = True,
        geom_groups: Sequence[int] = (1,),
        shadows: bool = False,
        reflections: bool = False,
    ) -> None:
        if not cameras:
            raise ValueError("CameraRenderer needs at least one camera")
        self._gl: Any = None
        self._ctx: mujoco.MjrContext | None = None
        self.model = model
        self.cameras = tuple(cameras)
        self.size = size
        self.depth = depth
        self.cull = cull
        known = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
        self._cams = []
        for name in self.cameras:
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            if cam_id < 0:
                raise CapVectorError(
                    f"camera {name!r} is not in the model; it has: {', '.join(known)}"
                )
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = cam_id
            self._cams.append(cam)
        width = size * len(self.cameras)
        # The offscreen framebuffer is sized from the model when the context is made.
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, size)
        model.vis.quality.offsamples = msaa_samples
        self._gl = _gl_context_class()(width, size)
        _track(self)
        self._gl.make_current()
        self._ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._ctx)
        # Reversed-Z float depth, as mujoco.Renderer sets it (precise over the whole range).
        self._ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=2000)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(shadows)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(reflections)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        self._scene.flags[mujoco.mjtRndFlag.mjRND_HAZE] = 0
        # Bounding-sphere radius per model geom; planes (rbound 0: infinite) are never culled.
        self._rbound = np.where(
            model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE, np.inf, model.geom_rbound
        )
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = 0
        self._option.geomgroup[list(geom_groups)] = 1
        self._full = mujoco.MjrRect(0, 0, width, size)
        self._rects = [mujoco.MjrRect(i * size, 0, size, size) for i in range(len(self.cameras))]
        self._rgb = np.empty((size, width, 3), dtype=np.uint8)
        self._zbuf = np.empty((size, width), dtype=np.float32) if depth else None

    def render(
        self, data: mujoco.MjData
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
        """Images ``{camera: (H, W, 3) uint8}`` upright, and depth ``{camera: (H, W) float32}``
        in metres along the optical axis (None unless built with ``depth=True``)."""
        if self._ctx is None:
            raise RuntimeError("CameraRenderer.render called after close()")
        self._gl.make_current()
        for cam, rect in zip(self._cams, self._rects, strict=True):
            mujoco.mjv_updateScene(
                self.model,
                data,
                self._option,
                None,
                cam,
                mujoco.mjtCatBit.mjCAT_ALL.value,
                self._scene,
            )
            if self.cull:
                self._cull(cam.fixedcamid, data)
            mujoco.mjr_render(rect, self._scene, self._ctx)
        mujoco.mjr_readPixels(self._rgb, self._zbuf, self._full, self._ctx)
        # OpenGL rows start at the bottom: flip once here so every image we hand out is upright.
        rgb = self._rgb[::-1]
        s = self.size
        images = {
            name: np.ascontiguousarray(rgb[:, i * s : (i + 1) * s])
            for i, name in enumerate(self.cameras)
        }
        if self._zbuf is None:
            return images, None
        metres = self._linear_depth(self._zbuf[::-1])
        depth = {
            name: np.ascontiguousarray(metres[:, i * s : (i + 1) * s])
            for i, name in enumerate(self.cameras)
        }
        return images, depth

    def _cull(self, cam_id: int, data: mujoco.MjData) -> int:
        """Mark scene geoms wholly outside camera ``cam_id``'s frustum as not drawn; the count."""
        geoms = [g for g in self._scene.geoms[: self._scene.ngeom]]
        index = [i for i, g in enumerate(geoms) if g.objtype == mujoco.mjtObj.mjOBJ_GEOM]
        if not index:
            return 0
        centres = np.array([geoms[i].pos for i in index])
        radius = self._rbound[[geoms[i].objid for i in index]]
        # Camera frame: x right, y up, looking down -z (MuJoCo). Square viewport: the horizontal
        # half-angle equals the vertical one, fovy / 2.
        local = (centres - data.cam_xpos[cam_id]) @ data.cam_xmat[cam_id].reshape(3, 3)
        ahead = -local[:, 2]
        tan = math.tan(math.radians(self.model.cam_fovy[cam_id]) / 2)
        # Distance from a slanted side plane, scaled by its normal's length sqrt(1 + tan^2).
        slack = radius * math.sqrt(1 + tan * tan)
        outside = (ahead < -radius) | (np.abs(local[:, :2]).max(axis=1) - tan * ahead > slack)
        for i in np.asarray(index)[outside]:
            geoms[i].type = mujoco.mjtGeom.mjGEOM_NONE  # mjr_render skips it
        return int(outside.sum())

    def _linear_depth(self, zbuf: np.ndarray) -> np.ndarray:
        # Undo the reversed-Z projection with the model's clip planes (znear/zfar are fractions of
        # the model extent). Same arithmetic as mujoco/rendering/classic/renderer.py (3.3-3.9):
        # float32 glFrustum coefficients, then float64 for the division.
        extent = self.model.stat.extent
        znear = np.float32(self.model.vis.map.znear * extent)
        zfar = np.float32(self.model.vis.map.zfar * extent)
        c = -(zfar + znear) / (zfar - znear)
        d = -(np.float32(2) * zfar * znear) / (zfar - znear)
        c = np.float32(-0.5) * c - np.float32(0.5)
        d = np.float32(-0.5) * d
        return (d / (zbuf.astype(np.float64) + c)).astype(np.float32)

    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        if self._ctx is not None:
            self._gl.make_current()
            self._ctx.free()
            self._ctx = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __del__(self) -> None:
        # At interpreter exit EGL may already be torn down; freeing then raises inside PyOpenGL.
        with contextlib.suppress(Exception):
            self.close()


def proprio_from(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """The (8,) float32 proprio of a low-dim observation: eef pos, axis-angle, finger joints."""
    return np.concatenate([np.asarray(obs[k], dtype=np.float32) for k in PROPRIO_KEYS])


class SimEnv:
    """One robosuite task on one arm, with deterministic seeded resets and optional cameras.

    ``observation`` is the low-dim state after the last reset/step: ``robot0_eef_pos`` (3,),
    ``robot0_eef_quat`` (4,) xyzw, ``robot0_eef_axis_angle`` (3,), ``robot0_gripper_qpos`` (2,),
    the task's object positions (e.g. ``cube_pos``) and quaternions (e.g. ``cube_quat``, xyzw).
    ``robot0_eef_quat`` is robosuite's eef *body* quaternion in the world frame, the key the
    LIBERO/OFT datasets take the axis-angle proprio from. ``fast_step=False`` runs robosuite's
    full step instead of the fast one (the same states and observations; see the module
    docstring); ``fast_control`` says whether the lean controller substeps are installed.
    """

    def __init__(
        self,
        task: str,
        robot: str = "Panda",
        *,
        gripper: str | None = None,
        cameras: Sequence[str] = DEFAULT_CAMERAS,
        image_size: int = DEFAULT_IMAGE_SIZE,
        depth: bool = False,
        camera_fovy: Mapping[str, float] | None = None,
        msaa_samples: int = 0,
        fast_step: bool = True,
    ) -> None:
        self.task = task
        self.spec = get_task(task)
        self.randomizer: Any = None
        """The scene variant's ``SceneRandomizer`` applied after each reset (evaluation sets it)."""
        _check_robot(robot, gripper)
        self.robot = robot
        self.gripper = gripper
        self.cameras = tuple(cameras)
        self.image_size = image_size
        self.depth = depth
        self.env_kwargs = self._make_kwargs()
        self.env = suite.make(self.spec.env_name, **copy.deepcopy(self.env_kwargs))
        self.fast_control = fast_step and install_fast_control(self.env)
        if fast_step:
            self._compute_only_read_observables()
        self.seed: int | None = None
        self.steps = 0
        self._renderer: CameraRenderer | None = None
        model = self.env.sim.model._model
        self.model_fixes: dict[str, str] = {}
        for geom, why in MODEL_FIXES.get(robot, []):
            geom_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
            if geom_id >= 0:
                model.geom_contype[geom_id] = 0
                model.geom_conaffinity[geom_id] = 0
                self.model_fixes[geom] = why
        self.observation = self._lowdim(self.env.reset())
        self.camera_fovy: dict[str, float] = {}
        try:
            self._check_and_set_cameras(model, camera_fovy)
            n_fingers = self.observation["robot0_gripper_qpos"].shape[0]
            if n_fingers != 2:
                grip = type(self.env.robots[0].gripper["right"]).__name__
                raise CapVectorError(
                    f"{robot} with {grip} has {n_fingers} finger joints, but the 8-d proprio "
                    "(eef pos + axis-angle + 2 finger joints) needs a gripper with two: pass "
                    "gripper='PandaGripper' (CLI: --gripper PandaGripper) or 'RethinkGripper'"
                )
            if self.cameras:
                self._renderer = CameraRenderer(
                    model, self.cameras, image_size, depth=depth, msaa_samples=msaa_samples
                )
        except Exception:
            self.close()
            raise

    def _make_kwargs(self) -> dict[str, Any]:
        """The ``robosuite.make`` kwargs (JSON-serialisable) of this task, robot and cameras.

        These go verbatim into the HDF5 ``env_args`` so robomimic-style readers rebuild the same
        env. The camera entries describe what we render ourselves; robosuite's own camera
        observables stay off (``use_camera_obs=False``).
        """
        robot = self.robot
        # robosuite 1.5 "BASIC" composite controller = OSC_POSE delta for the arm, input range ±1,
        # 0.05 m / 0.5 rad per step, input_ref_frame "base"; the same 7-d action on every arm.
        controller = suite.load_composite_controller_config(controller="BASIC", robot=robot)
        # basic.json also configures left arm, torso, head, base and legs; a single arm only has
        # the "right" part, and robosuite warns about each missing part on every reset.
        parts = controller.get("body_parts", {})
        if "right" not in parts:
            raise CapVectorError(
                f"robosuite's BASIC controller config has no right arm for {robot!r}"
            )
        controller["body_parts"] = {"right": parts["right"]}
        kwargs: dict[str, Any] = {
            "robots": robot,
            "controller_configs": controller,
            "has_renderer": False,
            "has_offscreen_renderer": False,
            "use_camera_obs": False,
            "use_object_obs": True,
            "ignore_done": True,
            "hard_reset": False,
            "reward_shaping": False,
            "control_freq": 20,
            "seed": 0,
            "camera_names": list(self.cameras),
            "camera_heights": self.image_size,
            "camera_widths": self.image_size,
            "camera_depths": self.depth,
        }
        if self.gripper is not None:
            kwargs["gripper_types"] = self.gripper
        return kwargs

    def _check_and_set_cameras(
        self, model: mujoco.MjModel, camera_fovy: Mapping[str, float] | None
    ) -> None:
        def camera_id(name: str, what: str) -> int:
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            if cam_id < 0:
                known = [
                    mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i)
                    for i in range(model.ncam)
                ]
                raise CapVectorError(
                    f"{what} {name!r} is not in {self.task}; it has {', '.join(known)}"
                )
            return cam_id

        for name, fovy in {**self.spec.camera_fovy, **(camera_fovy or {})}.items():
            model.cam_fovy[camera_id(name, "camera_fovy names camera")] = fovy
        for name in self.cameras:
            self.camera_fovy[name] = float(model.cam_fovy[camera_id(name, "camera")])

    def _compute_only_read_observables(self) -> None:
        # robosuite updates every observable on every substep and samples all of them once per
        # control step (joint sines and cosines, accelerations, relative positions, ...); we read
        # only what _lowdim reads. Disabled observables stay disabled across (soft) resets.
        read = {"robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"}
        read |= {*self.spec.objects, *self.spec.orientations}
        for name in self.env._observables:
            if name not in read:
                self.env.modify_observable(name, "enabled", False)

    @property
    def instruction(self) -> str:
        return self.spec.instruction

    @property
    def max_steps(self) -> int:
        return self.spec.max_steps

    def intrinsics(self) -> dict[str, np.ndarray]:
        """``{camera: (3, 3)}`` pinhole intrinsics of the rendered images (after fovy overrides)."""
        return {
            name: camera_intrinsics(fovy, self.image_size)
            for name, fovy in self.camera_fovy.items()
        }

    def reset(self, seed: int) -> dict[str, np.ndarray]:
        """Reset to the initial state drawn from ``seed`` (same seed, same state, in any env)."""
        # Reseed in place: the placement samplers and robot reset hold this very Generator.
        self.env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
        self.observation = self._lowdim(self.env.reset())
        self.seed = seed
        self.steps = 0
        return self.observation

    def step(self, action: np.ndarray) -> float:
        """Execute one 7-d action; returns the reward. Raises :class:`SimulationFault`."""
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (ACTION_DIM,):
            raise ValueError(f"action must have {ACTION_DIM} values, got shape {np.shape(action)}")
        if not np.all(np.isfinite(a)):
            raise SimulationFault(f"non-finite action {a.tolist()}")
        data = self.env.sim.data._data
        before = [data.warning[w].number for w in _FAULT_WARNINGS]
        try:
            raw, reward, _, _ = self.env.step(a)
        except Exception as e:  # robosuite/MuJoCo errors; the env is reset by the next reset()
            raise SimulationFault(f"step raised {type(e).__name__}: {e}") from e
        for w, n in zip(_FAULT_WARNINGS, before, strict=True):
            if data.warning[w].number > n:
                raise SimulationFault(
                    f"MuJoCo {mujoco.mjtWarning(w).name} (unstable simulation) at t={data.time:.3f}s"
                )
        if not (np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))):
            raise SimulationFault("non-finite qpos/qvel")
        self.steps += 1
        self.observation = self._lowdim(raw)
        return float(reward)

    def finger_axis(self) -> np.ndarray:
        """(3,) unit vector from the right to the left fingerpad (the direction the fingers close
        along), from the gripper's ``important_geoms``; experts use it to choose a grasp yaw."""
        gripper = self.env.robots[0].gripper["right"]
        data, model = self.env.sim.data, self.env.sim.model
        pads = [gripper.important_geoms[f"{side}_fingerpad"][0] for side in ("left", "right")]
        left, right = (data.geom_xpos[model.geom_name2id(name)] for name in pads)
        axis = np.asarray(left - right, dtype=np.float64)
        return axis / np.linalg.norm(axis)

    def success(self) -> bool:
        return bool(self.env._check_success())

    def proprio(self) -> np.ndarray:
        """(8,) float32: eef pos, eef axis-angle, finger joints (same as the demos)."""
        return proprio_from(self.observation)

    def render(self) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
        """Upright images and optional depth of the current state; see :class:`CameraRenderer`."""
        if self._renderer is None:
            raise RuntimeError("this SimEnv was built without cameras")
        return self._renderer.render(self.env.sim.data._data)

    def flat_state(self) -> np.ndarray:
        """robosuite/robomimic flattened sim state: [time, qpos, qvel]."""
        return np.asarray(self.env.sim.get_state().flatten(), dtype=np.float64)

    def model_xml(self) -> str:
        return self.env.sim.model.get_xml()

    def env_args(self) -> dict[str, Any]:
        """robomimic ``env_args``: env_name, type 1 (robosuite), env_version, env_kwargs."""
        return {
            "env_name": self.spec.env_name,
            "type": 1,
            "env_version": suite.__version__,
            "env_kwargs": copy.deepcopy(self.env_kwargs),
        }

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self.env.close()

    def _lowdim(self, raw: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        quat = np.array(raw["robot0_eef_quat"], dtype=np.float64)
        obs = {
            "robot0_eef_pos": np.array(raw["robot0_eef_pos"], dtype=np.float64),
            "robot0_eef_quat": quat,
            # quat2axisangle clips its argument in place, hence the copy.
            "robot0_eef_axis_angle": np.asarray(quat2axisangle(quat.copy()), dtype=np.float64),
            "robot0_gripper_qpos": np.array(raw["robot0_gripper_qpos"], dtype=np.float64),
        }
        extra = self.spec.extra_positions(self.env) if self.spec.extra_positions else {}
        for key in self.spec.objects:
            obs[key] = np.array(extra[key] if key in extra else raw[key], dtype=np.float64)
        for key in self.spec.orientations:
            obs[key] = np.array(raw[key], dtype=np.float64)
        return obs
