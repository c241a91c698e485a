"""robosuite's controller substeps at a fraction of their cost, with the same controls to the bit.

robosuite 1.5 runs its controllers in Python on every 2 ms physics substep, 25 per 20 Hz control
step, and that is most of an evaluation's time. Per substep it recomputes the action limits three
times (only to assert the action's length), looks sites up by name, calls ``mj_jacSite`` six times
where one call gives what it uses, and recomputes the base pose, the goal in the world frame and
the base's velocity, none of which can change between two policy actions for an arm whose base is
welded to the world.

:func:`install` replaces one env's ``_pre_action``. The first substep of a control step
(``policy_step=True``: robosuite sets the controller goals and pushes its proprio buffers) still
runs robosuite's own code, after which the base pose, world-frame goal and base velocity are taken
once. The other 24 substeps run the arithmetic of robosuite 1.5.2's
``OperationalSpaceController.update`` and ``run_controller``, ``SimpleGripController.
run_controller`` and ``FixedBaseRobot.control``'s clipping: the same numpy expressions on arrays of
the same layout, and robosuite's own numba kernels (``opspace_matrices``, ``orientation_error``,
``nullspace_torques``). The controls written to ``data.ctrl`` and the controllers' state are
identical; ``tests/test_fast_control.py`` compares whole trajectories with robosuite's full step.

The substeps follow the env across hard resets (robosuite then builds a new model, data and
robot; LIBERO resets that way). Only what we build is covered: one fixed-base arm with an
``OSC_POSE`` controller without interpolators and a ``GRIP`` gripper controller
(``SimEnv``'s BASIC config; LIBERO's Panda has the same). Anything else keeps
robosuite's code: :func:`supported` says why, and :func:`install` returns False.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from capvector.errors import missing_extra

try:
    import mujoco
    from robosuite.controllers.parts.arm.osc import OperationalSpaceController
    from robosuite.controllers.parts.gripper.simple_grip import SimpleGripController
    from robosuite.robots.fixed_base_robot import FixedBaseRobot
    from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error
except ImportError as err:
    raise missing_extra("the simulator", "sim", err) from err

__all__ = ["install", "supported"]


class _FastSubsteps:
    """``env._pre_action`` with robosuite's own code on policy steps and the lean path between."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.original = type(env)._pre_action.__get__(env)
        self._bind_sim()

    def _bind_sim(self) -> None:
        # A hard reset (LIBERO's default: robosuite rebuilds the model from its XML) makes a new
        # model, data and robot: everything below is taken from the env as it is now.
        env = self.env
        robot = env.robots[0]
        self.robot = robot
        self.arm_name = robot.arms[0]
        self.gripper_name = robot.get_gripper_name(self.arm_name)
        self.model = env.sim.model._model
        self.data = env.sim.data._data
        actuators = robot._ref_actuators_indexes_dict
        arm_actuators = _as_index(actuators[self.arm_name])
        ctrlrange = self.model.actuator_ctrlrange[arm_actuators]
        self.arm_clip = (arm_actuators, ctrlrange[..., 0].copy(), ctrlrange[..., 1].copy())
        self.gripper_actuators = _as_index(actuators[self.gripper_name])
        self.arm: OperationalSpaceController | None = None
        self._bind_controllers()
        self.ref_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, self.arm.ref_name)
        self.center_site = _base_site(self.model, self.arm)
        nv = self.model.nv
        self._jacp, self._jacr = np.zeros((3, nv)), np.zeros((3, nv))
        self._mass_matrix = np.zeros((nv, nv))

    def _bind_controllers(self) -> None:
        # A robot's reset builds new controller objects: bind them again when they changed.
        arm = self.robot.part_controllers[self.arm_name]
        if arm is self.arm:
            return
        self.arm = arm
        self.gripper: SimpleGripController = self.robot.part_controllers[self.gripper_name]
        self.arm_qpos = _as_index(arm.qpos_index)
        self.arm_qvel = _as_index(arm.qvel_index)
        self.arm_block = _block(self.arm_qvel)
        self.gripper_qpos = _as_index(self.gripper.qpos_index)
        self.gripper_qvel = _as_index(self.gripper.qvel_index)

    def __call__(self, action: Any, policy_step: bool = False) -> None:
        if policy_step:
            self.original(action, policy_step=True)
            if self.env.sim.model._model is not self.model:
                self._bind_sim()
            self._bind_controllers()
            # The gripper's clipped output robosuite has just written holds until the next action.
            self.gripper_ctrl = self.data.ctrl[self.gripper_actuators].copy()
            self._hold_goal()
            return
        data = self.data
        # FixedBaseRobot.control clips each part's output to its ctrlrange (np.clip; the minimum of
        # the maximum is the same values at less cost).
        index, low, high = self.arm_clip
        data.ctrl[index] = np.minimum(np.maximum(self._arm_torques(self.arm), low), high)
        # SimpleGripController.run_controller: its update, then its output, which is what
        # robosuite computed and wrote on the policy step: the gripper's goal has not changed.
        gripper = self.gripper
        gripper.joint_pos = data.qpos[self.gripper_qpos].copy()
        gripper.joint_vel = data.qvel[self.gripper_qvel].copy()
        gripper.new_update = True
        data.ctrl[self.gripper_actuators] = self.gripper_ctrl

    def _hold_goal(self) -> None:
        """What robosuite recomputes on every substep but cannot change between policy steps,
        because the arm's base is welded to the world (:func:`supported` checks it): the origin
        (the base site's pose, computed from constants), the goal in the world frame, and the
        base site's velocity (zero Jacobian columns: exactly zero)."""
        arm, data = self.arm, self.data
        # CompositeController.update_state -> update_origin; OSC.run_controller's desired pose.
        arm.origin_pos = data.site_xpos[self.center_site].copy()
        arm.origin_ori = data.site_xmat[self.center_site].reshape([3, 3]).copy()
        if arm.input_ref_frame == "base":
            self.desired_world_pos = arm.origin_pos + np.dot(arm.origin_ori, arm.goal_pos)
            self.desired_world_ori = np.dot(arm.origin_ori, arm.goal_ori)
        else:  # "world" (checked by supported)
            self.desired_world_pos, self.desired_world_ori = arm.goal_pos, arm.goal_ori
        mujoco.mj_jacSite(self.model, data, self._jacp, self._jacr, self.center_site)
        self.base_pos_vel = np.dot(self._jacp, data.qvel)
        self.base_ori_vel = np.dot(self._jacr, data.qvel)

    def _arm_torques(self, arm: OperationalSpaceController) -> np.ndarray:
        """robosuite's update and run_controller of the arm, step by step: the same values
        (copies where robosuite copies, views where only values are read)."""
        data, model = self.data, self.model
        qvel = data.qvel
        columns = self.arm_qvel
        # Controller.update (lite physics: no forward) -> _update_single_reference. robosuite
        # computes each Jacobian in its own mj_jacSite call; one call gives both, the same values.
        jacp, jacr = self._jacp, self._jacr
        mujoco.mj_jacSite(model, data, jacp, jacr, self.ref_site)
        arm.ref_pos[:] = data.site_xpos[self.ref_site]
        arm.ref_ori_mat[:, :] = data.site_xmat[self.ref_site].reshape([3, 3])
        arm.ref_pos_vel[:] = np.dot(jacp, qvel)
        arm.ref_ori_vel[:] = np.dot(jacr, qvel)
        arm.J_pos[:, :] = jacp[:, columns]
        arm.J_ori[:, :] = jacr[:, columns]
        arm.J_full[:3] = arm.J_pos
        arm.J_full[3:] = arm.J_ori
        arm.joint_pos = data.qpos[self.arm_qpos].copy()
        arm.joint_vel = qvel[columns].copy()
        mujoco.mj_fullM(model, self._mass_matrix, data.qM)
        # robosuite's `M[index, :][:, index]` is Fortran-ordered, and its numba kernels are
        # compiled per memory layout: a C-ordered mass matrix takes another BLAS path there,
        # with other rounding. The same layout, then.
        arm.mass_matrix = np.asfortranarray(self._mass_matrix[self.arm_block])
        # OperationalSpaceController.run_controller, no interpolators.
        ori_error = orientation_error(self.desired_world_ori, arm.ref_ori_mat)
        position_error = self.desired_world_pos - arm.ref_pos
        vel_pos_error = -(arm.ref_pos_vel - self.base_pos_vel)
        desired_force = position_error * arm.kp[0:3] + vel_pos_error * arm.kd[0:3]
        vel_ori_error = -(arm.ref_ori_vel - self.base_ori_vel)
        desired_torque = ori_error * arm.kp[3:6] + vel_ori_error * arm.kd[3:6]
        lambda_full, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(
            arm.mass_matrix, arm.J_full, arm.J_pos, arm.J_ori
        )
        if arm.uncoupling:
            decoupled_wrench = np.concatenate(
                [np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)]
            )
        else:
            desired_wrench = np.concatenate([desired_force, desired_torque])
            decoupled_wrench = np.dot(lambda_full, desired_wrench)
        arm.torques = np.dot(arm.J_full.T, decoupled_wrench) + data.qfrc_bias[columns]
        arm.torques += nullspace_torques(
            arm.mass_matrix, nullspace_matrix, arm.initial_joint, arm.joint_pos, arm.joint_vel
        )
        arm.new_update = True  # Controller.run_controller
        return arm.torques


