"""Depth and scene annotations in LIBERO demos, from the fast renderer to a training step.

The referees: robosuite's own depth (``rendering="official", camera_depths=True``, its buffer
through ``camera_utils.get_real_depth_map``) for the fast renderer's, and the simulator's object
and camera poses for what the reader gives back from a recorded file: depth back-projected with
the intrinsics the reader returns must land on the objects where MuJoCo has them, and the RGB
pixel there must show the object. A depth map not rotated like the RGB, or intrinsics not rotated
with the frames, puts the points tens of centimetres off (the plate is 20 cm from the mirror line).
"""

from __future__ import annotations

import re
from pathlib import Path

import mujoco
import numpy as np
import pytest

pytestmark = pytest.mark.sim

SUITE = "libero_spatial"
CAMERAS = ("agentview", "robot0_eye_in_hand")
SIZE = 64
BOWL = "akita_black_bowl_1"  # the one the task moves: in both cameras' view at the start
MUJOCO_TO_OPENCV = np.diag([1.0, -1.0, -1.0])  # MuJoCo cameras look down -z with y up


def test_fast_depth_matches_robosuite_depth() -> None:
    from robosuite.utils.camera_utils import get_real_depth_map

    from capvector.envs.libero.env import initial_states, make_libero_env

    init = initial_states(SUITE, 0)[0]
    depth = {}
    for rendering in ("official", "fast"):
        env = make_libero_env(
            SUITE, 0, cameras=CAMERAS, image_size=SIZE, rendering=rendering, camera_depths=True
        )
        try:
            np.random.seed(0)  # LIBERO places its fixtures from numpy's global generator
            env.reset()
            obs = env.set_init_state(init)
            for camera in CAMERAS:
                d = obs[f"{camera}_depth"]
                if rendering == "official":
                    d = get_real_depth_map(env.env.sim, d)
                depth[rendering, camera] = d.reshape(SIZE, SIZE)
        finally:
            env.close()
    for camera in CAMERAS:
        official, fast = depth["official", camera], depth["fast", camera]
        diff = np.abs(official - fast)
        same = diff < 0.02  # off the edges, where decimated meshes and 4x MSAA move silhouettes
        # Measured at 64 px: 95% / 97% of the pixels, median 5.7 mm at ~1 m (agentview; robosuite
        # draws with 4x MSAA, whose depth reads ~0.4% short) and 0.2 mm (wrist camera). One of
        # them upside down: 1.8 m / 2.5 cm.
        assert same.mean() > 0.9, (camera, same.mean())
        assert np.median(diff[same]) < 0.008, (camera, np.median(diff[same]))
        assert np.median(np.abs(official - fast[::-1])) > 0.02


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One demo of LIBERO-Spatial task 0 with depth, recorded through the CLI."""
    from capvector.cli import main

    out = tmp_path_factory.mktemp("libero_depth")
    main(["demos", "--suite", SUITE, "--tasks", "0", "--episodes-per-task", "1", "--depth",
          "--image-size", str(SIZE), "--out", str(out / "demos"), "--no-progress"])  # fmt: skip
    (path,) = (out / "demos").glob("*.hdf5")
    return path


@pytest.fixture(scope="module")
def scene(recorded: Path):
    """(read samples at steps 0 and 60, the sim's object positions and camera poses there)."""
    import h5py

    from capvector.data.hdf5 import HDF5RobotDataset
    from capvector.envs.libero.env import make_libero_env
    from capvector.envs.libero.experts import task_env

    dataset = HDF5RobotDataset(
        [recorded], list(CAMERAS), ["ee_states", "gripper_states"], chunk_size=1,
        load_depth=True, load_annotations=True,
    )  # fmt: skip
    with h5py.File(recorded) as f:
        states = f["data/demo_0/states"][()]
    env = make_libero_env(SUITE, 0, render=False)
    inner = task_env(env)
    model, data = inner.sim.model._model, inner.sim.data._data
    out = []
    try:
        for t in (0, 60):
            inner.sim.set_state_from_flattened(states[t])
            inner.sim.forward()
            objects = {n: data.xpos[inner.obj_body_id[n]].copy() for n in inner.objects_dict}
            poses = {}
            for camera in CAMERAS:
                cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
                poses[camera] = (data.cam_xpos[cid].copy(), data.cam_xmat[cid].reshape(3, 3).copy())
            out.append((dataset[t], objects, poses))
    finally:
        env.close()
    return out


def _back_project(depth: np.ndarray, k: np.ndarray, pose) -> np.ndarray:
    """(H, W, 3) world points of every pixel, as GeometricTeacher back-projects (pixel centres)."""
    v, u = np.meshgrid(
        np.arange(depth.shape[0]) + 0.5, np.arange(depth.shape[1]) + 0.5, indexing="ij"
    )
    camera = np.stack([(u - k[0, 2]) * depth / k[0, 0], (v - k[1, 2]) * depth / k[1, 1], depth], -1)
    position, rotation = pose
    return camera @ (rotation @ MUJOCO_TO_OPENCV).T + position


def _pixel(point: np.ndarray, k: np.ndarray, pose) -> tuple[int, int]:
    """(row, column) where ``point`` (world) projects with the intrinsics ``k``."""
    position, rotation = pose
    x, y, z = MUJOCO_TO_OPENCV @ rotation.T @ (point - position)
    return int(np.floor(k[1, 1] * y / z + k[1, 2])), int(np.floor(k[0, 0] * x / z + k[0, 2]))


def test_read_depth_back_projects_onto_the_objects(scene) -> None:
    # The plate (flat, wide) and the cookie box, seen by both cameras at step 0 and (the arm
    # elsewhere) at step 60: the read depth at the pixel where the object projects, back-projected
    # with the read intrinsics, is the object's top surface, within 2 cm of its body origin
    # (measured: 0.4-1.5 cm). The black bowls are left out: from agentview, the pixel of a bowl's
    # origin sees its near wall, 6 cm along the ray.
    # Where the wrist camera looks at step 60 depends on the expert's path: an object out of its
    # view is skipped, but every camera must see some object.
    checked: dict[str, int] = dict.fromkeys(CAMERAS, 0)
    for sample, objects, poses in scene:
        for i, camera in enumerate(CAMERAS):
            k = sample["intrinsics"][i].numpy().astype(np.float64)
            points = _back_project(sample["depth"][i].numpy(), k, poses[camera])
            for name in ("plate_1", "cookies_1"):
                row, col = _pixel(objects[name], k, poses[camera])
                if not (0 <= row < SIZE and 0 <= col < SIZE):
                    continue
                error = np.linalg.norm(points[row, col] - objects[name])
                assert error < 0.02, (camera, name, error)
                checked[camera] += 1
    assert min(checked.values()) >= 2, checked


def _bowl_contrast(sample, objects, poses, camera: str, i: int) -> tuple[int, float]:
    """(pixels, grey levels): how many pixels the read depth puts on the black bowl's walls
    (within 5 cm of its axis, 2 cm or more above the table), and how much darker the read RGB is
    there than on the table around it (12-20 cm from the bowl, at the bowl's foot)."""
    k = sample["intrinsics"][i].numpy().astype(np.float64)
    offset = _back_project(sample["depth"][i].numpy(), k, poses[camera]) - objects[BOWL]
    radius = np.linalg.norm(offset[..., :2], axis=-1)
    wall = (radius < 0.05) & (offset[..., 2] > 0.02)
    table = (radius > 0.12) & (radius < 0.2) & (np.abs(offset[..., 2]) < 0.01)
    grey = sample["images"][i].numpy().mean(axis=0) * 255
    return int(wall.sum()), float(grey[table].mean() - grey[wall].mean())


def test_read_depth_and_rgb_stay_aligned(scene) -> None:
    # Where the read depth sees the walls of the black bowl, the RGB read beside it is dark:
    # measured 74 (agentview) and 124 (wrist camera) grey levels darker than the light wood table
    # around it. The depth rotated against the RGB: 7 and 14; mirrored left-right: 22 and 67;
    # upside down: no wall at all; the intrinsics left as stored (not rotated with the frames):
    # 43 and 66. Every camera must pass, as every orientation bug hits both.
    sample, objects, poses = scene[0]
    for i, camera in enumerate(CAMERAS):
        pixels, darker = _bowl_contrast(sample, objects, poses, camera, i)
        assert pixels >= 10 and darker > 55, (camera, pixels, darker)


def test_annotations_state_where_the_objects_are(scene) -> None:
    # Every movable object's "x=.., y=.." in the step's annotation is where MuJoCo has it.
    from capvector.envs.libero.annotations import readable_names

    for t, (sample, objects, _) in zip((0, 60), scene, strict=True):
        text = sample["annotation"]
        names = readable_names(list(objects))
        for name, position in objects.items():
            found = re.search(
                rf"The {names[name]} (?:is|is in the gripper) at x=(-?[0-9.]+), y=(-?[0-9.]+)", text
            )
            assert found, (name, text)
            assert np.allclose([float(found[1]), float(found[2])], position[:2], atol=0.006), text
        if t == 0:
            assert text.startswith("The robot is moving above the akita black bowl 1."), text
        else:
            assert "The akita black bowl 1 is in the gripper" in text, text


def test_aux_sft_trains_on_libero_demos(recorded: Path, tmp_path: Path) -> None:
    """configs/recipes/aux_sft.yaml's objectives on the recorded LIBERO demo: two steps through
    ``capvector fit``, both auxiliary losses finite and non-zero."""
    import csv

    from capvector.cli import main

    repo = Path(__file__).resolve().parents[1]
    main([
        "fit", "--config", str(repo / "configs/recipes/aux_sft.yaml"),
        f"--data.train_files=[{recorded}]", "--data.cameras=[agentview,robot0_eye_in_hand]",
        "--data.proprio_keys=[ee_states,gripper_states]", "--data.batch_size=2",
        "--trainer.max_steps=2", "--trainer.log_every_n_steps=1",
        f"--trainer.default_root_dir={tmp_path}", f"--trainer.logger.init_args.save_dir={tmp_path}",
        "--trainer.enable_progress_bar=false",
    ])  # fmt: skip
    with (tmp_path / "fit" / "version_0" / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    for column in ("train/loss_spatial_alignment", "train/loss_reasoning"):
        values = [float(r[column]) for r in rows if r.get(column)]
        assert len(values) == 2, (column, rows)
        assert all(np.isfinite(v) and v != 0.0 for v in values), (column, values)
