"""Scripted experts for LIBERO's pick-and-place tasks, judged by LIBERO's own success predicate.

An expert reads what to do from the task's BDDL goal as LIBERO's parser returns it
(``env.parsed_problem["goal_state"]``, e.g. ``[["on", "akita_black_bowl_1", "plate_1"]]``): the
first argument is the object to move, the second an object or a region site to put it on or in.
It then runs the phase machine of :mod:`capvector.envs.robosuite.experts` (approach, descend, grasp, lift,
carry, lower, release, retreat) over the simulator's state, with OSC_POSE delta actions:
translation ``clip(10 * (target - eef), -1, 1)``, the gripper held at its reset orientation turned
by the chosen grasp yaw, gripper -1 open / +1 closed.

Where and how to grasp comes from the object's collision geometry (its world bounding box and
its extent along candidate finger axes), not from per-task tables:

- Bowls (an object whose top is open, :data:`RIM_GRASP`) are gripped at the rim wall, the
  fingers closing across it about 4.7 cm from the bowl's centre (``research/libero_offline.md``,
  "Scripted experts are feasible"); of 32 finger headings, the one whose open outer finger and
  hand land farthest from the other objects' and the fixtures' collision geoms (a drawer's walls),
  within the arm's reach.
- Everything else is gripped at its centre, the fingers closing across its narrowest horizontal
  side, a little below its top.

LIBERO's ``On(a, b)`` holds when a is in contact with b, above it and within 3 cm of its centre
in xy; ``In(a, region)`` when a's body origin is inside the region's box. So the expert carries the
object until the *object's* origin (not the gripper) is over the target, lowers it until its
bottom is just above the target's top, and lets go. It lifts the object out from under whatever
overhangs it (a cabinet's top over its open drawer) before lifting it up, and carries it just over
what lies on its way, not over everything in the scene (the Spatial step limit is short).

Measured success, the 50 official initial states of every task, LIBERO's protocol (10 wait
steps, the suite's step limit; robosuite 1.5.2 through rpent-libero): see docs/evaluation.md;
reproduce with ``python -m capvector.workflows.expert_success --suite libero_spatial``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from robosuite.utils import transform_utils as T

from capvector.envs.robosuite.experts import GRIPPER_CLOSED, GRIPPER_OPEN
from capvector.errors import CapVectorError

RIM_GRASP = ("bowl",)
"""Object names containing one of these are grasped at the rim wall, not at the centre."""
RIM_OFFSET = 0.047
"""Bowl rim grasp: metres from the bowl's centre along the finger axis."""
FINGERTIP_BELOW_EEF = 0.013
"""The Panda fingers reach this far below the end-effector site: the lowest grasp over a surface."""
HAND_HALF_LENGTH, HAND_HALF_WIDTH, HAND_ABOVE_EEF = 0.11, 0.035, 0.03
"""The Panda hand's footprint about the end-effector site (along and across the finger axis) and
how far above the site it begins: what must not land on a neighbour."""
MAX_GRASP_WIDTH = 0.075
"""The Panda hand opens to 8 cm; wider sides cannot be gripped across."""
RIM_YAWS = 16
"""Bowl rim grasps: finger axes tried, 180/RIM_YAWS degrees apart (each from both sides)."""
REACH = 0.805
"""How far (m, in the vertical plane through the arm's base, along x and z) from the Panda's
shoulder it can lower its hand to a bowl's rim: measured on table-top bowls, where beyond x = 0.08
m it cannot; a rim up in a drawer is in reach farther out. (Across, in y, the arm turns.)"""
PLACE_REACH = 0.75
"""How far (m) from the shoulder the hand can let a bowl go: stretched out to a plate at y = 0.2
it stalls 0.785 m out, drifting 3 cm forward of the plate's centre as it goes down."""
DRAWER_JOINTS = (mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE)
"""Joints that open a region (a drawer's slide, a door's hinge)."""

FIXTURE_SEED_START = 1_000_000
"""Trial i's fixtures are placed from seed FIXTURE_SEED_START + i, as in ``capvector evaluate``
(``capvector.envs.base.EVAL_SEED_START``)."""