def _base_site(model: mujoco.MjModel, arm: OperationalSpaceController) -> int:
    """The id of the site robosuite takes the arm's base pose from (-1: none)."""
    name = f"{arm.naming_prefix}{arm.part_name}_center"
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)


def _block(index: slice | np.ndarray) -> tuple:
    """The rows and columns ``index`` of a square matrix, for ``matrix[_block(index)]``."""
    return (index, index) if isinstance(index, slice) else np.ix_(index, index)


def _as_index(index: Any) -> slice | np.ndarray:
    """A slice for consecutive indices (views instead of fancy-indexing copies), else an array."""
    index = np.asarray(index, dtype=np.intp).reshape(-1)
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


def supported(env: Any) -> str | None:
    """Why :func:`install` would keep robosuite's code for ``env`` (None: it is covered)."""
    if len(env.robots) != 1 or not isinstance(env.robots[0], FixedBaseRobot):
        return "it is not one fixed-base robot"
    robot = env.robots[0]
    if len(robot.arms) != 1:
        return "the robot has more than one arm"
    arm_name = robot.arms[0]
    parts = robot.part_controllers
    gripper_name = robot.get_gripper_name(arm_name)
    if set(parts) != {arm_name, gripper_name}:
        return f"its controller has parts {sorted(parts)}, not one arm and its gripper"
    if not all(robot._enabled_parts.get(part, False) for part in parts):
        return "a part of its controller is disabled"
    arm, gripper = parts[arm_name], parts[gripper_name]
    if type(arm) is not OperationalSpaceController or type(gripper) is not SimpleGripController:
        return f"its controllers are {type(arm).__name__} and {type(gripper).__name__}"
    if arm.interpolator_pos is not None or arm.interpolator_ori is not None:
        return "the arm controller interpolates"
    if gripper.interpolator is not None or not gripper.use_action_scaling:
        return "the gripper controller interpolates or does not scale its action"
    model = env.sim.model._model
    site = _base_site(model, arm)
    if site < 0 or model.body_weldid[model.site_bodyid[site]] != 0:
        return "the arm's base site is missing or can move"
    if not (env.lite_physics and arm.lite_physics):
        return "it runs without lite_physics (robosuite then forwards in every update)"
    if arm.num_ref_sites != 1 or arm.input_ref_frame not in ("base", "world"):
        return "the arm controller follows several sites or an unknown reference frame"
    return None


def install(env: Any) -> bool:
    """Run ``env``'s substeps between policy actions through the lean path; False when
    :func:`supported` says it does not cover the env (robosuite's code then runs unchanged)."""
    if supported(env) is not None:
        return False
    env._pre_action = _FastSubsteps(env)
    return True
