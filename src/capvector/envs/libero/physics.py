"""Make MuJoCo 3 simulate LIBERO's scenes as MuJoCo 2.3.7 (robosuite 1.4, upstream LIBERO) does.

LIBERO's data and every published LIBERO number come from MuJoCo 2.3.7. The same compiled scene
XML simulated by MuJoCo 2.3.7 and 3.9 parts in two places (found by replaying one model, start
state and control sequence in both; docs/evaluation.md, "Against robosuite 1.4"):

1. **Object masses.** LIBERO objects get their mass from their visual mesh (density 100) as well
   as their collision boxes, and MuJoCo 3 computes a mesh's volume differently from 2.3.7: the
   same black bowl weighs 45.9 g in MuJoCo 3.9 and 31.3 g in 2.3.7, the ramekin 38.0 g and 27.6 g.
   Objects fall, rest and are pushed with other inertias. We copy 2.3.7's compiled inertial
   properties (mass, principal inertia, centre of mass, inertia frame) per object body from a table
   that MuJoCo 2.3.7 wrote (``inertia_mujoco237.json``, made by
   ``tools/libero/make_settle_fixture.py`` in the robosuite 1.4 stack).
2. **Box-box contact depth.** Every LIBERO object collides through boxes (a bowl is 40 of them),
   and MuJoCo 2.3.7's box-box collider reports half the penetration depth (a box sunk 3 mm into
   another is a contact at -1.5 mm; MuJoCo 3.9 says -3 mm), so in 2.3.7 the contact spring is half
   as stiff and objects rest twice as deep. The reference acceleration of a contact at depth r is
   ``-b v - k imp(r) r`` (MuJoCo's solver docs: ``b = 2 / (dmax tc)``, ``k = 1 / (dmax² tc²
   dr²)``, ``imp`` a function of ``|r| / width``); 2.3.7's contact at r/2 is reproduced at r by
   halving k with b kept (dampratio ×√2) and doubling the impedance width. Applied to box geoms.
   A box touching a non-box geom (the robot's link meshes, the floor plane) goes through another
   collider, which does not halve (a box on a plane rests at the same height in both versions to
   the bit); MuJoCo mixes the two geoms' parameters (their mean, at LIBERO's solmix 1), so the
   non-box geoms are shifted by minus the boxes' change and those pairs keep 2.3.7's mixed
   parameters (:func:`keep_box_other_contacts`).

What stays (docs/evaluation.md has the measurements): a bowl dropped onto the stove's 1 mm burner
plate tunnels into it in both versions, and 2.3.7's box-box collider keeps the plate wedged in the
bowl (contacts on both faces) where MuJoCo 3's pushes it out on top (3.44 mm); a bowl dropped onto
a ramekin lands chaotically in 2.3.7 itself (10 um at the start moves it up to 13 mm). No contact
parameter reproduces another collider's choice of normals.
"""

from __future__ import annotations

import functools
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

INERTIA_TABLE = Path(__file__).with_name("inertia_mujoco237.json")
"""``<object category><body suffix>`` (e.g. ``akita_black_bowl_main``) -> MuJoCo 2.3.7's compiled
``[mass, inertia (3), ipos (3), iquat (4, wxyz)]`` of that body."""
_BOX = 6  # mjtGeom.mjGEOM_BOX


@functools.cache
def inertia_table() -> dict[str, list[float]]:
    return json.loads(INERTIA_TABLE.read_text())


def _category(instance: str) -> str:
    """LIBERO names object instances ``<category>_<n>`` (``akita_black_bowl_1``)."""
    return re.sub(r"_\d+$", "", instance)


