"""`capvector demos`: the HDF5 layout, shapes, orientation, success, atomic writes, CLI errors."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from capvector.cli import main as capvector
from capvector.envs.robosuite.demos import record_demos
from capvector.envs.robosuite.env import SimEnv, camera_intrinsics
from capvector.errors import CapVectorError
from capvector.workflows.demos import main

SIZE = 32
CAMERAS = ["agentview", "robot0_eye_in_hand"]


@pytest.fixture(scope="module")
def demo_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demos") / "lift.hdf5"
    argv = ["--task", "Lift", "--episodes", "2", "--out", str(out), "--image-size", str(SIZE)]
    assert main([*argv, "--depth", "--seed", "40", "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def sim() -> SimEnv:
    env = SimEnv("Lift", cameras=CAMERAS, image_size=SIZE, depth=True)
    yield env
    env.close()


@pytest.mark.sim
def test_data_group_attrs(demo_file: Path) -> None:
    with h5py.File(demo_file) as f:
        data = f["data"]
        env_args = json.loads(data.attrs["env_args"])
        assert env_args["env_name"] == "Lift" and env_args["type"] == 1
        assert env_args["env_version"] == "1.5.2"
        kwargs = env_args["env_kwargs"]
        assert kwargs["robots"] == "Panda" and "controller_configs" in kwargs
        assert data.attrs["language_instruction"] == "lift the red cube"
        assert json.loads(data.attrs["cameras"]) == CAMERAS
        np.testing.assert_allclose(data.attrs["agentview_intrinsics"], camera_intrinsics(35, SIZE))
        assert data.attrs["robot0_eye_in_hand_intrinsics"].shape == (3, 3)
        demos = sorted(data.keys())
        assert demos == ["demo_0", "demo_1"]
        assert data.attrs["total"] == sum(data[d].attrs["num_samples"] for d in demos)


@pytest.mark.sim
def test_demo_layout_and_shapes(demo_file: Path) -> None:
    with h5py.File(demo_file) as f:
        demo = f["data/demo_0"]
        t = demo.attrs["num_samples"]
        assert demo.attrs["seed"] == 40
        assert demo.attrs["language_instruction"] == "lift the red cube"
        assert demo.attrs["model_file"].startswith("<mujoco")
        assert demo["actions"].shape == (t, 7) and demo["actions"].dtype == np.float32
        assert demo["executed_actions"].shape == (t, 7)
        assert demo["states"].ndim == 2 and demo["states"].shape[0] == t
        assert demo["rewards"].shape == demo["dones"].shape == (t,)
        assert demo["annotations"].shape == (t,)
        obs = demo["obs"]
        for cam in CAMERAS:
            assert obs[f"{cam}_image"].shape == (t, SIZE, SIZE, 3)
            assert obs[f"{cam}_image"].dtype == np.uint8
            assert obs[f"{cam}_depth"].shape == (t, SIZE, SIZE)
            assert obs[f"{cam}_depth"].dtype == np.float32
        expected = {
            "robot0_eef_pos": 3,
            "robot0_eef_quat": 4,
            "robot0_eef_axis_angle": 3,
            "robot0_gripper_qpos": 2,
            "cube_pos": 3,
            "cube_quat": 4,
        }
        for key, dim in expected.items():
            assert obs[key].shape == (t, dim), key


@pytest.mark.sim
def test_demos_succeed_and_labels_are_clean(demo_file: Path) -> None:
    with h5py.File(demo_file) as f:
        for name in ("demo_0", "demo_1"):
            demo = f["data"][name]
            first = demo.attrs["first_success"]
            t = demo.attrs["num_samples"]
            assert 0 < first < t
            assert demo["rewards"][-1] > 0 and demo["dones"][-1] == 1 and demo["dones"][0] == 0
            # The cube ends 4+ cm above where it started (Lift's success test).
            cube_z = demo["obs/cube_pos"][:, 2]
            assert cube_z[-1] - cube_z[0] > 0.04
            actions, executed = demo["actions"][:], demo["executed_actions"][:]
            assert set(np.unique(actions[:, 6])) <= {-1.0, 1.0}
            # DART noise moves only the executed xyz; the labels stay the expert's.
            assert not np.allclose(actions[:, :3], executed[:, :3])
            np.testing.assert_array_equal(actions[:, 3:], executed[:, 3:])


@pytest.mark.sim
def test_stored_images_are_upright_renders_of_the_seed(demo_file: Path, sim: SimEnv) -> None:
    with h5py.File(demo_file) as f:
        demo = f["data/demo_0"]
        stored = {cam: demo[f"obs/{cam}_image"][0] for cam in CAMERAS}
        stored_depth = demo["obs/agentview_depth"][0]
        sim.reset(int(demo.attrs["seed"]))
        np.testing.assert_array_equal(sim.flat_state(), demo["states"][0])
    images, depth = sim.render()
    for cam in CAMERAS:
        np.testing.assert_array_equal(stored[cam], images[cam])
    np.testing.assert_allclose(stored_depth, depth["agentview"])
    agent = stored["agentview"].astype(float)
    assert agent[-4:].mean() > agent[:4].mean() + 30  # the table at the bottom


@pytest.mark.sim
def test_annotations_describe_phase_and_positions(demo_file: Path) -> None:
    with h5py.File(demo_file) as f:
        demo = f["data/demo_0"]
        notes = [n.decode() for n in demo["annotations"][:]]
        cube = demo["obs/cube_pos"][0]
    assert notes[0].startswith("The robot is moving above the red cube.")
    assert f"x={round(float(cube[0]), 2) + 0.0:.2f}" in notes[0]
    assert any("closing the gripper on the red cube" in n for n in notes)
    assert "in the gripper" in notes[-1]


@pytest.mark.sim
def test_failure_to_reach_the_count_leaves_no_file(tmp_path: Path, sim: SimEnv) -> None:
    out = tmp_path / "never.hdf5"
    with pytest.raises(CapVectorError, match="only 1 of 1 attempts"):
        record_demos("Lift", 2, out, max_attempts=1, sim=sim, progress=False, seed=40)
    assert list(tmp_path.iterdir()) == []


def test_cli_reports_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.hdf5"
    argv = ["demos", "--task", "Lift", "--episodes", "1", "--out", str(out), "--fovy", "agentview"]
    assert capvector(argv) == 2
    assert "CAMERA=DEGREES" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.sim
def test_no_cameras_records_low_dim_demos(tmp_path: Path) -> None:
    out = tmp_path / "lowdim.hdf5"
    argv = ["--task", "Lift", "--episodes", "1", "--out", str(out), "--cameras", "--no-progress"]
    assert main(argv) == 0
    with h5py.File(out) as f:
        assert json.loads(f["data"].attrs["cameras"]) == []
        obs = f["data/demo_0/obs"]
        assert not [key for key in obs if key.endswith(("_image", "_depth"))]
        assert "robot0_eef_pos" in obs and "cube_pos" in obs
