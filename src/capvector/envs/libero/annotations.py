"""Per-step text for LIBERO scenes: the sentences of
:mod:`capvector.envs.robosuite.annotations` for every movable object of a LIBERO task."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from capvector.envs.robosuite.annotations import _HELD_PHASES, _cm, _doing, _num, _offset_phrase


def readable_names(names: Sequence[str]) -> dict[str, str]:
    """LIBERO names -> words: ``akita_black_bowl_1`` -> "akita black bowl 1", and ``plate_1`` ->
    "plate" when the scene has no other plate."""
    stems = [n.rsplit("_", 1)[0] if n.rsplit("_", 1)[-1].isdigit() else n for n in names]
    return {
        name: (stem if stems.count(stem) == 1 else name).replace("_", " ")
        for name, stem in zip(names, stems, strict=True)
    }


class LiberoAnnotator:
    """Sentences for a LIBERO scene: the expert's phase towards its goal (put ``obj`` ``relation``
    ``target``) and every movable object's place. ``env`` is LIBERO's task env (the robosuite
    env that holds ``objects_dict``); call :meth:`reset` when an episode starts (objects at rest).
    """

    def __init__(self, env: Any, obj: str, relation: str, target: str) -> None:
        self.env = env
        self.obj = obj
        self.objects = list(env.objects_dict)
        self.supports = self.objects + list(env.fixtures_dict)
        # the goal's target may be a region (a site): named by its words all the same
        self.names = readable_names([*self.supports, *([target] * (target not in self.supports))])
        self.onto = f"{'into' if relation == 'in' else 'onto'} the {self.names[target]}"
        self.over = f"over the {self.names[target]}"
        self._rest_z: dict[str, float] = {}

    def _position(self, name: str) -> np.ndarray:
        return np.array(self.env.sim.data.body_xpos[self.env.obj_body_id[name]])

    def reset(self) -> None:
        self._rest_z = {name: float(self._position(name)[2]) for name in self.objects}

    def __call__(self, phase: str, obs: Mapping[str, np.ndarray]) -> str:
        eef = np.asarray(obs["robot0_eef_pos"])
        states = self.env.object_states_dict
        sentences = [_doing(phase, self.names[self.obj], self.onto, self.over)]
        for name in self.objects:
            pos = self._position(name)
            where = f"x={_num(pos[0])}, y={_num(pos[1])}"
            height = _cm(pos[2] - self._rest_z[name])
            under = [s for s in self.supports if s != name and states[name].check_ontop(states[s])]
            if name == self.obj and phase in _HELD_PHASES:
                text = f"is in the gripper at {where}, {height} cm above where it started"
            elif under:
                text = f"is at {where} on the {self.names[under[0]]}, {_offset_phrase(pos, eef)}"
            elif pos[2] - self._rest_z[name] < 0.01:
                text = f"is at {where} on the table, {_offset_phrase(pos, eef)}"
            else:
                text = f"is at {where}, {height} cm up, {_offset_phrase(pos, eef)}"
            sentences.append(f"The {self.names[name]} {text}.")
        return " ".join(sentences)