@dataclass(frozen=True)
class PlaceGoal:
    """The one goal predicate an expert serves: put ``obj`` ``relation`` ``target``."""

    relation: str
    """``on`` or ``in`` (LIBERO's predicate names, lower case as its parser returns them)."""
    obj: str
    target: str
    target_is_site: bool


def task_env(env: Any) -> Any:
    """LIBERO's robosuite env inside the wrappers (``ControlEnv``, the fast renderer's)."""
    inner = env
    while not hasattr(inner, "parsed_problem"):
        inner = inner.env
    return inner


def place_goal(env: Any) -> PlaceGoal:
    """The task's goal from its parsed BDDL, or a CapVectorError if it is not a single placement."""
    inner = task_env(env)
    goal = [list(map(str, p)) for p in inner.parsed_problem["goal_state"]]
    if len(goal) != 1 or len(goal[0]) != 3 or goal[0][0] not in ("on", "in"):
        raise CapVectorError(
            f"no scripted LIBERO expert for the goal {goal} of "
            f"{inner.parsed_problem['problem_name']}: experts place one object on or in another "
            "(one `On` or `In` predicate)"
        )
    relation, obj, target = goal[0]
    if obj not in inner.objects_dict:
        raise CapVectorError(f"goal {goal}: {obj} is not a movable object of the scene")
    return PlaceGoal(relation, obj, target, target not in inner.objects_dict)


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _heading(v: np.ndarray) -> float:
    return math.atan2(float(v[1]), float(v[0]))


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle), 0.0])


class _Geometry:
    """World-frame collision geometry of a LIBERO scene's bodies, read from MuJoCo each call."""

    def __init__(self, env: Any) -> None:
        self.inner = task_env(env)
        self.model = self.inner.sim.model._model
        self.data = self.inner.sim.data._data
        self._geoms: dict[str, np.ndarray] = {}

    def geoms(self, name: str) -> np.ndarray:
        """Collision geoms of body ``name`` and its descendants."""
        if name not in self._geoms:
            root = self.inner.obj_body_id[name]
            m = self.model
            ids = []
            for g in range(m.ngeom):
                if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0:
                    continue  # visual only
                body = m.geom_bodyid[g]
                while body not in (0, root):
                    body = m.body_parentid[body]
                if body == root:
                    ids.append(g)
            self._geoms[name] = np.asarray(ids, dtype=np.int64)
        return self._geoms[name]

    def corners(self, name: str) -> np.ndarray:
        """(8 * G, 3) world corners of the geoms' local bounding boxes."""
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        out = []
        for g in self.geoms(name):
            centre, half = self.model.geom_aabb[g][:3], self.model.geom_aabb[g][3:]
            rot = self.data.geom_xmat[g].reshape(3, 3)
            out.append(self.data.geom_xpos[g] + (centre + signs * half) @ rot.T)
        return np.concatenate(out)

    def geom_boxes(self, name: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """World axis-aligned bounding box (lo, hi) of each collision geom of a body."""
        corners = self.corners(name).reshape(-1, 8, 3)
        return [(c.min(axis=0), c.max(axis=0)) for c in corners]

    def oriented_boxes(self, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centres (G, 3), rotations (G, 3, 3), half sizes (G, 3)) of the collision geoms' own
        boxes: a turned cabinet's walls as they stand, not the world boxes around them (which
        fill its open drawer)."""
        ids = np.concatenate([self.geoms(n) for n in names]) if names else np.zeros(0, np.int64)
        rot = self.data.geom_xmat[ids].reshape(-1, 3, 3)
        aabb = self.model.geom_aabb[ids]
        centres = self.data.geom_xpos[ids] + np.einsum("gij,gj->gi", rot, aabb[:, :3])
        return centres, rot, aabb[:, 3:]

    def box(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounding box (lo, hi) of a body's collision geometry."""
        c = self.corners(name)
        return c.min(axis=0), c.max(axis=0)

    def bulk_centre(self, name: str) -> np.ndarray:
        """World centre of the body's largest collision geom (by bounding-box volume)."""
        geoms = self.geoms(name)
        volumes = [np.prod(self.model.geom_aabb[g][3:]) for g in geoms]
        g = geoms[int(np.argmax(volumes))]
        rot = self.data.geom_xmat[g].reshape(3, 3)
        return self.data.geom_xpos[g] + rot @ self.model.geom_aabb[g][:3]

    def extent(self, name: str, direction: np.ndarray) -> float:
        """Width of the body's geometry along a horizontal unit ``direction``."""
        projected = self.corners(name) @ direction
        return float(projected.max() - projected.min())

    def position(self, name: str) -> np.ndarray:
        return np.array(self.data.xpos[self.inner.obj_body_id[name]])

    def site(self, name: str) -> np.ndarray:
        return np.array(self.inner.sim.data.get_site_xpos(name))

    def finger_axis(self) -> np.ndarray:
        """(3,) unit vector from the right to the left fingerpad (the direction they close along)."""
        gripper = self.inner.robots[0].gripper["right"]
        sim = self.inner.sim
        pads = [gripper.important_geoms[f"{side}_fingerpad"][0] for side in ("left", "right")]
        left, right = (sim.data.geom_xpos[sim.model.geom_name2id(n)] for n in pads)
        axis = np.asarray(left - right, dtype=np.float64)
        return axis / np.linalg.norm(axis)