def set_mujoco_237_inertia(model: Any, body_names: dict[int, str], objects: list[str]) -> int:
    """Give the bodies of ``objects`` (LIBERO instance names) MuJoCo 2.3.7's inertial properties;
    ``body_names`` maps body id -> name. Returns how many bodies changed. Bodies whose category the
    table lacks keep MuJoCo 3's (the table covers every object of LIBERO-Spatial, -Object, -Goal)."""
    table = inertia_table()
    changed = 0
    for body, name in body_names.items():
        for instance in objects:
            if not name.startswith(instance + "_"):
                continue
            row = table.get(_category(instance) + name[len(instance) :])
            if row is None:
                continue
            model.body_mass[body] = row[0]
            model.body_inertia[body] = row[1:4]
            model.body_ipos[body] = row[4:7]
            model.body_iquat[body] = row[7:11]
            changed += 1
    return changed


def halve_box_contact_depth(model: Any) -> None:
    """Box geoms' contact parameters such that a box-box contact at depth r pushes back as MuJoCo
    2.3.7's at r/2 (module docstring): stiffness halved at the same damping, impedance width
    doubled."""
    box = np.asarray(model.geom_type) == _BOX
    solref = np.array(model.geom_solref)
    standard = box & (solref[:, 0] > 0)  # (timeconst, dampratio)
    direct = box & (solref[:, 0] <= 0)  # (-stiffness, -damping)
    solref[standard, 1] *= math.sqrt(2.0)
    solref[direct, 0] *= 0.5
    model.geom_solref[:] = solref
    model.geom_solimp[box, 2] *= 2.0


def keep_box_other_contacts(
    model: Any, original_solref: np.ndarray, original_solimp: np.ndarray
) -> None:
    """Undo :func:`halve_box_contact_depth` for contacts of a box with a non-box geom (the robot's
    link meshes, the floor plane), which MuJoCo 2.3.7 did not halve: other colliders.

    MuJoCo mixes a contact's ``solref``/``solimp`` linearly by the geoms' ``solmix`` (equal in
    LIBERO: the mean), so with every non-box geom shifted by minus the boxes' change, mean(box',
    other') = mean(box, other). The change is the one most boxes share (every LIBERO object and
    fixture box: dampratio +0.414, width +1 mm); the gripper's two finger pads (dampratio 0.5)
    differ, and only touch the robot's own meshes with it. Contacts between two non-box geoms get
    the shifted values; none of LIBERO's scenes rests on one. With unequal ``solmix`` or
    ``priority`` nothing is shifted. The arm grazing a cabinet before it grasps (LIBERO-Goal 0 in
    tests/fixtures/libero_referee) is 0.68 mm off robosuite 1.4 with this and 2.0 mm without."""
    box = np.asarray(model.geom_type) == _BOX
    if not box.any() or np.ptp(model.geom_solmix) > 0 or np.ptp(model.geom_priority) > 0:
        return
    change = np.concatenate(
        [
            np.asarray(model.geom_solref) - original_solref,
            np.asarray(model.geom_solimp) - original_solimp,
        ],
        axis=1,
    )[box]
    rows, counts = np.unique(change.round(12), axis=0, return_counts=True)
    common = rows[counts.argmax()]
    model.geom_solref[~box] = original_solref[~box] - common[:2]
    model.geom_solimp[~box] = original_solimp[~box] - common[2:]


def match_mujoco_237(env: Any) -> None:
    """Apply both corrections to the robosuite env ``env`` (LIBERO's ``env.env``) now and whenever
    a reset builds a new model (robosuite's hard reset), then recompute the model's constants that
    depend on masses (``mj_setConst``: the constraint solver's regularisation uses them)."""
    import mujoco

    patched: list[Any] = []

    def patch() -> None:
        model = env.sim.model._model
        if patched and patched[0] is model:
            return
        names = {
            b: mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(model.nbody)
        }
        set_mujoco_237_inertia(model, {b: n for b, n in names.items() if n}, list(env.objects_dict))
        solref, solimp = np.array(model.geom_solref), np.array(model.geom_solimp)
        halve_box_contact_depth(model)
        keep_box_other_contacts(model, solref, solimp)
        mujoco.mj_setConst(model, mujoco.MjData(model))
        patched[:] = [model]

    reset_internal = env._reset_internal

    def reset_and_patch() -> None:
        patch()
        reset_internal()

    env._reset_internal = reset_and_patch
    patch()
