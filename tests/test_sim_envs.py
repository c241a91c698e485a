"""SimEnv: seeded resets, upright images, intrinsics consistent with what is rendered, depth."""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

from capvector.envs.robosuite.env import (
    TASKS,
    CameraRenderer,
    SimEnv,
    SimulationFault,
    camera_intrinsics,
    get_task,
)

CAMERAS = ("agentview", "robot0_eye_in_hand")


def test_camera_intrinsics_matches_fovy() -> None:
    k = camera_intrinsics(90.0, 64)
    # tan(45 deg) = 1: the focal length is half the image height, principal point at the centre.
    np.testing.assert_allclose(k, [[32, 0, 32], [0, 32, 32], [0, 0, 1]], atol=1e-12)
    wide = camera_intrinsics(45.0, 48, 64)
    assert wide[0, 2] == 32 and wide[1, 2] == 24
    assert math.isclose(wide[0, 0], 24 / math.tan(math.radians(22.5)))


def test_unknown_task_names_the_known_ones() -> None:
    with pytest.raises(KeyError, match="Lift"):
        get_task("Lfit")


def test_env_kwargs_are_json_and_single_arm(sim: SimEnv) -> None:
    import json

    kwargs = sim.env_kwargs
    assert json.loads(json.dumps(kwargs)) == kwargs
    assert list(kwargs["controller_configs"]["body_parts"]) == ["right"]
    assert kwargs["controller_configs"]["body_parts"]["right"]["type"] == "OSC_POSE"
    assert not kwargs["has_offscreen_renderer"] and not kwargs["use_camera_obs"]


@pytest.fixture(scope="module")
def sim() -> SimEnv:
    env = SimEnv("Lift", cameras=CAMERAS, image_size=64, depth=True)
    yield env
    env.close()


def _camera_pose(sim: SimEnv, name: str) -> tuple[np.ndarray, np.ndarray]:
    model, data = sim.env.sim.model._model, sim.env.sim.data._data
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
    return data.cam_xpos[cam].copy(), data.cam_xmat[cam].reshape(3, 3).copy()


def _project(point: np.ndarray, pos: np.ndarray, rot: np.ndarray, k: np.ndarray) -> np.ndarray:
    # MuJoCo cameras look along their -z axis with +y up; image rows grow downwards.
    p = rot.T @ (point - pos)
    return np.array([k[0, 2] + k[0, 0] * p[0] / -p[2], k[1, 2] - k[1, 1] * p[1] / -p[2]])


@pytest.mark.sim
def test_reset_is_a_function_of_the_seed(sim: SimEnv) -> None:
    a = sim.reset(11)["cube_pos"]
    sim.reset(12)
    state = sim.flat_state()
    assert not np.allclose(sim.observation["cube_pos"], a)
    np.testing.assert_array_equal(sim.reset(11)["cube_pos"], a)
    sim.reset(12)
    np.testing.assert_array_equal(sim.flat_state(), state)


@pytest.mark.sim
def test_lift_zooms_agentview_and_reports_it(sim: SimEnv) -> None:
    assert sim.camera_fovy["agentview"] == TASKS["Lift"].camera_fovy["agentview"] == 35.0
    np.testing.assert_allclose(sim.intrinsics()["agentview"], camera_intrinsics(35.0, 64))


@pytest.mark.sim
def test_images_are_upright_and_match_intrinsics(sim: SimEnv) -> None:
    sim.reset(3)
    images, depth = sim.render()
    agent = images["agentview"].astype(float)
    assert images["agentview"].dtype == np.uint8 and agent.shape == (64, 64, 3)
    # The table (bright, near the camera) fills the bottom of an upright agentview image; the
    # robot base and the dark wall are at the top.
    assert agent[-8:].mean() > agent[:8].mean() + 30
    assert depth is not None and depth["agentview"][-8:].mean() < depth["agentview"][:8].mean()
    # The wrist camera sees its own fingers at the bottom of the picture.
    wrist = images["robot0_eye_in_hand"].astype(float)
    assert wrist[-6:].mean() < wrist[:6].mean() - 30
    # The red cube's pixels sit where the stored intrinsics project the cube's centre.
    red = (agent[..., 0] > 60) & (agent[..., 0] - agent[..., 1:].max(axis=-1) > 40)
    assert red.sum() > 30, "the zoomed cube should cover over 30 px at 64x64"
    rows, cols = np.nonzero(red)
    centroid = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
    pos, rot = _camera_pose(sim, "agentview")
    uv = _project(sim.observation["cube_pos"], pos, rot, sim.intrinsics()["agentview"])
    assert np.abs(centroid - uv).max() < 1.5, (centroid, uv)


@pytest.mark.sim
def test_images_match_robosuites_flipped_camera_obs(sim: SimEnv) -> None:
    # robosuite's own renderer returns OpenGL-convention (bottom-up) arrays (macros.IMAGE_CONVENTION
    # "opengl"); ours must equal them flipped vertically, up to lighting differences.
    from robosuite.utils.binding_utils import MjRenderContextOffscreen

    sim.reset(4)
    ours = sim.render()[0]["agentview"].astype(float)
    if sim.env.sim._render_context_offscreen is None:
        MjRenderContextOffscreen(sim.env.sim, device_id=-1)
    theirs = sim.env.sim.render(camera_name="agentview", width=64, height=64).astype(float)
    upright = np.corrcoef(ours.ravel(), theirs[::-1].ravel())[0, 1]
    as_is = np.corrcoef(ours.ravel(), theirs.ravel())[0, 1]
    assert upright > 0.9 and upright > as_is + 0.2, (upright, as_is)