@dataclass(frozen=True)
class ExpertStep:
    action: np.ndarray
    """(7,) float64 OSC_POSE delta action, gripper -1 open / +1 closed."""
    phase: str


class LiberoPlaceExpert:
    """Pick ``goal.obj`` and put it on or in ``goal.target``; call :meth:`reset` after every
    ``set_init_state`` (and after the wait steps), then :meth:`act` once per step."""

    approach_height = 0.06
    clearance = 0.05
    """Carry height: the object's bottom this far above the top of everything else."""
    release_height = 0.015
    grasp_steps = 6
    release_steps = 8
    descend_steps = 40

    def __init__(self, env: Any, goal: PlaceGoal | None = None) -> None:
        self.env = env
        self.goal = goal or place_goal(env)
        self.geometry = _Geometry(env)
        self.reset()

    # --- planning ------------------------------------------------------------------------------

    def reset(self) -> None:
        g = self.geometry
        obs = self.geometry.inner._get_observations(force_update=True)
        self._rot0 = T.quat2mat(obs["robot0_eef_quat"])
        self._axis0 = _heading(g.finger_axis())
        self._others = [n for n in g.inner.objects_dict if n != self.goal.obj]
        self._release_at: np.ndarray | None = None  # where the hand stays as it lets go
        self._check_target_open()
        self._plan_grasp()
        self._enter("approach")

    def _check_target_open(self) -> None:
        """Refuse a target region inside a drawer that is not open (LIBERO-Goal 3: "open the top
        drawer and put the bowl inside" has one ``In`` goal): the expert places from above and
        does not open it first. "Open" is LIBERO's own predicate on the region's slide and hinge
        joints (its ``Close`` is false at a drawer's closed stop, so it cannot be used)."""
        if not self.goal.target_is_site:
            return
        inner, model = self.geometry.inner, self.geometry.model
        site_joints = inner.object_sites_dict[self.goal.target].joints or []
        joints = [j for j in site_joints if model.jnt_type[model.joint(j).id] in DRAWER_JOINTS]
        if not joints:  # a fixed region, or the free joint of a basket that carries it
            return
        parent = inner.get_object(inner.object_states_dict[self.goal.target].parent_name)
        qpos = [inner.sim.data.qpos[inner.sim.model.get_joint_qpos_addr(j)] for j in joints]
        if not any(parent.is_open(q) for q in qpos):
            raise CapVectorError(
                f"{self.goal.target} is inside a closed drawer: the expert places from above and "
                "does not open it first"
            )

    def _plan_grasp(self) -> None:
        """Choose the grasp yaw and point from the object's geometry as it lies now."""
        g, name = self.geometry, self.goal.obj
        lo, hi = g.box(name)
        centre = g.position(name)
        if any(key in name for key in RIM_GRASP):
            yaw, point = self._rim_grasp(centre, lo, hi)
            z = hi[2] - 0.022  # the middle of the rim wall's collision boxes
        else:
            # at the height of its bulk (the carton, not the gable fin on top of it)
            z = min(g.bulk_centre(name)[2], hi[2] - 0.02)
            z = max(z, lo[2] + FINGERTIP_BELOW_EEF + 0.002)
            point = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z])
            yaw = self._narrow_yaw(name, point)
        point[2] = z
        # the fingers close along (cos yaw, sin yaw); a turn of delta about z gets them there
        delta = (yaw - self._axis0 + math.pi / 2) % math.pi - math.pi / 2
        self._ref_rot = _rot_z(delta) @ self._rot0
        self._grasp = point
        self._grasp_offset = point - centre  # from the object's origin, kept while it moves

    def _narrow_yaw(self, name: str, point: np.ndarray) -> float:
        """Heading that closes the fingers across the object's narrowest horizontal side, among
        the 12 headings 15 degrees apart (a heading and its opposite grasp alike), with the hand
        and fingers clear of the neighbours when they reach the grasp ``point``."""
        best, best_score = None, np.inf
        for k in range(-6, 6):
            yaw = self._axis0 + k * math.pi / 12
            width = self.geometry.extent(name, _unit(yaw))
            if width > MAX_GRASP_WIDTH:
                continue
            score = width + 1e-3 * abs(k) + (1.0 if self._hand_hits(yaw, point) else 0.0)
            if score < best_score:
                best, best_score = yaw, score
        if best is None:
            raise CapVectorError(
                f"{name} is wider than the gripper opens ({MAX_GRASP_WIDTH * 100:.1f} cm) "
                "whichever way it is gripped"
            )
        return best

    def _hand_hits(self, yaw: float, point: np.ndarray) -> bool:
        """Whether the hand or the open fingers, lowered to grasp at ``point`` with the fingers
        along ``yaw``, would land on another object (its box overlapping the footprint)."""
        u, v = _unit(yaw), _unit(yaw + math.pi / 2)
        # (half length along the finger axis, half width across it, lowest z above the grasp)
        parts = (
            (HAND_HALF_LENGTH, HAND_HALF_WIDTH, HAND_ABOVE_EEF),
            (0.05, 0.012, -FINGERTIP_BELOW_EEF),
        )
        for other in self._others:
            corners = self.geometry.corners(other)
            along, across = (corners - point) @ u, (corners - point) @ v
            top = corners[:, 2].max()
            for half_length, half_width, above in parts:
                if top < point[2] + above:
                    continue
                overlaps_along = along.max() > -half_length and along.min() < half_length
                if overlaps_along and across.max() > -half_width and across.min() < half_width:
                    return True
        return False

    def _rim_grasp(
        self, centre: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[float, np.ndarray]:
        """(yaw, point) on a bowl's rim wall where the open fingers and the hand land farthest
        from anything else: the other objects' and the fixtures' (a drawer's walls, a cabinet's
        top) collision geoms, as the oriented boxes they are."""
        g = self.geometry
        z = hi[2] - 0.022
        boxes = g.oriented_boxes(self._others + list(g.inner.fixtures_dict))
        shoulder = g.inner.sim.data.get_body_xpos("robot0_link2")
        place_xy, surface = self._place_target()
        # where the hand lets go: the bowl's bottom just above the surface, held 2 cm lower
        # than planned (a bowl held by its rim tilts 15-20 degrees as it is lifted)
        place_z = surface + self.release_height + (z - lo[2]) + 0.02
        best, best_score = (self._axis0, centre.copy()), -np.inf
        for k in range(-RIM_YAWS // 2, RIM_YAWS // 2):
            yaw = self._axis0 + k * math.pi / RIM_YAWS
            for side in (1.0, -1.0):
                u = side * _unit(yaw)
                point = np.array([*(centre + RIM_OFFSET * u)[:2], z])
                clearance = _clearance(_hand_points(point, u), boxes)
                # clear by 2 cm is enough; within the arm's reach, here and (as a tie-break
                # among clear sides: a bowl deep in a drawer has one) where it lets go; less
                # wrist turn
                reach = max(0.0, float(np.linalg.norm((point - shoulder)[[0, 2]])) - REACH)
                place = np.array([*(place_xy + point[:2] - centre[:2]), place_z])
                reach += 0.1 * max(0.0, float(np.linalg.norm(place - shoulder)) - PLACE_REACH)
                score = min(clearance, 0.02) - 2.0 * reach - 0.001 * abs(k)
                if score > best_score:
                    best, best_score = (yaw, point.copy()), score
        return best

    def _way_out(self) -> np.ndarray | None:
        """Horizontal unit vector that slides the held object out from under whatever is just
        above it (a bowl at the back of an open drawer sits under the cabinet's top, 1 cm above
        its rim, and lifted straight up it is wiped out of the fingers), or None if it is free."""
        g = self.geometry
        centres, rot, half = g.oriented_boxes(self._others + list(g.inner.fixtures_dict))
        corners = g.corners(self.goal.obj)
        # the object's geometry 1 to 4 cm above where it is now
        raised = np.concatenate([corners + np.array([0.0, 0.0, dz]) for dz in (0.01, 0.02, 0.04)])
        local = np.einsum("gji,pgj->pgi", rot, raised[:, None, :] - centres[None])
        inside = (np.abs(local) <= half[None] + 0.002).all(axis=-1)  # (P, G)
        if not inside.any():
            return None
        blocker = int(np.argmax(inside.sum(axis=0)))
        away = (g.position(self.goal.obj) - centres[blocker])[:2]
        return np.array([*(away / np.linalg.norm(away)), 0.0])

    def _place_target(self) -> tuple[np.ndarray, float]:
        """(xy where the object's origin goes, z of the surface its bottom goes to)."""
        g, goal = self.geometry, self.goal
        if not goal.target_is_site:
            lo, hi = g.box(goal.target)
            return g.position(goal.target)[:2], float(hi[2])
        site = g.site(goal.target)
        parent = self._site_parent(goal.target)
        if goal.relation == "in" and parent is not None:
            return site[:2], float(g.box(parent)[1][2])  # drop over the container's wall
        return site[:2], float(site[2])

    def _site_parent(self, site: str) -> str | None:
        names = list(self.geometry.inner.objects_dict) + list(self.geometry.inner.fixtures_dict)
        matches = [n for n in names if site.startswith(n + "_")]
        return max(matches, key=len) if matches else None

    def _carry_floor(self, xy: np.ndarray) -> float:
        """z the held object's bottom must clear while carried to ``xy``: the tops of the other
        objects' and the fixtures' collision geoms it would pass over (clearing everything in the
        scene, a bowl up on a cabinet, costs the Spatial tasks' short step limit the time to
        lower again)."""
        g = self.geometry
        lo, hi = g.box(self.goal.obj)
        reach = (hi[:2] - lo[:2]) / 2 + 0.02  # the held object's half size, and a margin
        start = (lo[:2] + hi[:2]) / 2
        path = start + np.linspace(0.0, 1.0, 20)[:, None] * (xy - start)
        centres, rot, half = g.oriented_boxes(self._others + list(g.inner.fixtures_dict))
        world_half = np.einsum("gij,gj->gi", np.abs(rot), half)  # their world boxes' half sizes
        gap = np.abs(path[:, None, :] - centres[None, :, :2]) - world_half[None, :, :2]  # (P, G, 2)
        passed = (gap < reach).all(axis=-1).any(axis=0)
        tops = centres[passed, 2] + world_half[passed, 2]
        return float(tops.max(initial=-np.inf)) + self.clearance

    # --- acting --------------------------------------------------------------------------------

    def _enter(self, phase: str) -> None:
        self.phase = phase
        self._count = 0
        self._xy_error_sum = np.zeros(3)
        self._heights: list[float] = []

    def _rotation_error(self, quat: np.ndarray) -> np.ndarray:
        rot = T.quat2mat(quat)
        return np.asarray(T.quat2axisangle(T.mat2quat(self._ref_rot @ rot.T)))

    def _step(
        self, obs: Mapping[str, np.ndarray], target: np.ndarray, gripper: float
    ) -> ExpertStep:
        error = target - np.asarray(obs["robot0_eef_pos"])
        if self.phase in ("descend", "carry", "lower", "release"):
            # an integral term on xy: stretched far forward the OSC settles 7-13 mm short, enough
            # to put a fingertip on the rim or the bowl off the plate
            self._xy_error_sum[:2] = np.clip(self._xy_error_sum[:2] + error[:2], -0.3, 0.3)
        move = np.clip(10.0 * error + 1.0 * self._xy_error_sum, -1.0, 1.0)
        turn = np.clip(self._rotation_error(obs["robot0_eef_quat"]) / 0.5, -1.0, 1.0)
        return ExpertStep(np.concatenate([move, turn, [gripper]]), self.phase)

    def _holding(self, obs: Mapping[str, np.ndarray]) -> bool:
        """The object still moves with the hand: its grasp point within 5 cm of the gripper. (The
        finger opening says nothing here: a bowl hangs by its 2 mm wall with the fingers as
        closed as on nothing.)"""
        grasp = self.geometry.position(self.goal.obj) + self._grasp_offset
        return bool(np.linalg.norm(grasp - np.asarray(obs["robot0_eef_pos"])) < 0.05)

    def act(self, obs: Mapping[str, np.ndarray]) -> ExpertStep:
        eef = np.asarray(obs["robot0_eef_pos"])
        g, goal = self.geometry, self.goal
        obj = g.position(goal.obj)
        grasp = obj + self._grasp_offset
        self._count += 1
        if self.phase == "approach":
            target = grasp + np.array([0.0, 0.0, self.approach_height])
            # the open fingertips above the object's top until lined up over it
            target[2] = max(target[2], g.box(goal.obj)[1][2] + FINGERTIP_BELOW_EEF + 0.02)
            aligned = np.linalg.norm(self._rotation_error(obs["robot0_eef_quat"])) < 0.08
            if (
                np.linalg.norm((target - eef)[:2]) < 0.01
                and abs(target[2] - eef[2]) < 0.05
                and aligned
            ):
                self._enter("descend")
            return self._step(obs, target, GRIPPER_OPEN)
        if self.phase == "descend":
            error = grasp - eef
            lined_up = np.linalg.norm(error[:2]) < 0.005 and abs(error[2]) < 0.008
            if lined_up or self._count > self.descend_steps:
                self._enter("grasp")
            target = grasp.copy()
            if np.linalg.norm((grasp - eef)[:2]) > 0.004:
                target[2] = max(grasp[2], eef[2] - 0.01)  # line up before going lower
            return self._step(obs, target, GRIPPER_OPEN)
        if self.phase == "grasp":
            # lift once the fingers have stopped closing: lifting a bowl by its 2 mm rim wall
            # before they squeeze it lets the wall slip out
            closing = np.abs(np.asarray(obs["robot0_gripper_qvel"])).max() > 0.01
            if (self._count >= self.grasp_steps and not closing) or self._count >= 25:
                # at least 6 cm up first: off a cabinet or a stove, not dragged across it
                self._lift_floor = eef[2] + 0.06
                # where the hand did close (a descent stopped by a tall bottle's top closes
                # higher than planned): what _holding compares against
                self._grasp_offset = eef - obj
                self._enter("lift")
            return self._step(obs, grasp, GRIPPER_CLOSED)
        if self.phase in ("lift", "carry", "lower") and not self._holding(obs):
            self._plan_grasp()  # dropped it: grasp again from where it lies now
            self._enter("approach")
            return self.act(obs)
        bottom_below_eef = eef[2] - g.box(goal.obj)[0][2]
        xy, surface = self._place_target()
        carry_z = max(self._carry_floor(xy), surface + self.clearance) + bottom_below_eef
        carry_z = max(carry_z, self._lift_floor)
        over = np.array([*(eef[:2] + xy - obj[:2]), carry_z])
        if self.phase == "lift":
            target = np.array([eef[0], eef[1], carry_z])
            way_out = self._way_out()
            if way_out is not None:  # under a cabinet's top: slide it out first, then up
                target = eef + 0.05 * way_out
            if carry_z - eef[2] < 0.01:
                self._enter("carry")
            return self._step(obs, target, GRIPPER_CLOSED)
        if self.phase == "carry":
            # On needs the centres within 3 cm, In the origin inside the region; a bowl hanging
            # by its rim swings about the target for tens of steps before it settles within 8 mm
            tolerance = 0.015 if self.goal.relation == "on" else 0.008
            if np.linalg.norm(obj[:2] - xy) < tolerance or self._count > 80:
                self._enter("lower")
            return self._step(obs, over, GRIPPER_CLOSED)
        if self.phase == "lower":
            target = over.copy()
            target[2] = surface + self.release_height + bottom_below_eef
            self._heights.append(float(eef[2]))
            # or the arm has stopped going down: stretched to the end of its reach (a bowl held
            # high on its rim hangs low, tilted), waiting out the 60 steps loses the episode
            stalled = len(self._heights) > 10 and self._heights[-6] - eef[2] < 0.002
            if abs(target[2] - eef[2]) < 0.006 or self._count > 60:
                self._release_at = None  # stay where it is
                self._enter("release")
            elif stalled:
                # hold the hand at the target while the fingers open, keeping the integral term
                # (not _enter, which zeroes it): the stretched arm, told to stay where it is,
                # springs 2 cm forward and swings the bowl off the plate
                self._release_at = np.array([*target[:2], eef[2]])
                self.phase, self._count = "release", 0
            return self._step(obs, target, GRIPPER_CLOSED)
        if self.phase == "release":
            if self._count >= self.release_steps:
                self._enter("retreat")
            hold = eef if self._release_at is None else self._release_at
            return self._step(obs, hold, GRIPPER_OPEN)
        return self._step(obs, eef + np.array([0.0, 0.0, 0.05]), GRIPPER_OPEN)


def _hand_points(point: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(P, 3) points on the open outer finger and the hand when the end-effector is at ``point``
    with the fingers closing along ``u`` (horizontal unit vector pointing to the outer finger)."""
    v = np.array([-u[1], u[0], 0.0])
    z = np.array([0.0, 0.0, 1.0])
    finger = [
        point + r * u + w * v + h * z
        for r in (0.04, 0.05)  # the open finger's pad and its outer face
        for w in (-0.01, 0.0, 0.01)
        for h in (-FINGERTIP_BELOW_EEF, 0.01, HAND_ABOVE_EEF)
    ]
    hand = [
        point + r * u + w * v + h * z
        for r in np.linspace(-HAND_HALF_LENGTH, HAND_HALF_LENGTH, 5)
        for w in (-HAND_HALF_WIDTH, HAND_HALF_WIDTH)
        for h in (HAND_ABOVE_EEF + 0.01, HAND_ABOVE_EEF + 0.05)
    ]
    return np.array(finger + hand)


def _clearance(points: np.ndarray, boxes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    """Smallest distance from any of ``points`` (P, 3) to any oriented box (1.0 if no boxes)."""
    centres, rot, half = boxes
    if len(centres) == 0:
        return 1.0
    local = np.einsum("gji,pgj->pgi", rot, points[:, None, :] - centres[None])  # (P, G, 3)
    outside = np.maximum(np.abs(local) - half[None], 0.0)
    return float(np.linalg.norm(outside, axis=-1).min())


@dataclass
class TrialResult:
    success: bool
    steps: int
    """Policy steps (after the wait steps) until success, or the step limit."""


def run_trial(
    env: Any,
    init_state: np.ndarray | None,
    max_steps: int,
    *,
    on_step: Any = None,
    fixture_seed: int | None = None,
) -> TrialResult:
    """One trial under LIBERO's protocol: ``reset`` and ``set_init_state``, 10 wait steps, then
    the expert until LIBERO's ``done`` or ``max_steps``. ``init_state=None`` starts from the env's
    current state without a reset (demos: the caller has placed the objects).

    ``on_step(obs, step, done)`` is called before every expert step (``obs`` the observation the
    step acts on) (demo recording). ``fixture_seed`` seeds numpy's global RNG for the reset,
    from which LIBERO places the fixtures (cabinets, stoves; restored after).
    """
    obs = _settle(env, init_state, fixture_seed)
    expert = LiberoPlaceExpert(env)
    for t in range(max_steps):
        step = expert.act(obs)
        if on_step is not None:
            on_step(obs, step, t)
        obs, _, done, _ = env.step(step.action.tolist())
        if done:
            return TrialResult(True, t + 1)
    return TrialResult(False, max_steps)


def check_served(env: Any, init_state: np.ndarray, fixture_seed: int) -> None:
    """Raise CapVectorError, saying why, if the expert cannot serve the task from this initial
    state: its goal is not one placement, the object is wider than the gripper opens, or the
    target is inside a closed drawer."""
    _settle(env, init_state, fixture_seed)
    LiberoPlaceExpert(env)


def _settle(env: Any, init_state: np.ndarray | None, fixture_seed: int | None) -> dict:
    """A trial's start: ``reset`` and ``set_init_state`` (unless ``init_state`` is None), then
    LIBERO's wait steps; the last observation."""
    from capvector.envs.libero.env import NUM_WAIT_STEPS, WAIT_ACTION, seeded_reset

    if init_state is not None:
        if fixture_seed is None:
            env.reset()
        else:
            seeded_reset(env, fixture_seed)
        env.set_init_state(init_state)
    for _ in range(NUM_WAIT_STEPS):
        obs, _, _, _ = env.step(WAIT_ACTION.tolist())  # objects settle, as in the evaluation
    return obs


def evaluate_expert(
    suite: str,
    tasks: Sequence[int] | None = None,
    trials: int = 50,
    *,
    progress: bool = True,
    on_task: Any = None,
) -> dict[int, list[TrialResult]]:
    """The expert on the first ``trials`` official initial states of each task;
    ``on_task(task_id, results)`` is called as each task finishes. Without ``tasks``, every task
    the expert serves from its first initial state (:func:`check_served`); the others are left
    out, said on stderr (named in ``tasks``, such a task is an error)."""
    from tqdm import tqdm

    from capvector.envs.libero.env import (
        LIBERO_NUM_TASKS,
        initial_states,
        make_libero_env,
        max_steps,
    )

    every_task = tasks is None
    tasks = list(range(LIBERO_NUM_TASKS[suite])) if tasks is None else list(tasks)
    results: dict[int, list[TrialResult]] = {}
    bar = tqdm(
        total=len(tasks) * trials, desc=f"{suite} expert", unit="trial", disable=not progress
    )
    for task_id in tasks:
        # as `capvector evaluate` (eval/libero.py): soft resets (the same states after
        # set_init_state, in a tenth of the time), trial i's fixtures from seed 1,000,000 + i
        env = make_libero_env(suite, task_id, render=False, hard_reset=False)
        try:
            states = initial_states(suite, task_id)[:trials]
            if every_task:
                try:
                    check_served(env, states[0], FIXTURE_SEED_START)
                except CapVectorError as not_served:
                    print(f"{suite} task {task_id}: left out: {not_served}", file=sys.stderr)
                    bar.total -= trials
                    continue
            results[task_id] = []
            for trial, state in enumerate(states):
                seed = FIXTURE_SEED_START + trial
                results[task_id].append(run_trial(env, state, max_steps(suite), fixture_seed=seed))
                done = sum(r.success for r in results[task_id])
                bar.set_postfix(task=task_id, success=f"{done}/{len(results[task_id])}")
                bar.update(1)
        finally:
            env.close()
        if on_task is not None:
            on_task(task_id, results[task_id])
    bar.close()
    return results


def success_table(suite: str, results: Mapping[int, Sequence[TrialResult]]) -> str:
    """A Markdown table: per task its instruction, successes over trials and mean steps."""
    from capvector.envs.libero.env import libero_task

    lines = ["| task | instruction | success | mean steps (successes) |", "|---|---|---|---|"]
    for task_id, trials in sorted(results.items()):
        wins = [r.steps for r in trials if r.success]
        steps = f"{np.mean(wins):.0f}" if wins else "-"
        instruction = libero_task(suite, task_id).instruction
        lines.append(f"| {task_id} | {instruction} | {len(wins)}/{len(trials)} | {steps} |")
    total = sum(r.success for trials in results.values() for r in trials)
    count = sum(len(trials) for trials in results.values())
    lines.append(f"| all | | {total}/{count} | |")
    return "\n".join(lines)
