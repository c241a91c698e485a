"""Scripted experts solve their tasks (a few seeds each, physics only) and annotations read right."""

from __future__ import annotations

import numpy as np
import pytest

from capvector.envs.robosuite.annotations import Annotator
from capvector.envs.robosuite.demos import record_episode
from capvector.envs.robosuite.env import TASKS, SimEnv
from capvector.envs.robosuite.experts import EXPERTS, PHASES, ExpertAction, make_expert

# (task, arm, gripper): every expert on the Panda, and Lift on two other arms with the same
# 7-d OSC action space (the transfer setting); success rates measured over 100-200 seeds are in
# the module docs of capvector.envs.robosuite.experts.
CASES = [
    ("Lift", "Panda", None),
    ("Stack", "Panda", None),
    ("PickPlaceCan", "Panda", None),
    ("Lift", "IIWA", "PandaGripper"),
    ("Lift", "Sawyer", None),  # needs envs.MODEL_FIXES["Sawyer"]
]


def test_every_task_has_an_expert() -> None:
    assert set(EXPERTS) == set(TASKS)


@pytest.mark.sim
@pytest.mark.parametrize(("task", "robot", "gripper"), CASES)
def test_expert_solves_the_task(task: str, robot: str, gripper: str | None) -> None:
    sim = SimEnv(task, robot, gripper=gripper, cameras=())
    try:
        expert = make_expert(sim)
        annotator = Annotator(task, sim.spec)
        seeds = (900, 901) if task != "Lift" else (900, 901, 902)
        for seed in seeds:
            ep = record_episode(sim, expert, annotator, seed, render=False)
            assert ep is not None, f"{task} on {robot}: expert failed seed {seed}"
            assert ep.first_success < sim.max_steps
            phases = {note.split(".")[0] for note in ep.annotations}
            assert any("closing the gripper" in p for p in phases)
    finally:
        sim.close()


def _obs(eef: list[float], **objects: list[float]) -> dict[str, np.ndarray]:
    out = {"robot0_eef_pos": np.array(eef)}
    out.update({key: np.array(value) for key, value in objects.items()})
    return out


def _step(phase: str, target: str) -> ExpertAction:
    assert phase in PHASES
    return ExpertAction(action=np.zeros(7), phase=phase, target=target)


def test_annotation_directions_are_the_robots() -> None:
    note = Annotator("Lift", TASKS["Lift"])
    start = _obs([-0.10, 0.00, 1.00], cube_pos=[0.02, 0.03, 0.82])
    note.reset(start)
    text = note(_step("approach", "cube_pos"), start)
    assert text == (
        "The robot is moving above the red cube. The red cube is at x=0.02, y=0.03 on the table, "
        "3 cm to the left of, 12 cm in front of and 18 cm below the gripper."
    )
    held = _obs([0.02, 0.03, 0.93], cube_pos=[0.02, 0.03, 0.92])
    assert note(_step("lift", "cube_pos"), held).endswith(
        "The red cube is in the gripper at x=0.02, y=0.03, 10 cm above where it started."
    )
    right_behind = _obs([0.10, 0.05, 0.83], cube_pos=[0.02, -0.001, 0.82])
    assert "y=0.00 on the table, 5 cm to the right of, 8 cm behind and 1 cm below" in note(
        _step("descend", "cube_pos"), right_behind
    )


def test_place_annotations_name_the_goal() -> None:
    note = Annotator("Stack", TASKS["Stack"])
    obs = _obs([0.0, 0.0, 0.95], cubeA_pos=[0.0, 0.0, 0.94], cubeB_pos=[0.05, 0.0, 0.825])
    note.reset(_obs([0.0, 0.0, 1.0], cubeA_pos=[0.0, 0.0, 0.82], cubeB_pos=[0.05, 0.0, 0.825]))
    text = note(_step("carry", "cubeA_pos"), obs)
    assert text.startswith("The robot is carrying the red cube over the green cube.")
    assert "The green cube is at x=0.05, y=0.00 on the table" in text
    can = Annotator("PickPlaceCan", TASKS["PickPlaceCan"])
    start = _obs([0.0, -0.1, 1.0], Can_pos=[0.1, -0.3, 0.86], Can_target_pos=[0.1975, 0.4025, 0.8])
    can.reset(start)
    text = can(_step("lower", "Can_pos"), start)
    assert text.startswith("The robot is lowering the red can into its compartment.")
    assert "The can's compartment is at x=0.20, y=0.40." in text