def _ray_depth(sim: SimEnv, camera: str) -> np.ndarray:
    """Ground truth without a renderer: z-depth of the first visual geom along each pixel ray."""
    model, data = sim.env.sim.model._model, sim.env.sim.data._data
    pos, rot = _camera_pose(sim, camera)
    k = sim.intrinsics()[camera]
    visual = np.array([0, 1, 0, 0, 0, 0], dtype=np.uint8)
    hit = np.zeros(1, dtype=np.int32)
    size = sim.image_size
    out = np.empty((size, size))
    for row in range(size):
        for col in range(size):
            # Unnormalised ray with camera-frame z = -1: mj_ray's distance is then the z-depth.
            ray = np.array(
                [(col + 0.5 - k[0, 2]) / k[0, 0], -(row + 0.5 - k[1, 2]) / k[1, 1], -1.0]
            )
            out[row, col] = mujoco.mj_ray(model, data, pos, rot @ ray, visual, 1, -1, hit)
    return out


@pytest.mark.sim
def test_depth_is_metric(sim: SimEnv) -> None:
    sim.reset(5)
    _, depth = sim.render()
    assert depth is not None and depth["agentview"].dtype == np.float32
    for cam in CAMERAS:
        truth = _ray_depth(sim, cam)
        err = np.abs(depth[cam] - truth)
        # Exact up to float32 except where a pixel centre grazes a silhouette edge.
        assert np.median(err) < 1e-5 and np.mean(err < 1e-3) > 0.99, (cam, np.median(err))
    assert 0.4 < depth["agentview"][32, 32] < 1.2  # the table, some 0.7 m from the camera


@pytest.mark.sim
def test_faults_and_bad_actions(
    sim: SimEnv, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # MuJoCo appends its warnings to ./MUJOCO_LOG.TXT
    sim.reset(6)
    with pytest.raises(ValueError, match="7 values"):
        sim.step(np.zeros(6))
    with pytest.raises(SimulationFault, match="non-finite"):
        sim.step(np.array([np.nan] * 7))
    sim.env.sim.data.qvel[:] = 1e12
    with pytest.raises(SimulationFault, match="mjWARN_BAD"):
        sim.step(np.zeros(7))
    # The env survives: the next reset gives a clean episode.
    sim.reset(6)
    sim.step(np.zeros(7))
    assert np.all(np.isfinite(sim.flat_state()))


@pytest.mark.sim
def test_proprio_is_the_8d_vector(sim: SimEnv) -> None:
    obs = sim.reset(7)
    p = sim.proprio()
    assert p.dtype == np.float32 and p.shape == (8,)
    np.testing.assert_allclose(p[:3], obs["robot0_eef_pos"], rtol=1e-6)
    np.testing.assert_allclose(p[3:6], obs["robot0_eef_axis_angle"], rtol=1e-6)
    np.testing.assert_allclose(p[6:], obs["robot0_gripper_qpos"], rtol=1e-6)
    # gripper pointing down: a rotation of about pi
    assert 2.9 < np.linalg.norm(p[3:6]) < 3.3


@pytest.mark.sim
def test_msaa_setting_changes_the_picture(sim: SimEnv) -> None:
    sim.reset(8)
    model, data = sim.env.sim.model._model, sim.env.sim.data._data
    antialiased = CameraRenderer(model, ["agentview"], 64, msaa_samples=4)
    try:
        smooth = antialiased.render(data)[0]["agentview"]
    finally:
        antialiased.close()
    hard = sim.render()[0]["agentview"]
    assert hard.shape == smooth.shape and not np.array_equal(hard, smooth)


@pytest.mark.sim
def test_frustum_culling_leaves_pictures_and_depth_unchanged(sim: SimEnv) -> None:
    model, data = sim.env.sim.model._model, sim.env.sim.data._data
    everything = CameraRenderer(model, CAMERAS, 64, depth=True, cull=False)
    try:
        sim.reset(9)
        for t in range(24):
            sim.step(np.array([0.4, -0.3, -0.5, 0.0, 0.0, 0.2, 1.0]))
            if t % 8 == 7:
                culled, culled_depth = sim.render()
                full, full_depth = everything.render(data)
                for cam in CAMERAS:
                    np.testing.assert_array_equal(culled[cam], full[cam])
                    np.testing.assert_array_equal(culled_depth[cam], full_depth[cam])
        # ... and it does skip work: most of the arm is outside the wrist camera's view.
        wrist = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "robot0_eye_in_hand")
        mujoco.mjv_updateScene(
            model,
            data,
            sim._renderer._option,
            None,
            sim._renderer._cams[1],
            mujoco.mjtCatBit.mjCAT_ALL.value,
            sim._renderer._scene,
        )
        assert sim._renderer._cull(wrist, data) > 20
    finally:
        everything.close()


@pytest.mark.sim
def test_arm_with_six_joint_gripper_needs_an_override() -> None:
    with pytest.raises(ValueError, match="--gripper PandaGripper"):
        SimEnv("Lift", "IIWA", cameras=())
