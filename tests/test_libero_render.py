"""LIBERO's fast rendering: the same physics as LIBERO as shipped, and images close to its own.

The referee is LIBERO itself (``rendering="official", fast_step=False``: robosuite's renderer and
controller code). The same actions from the same initial states run through it and through the
fast env, across a hard reset (LIBERO rebuilds the model on every ``reset``, and both fast paths
must follow). The states must be equal to the bit, not close: physics runs on robosuite's own
model, and the controller substeps give robosuite's controls to the bit
(``tests/test_fast_control.py``), so any difference is a bug. Images are compared by their mean
absolute difference in grey levels (0-255); the threshold is explained where it is checked.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from capvector.errors import CapVectorError, UnknownNameError

pytestmark = pytest.mark.sim

CAMERAS = ("agentview", "robot0_eye_in_hand")
KEYS = tuple(f"{c}_image" for c in CAMERAS)


def _sphere_mesh(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 0.1 m: (V, 3) vertices, (F, 3) outward-wound faces."""
    theta = np.linspace(0, np.pi, n + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    vert = 0.1 * np.concatenate([[[0, 0, 1]], ring, [[0, 0, -1]]])
    m = 2 * n
    faces = []
    for j in range(m):
        faces.append([0, 1 + j, 1 + (j + 1) % m])
        last = 1 + (n - 2) * m
        faces.append([len(vert) - 1, last + (j + 1) % m, last + j])
    for i in range(n - 2):
        for j in range(m):
            a, b = 1 + i * m + j, 1 + i * m + (j + 1) % m
            faces += [[a, a + m, b], [b, a + m, b + m]]
    return vert, np.array(faces, dtype=np.int32)


def _normals(vert: np.ndarray, face: np.ndarray) -> np.ndarray:
    return np.cross(vert[face[:, 1]] - vert[face[:, 0]], vert[face[:, 2]] - vert[face[:, 0]])


def test_decimation_keeps_the_shape_and_the_winding() -> None:
    from capvector.envs.libero.render import decimate_mesh

    vert, face = _sphere_mesh(48)
    cells = 8
    kept, faces, moved, positions = decimate_mesh(vert, face, cells)
    assert len(kept) < len(face) / 10
    assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]))
    assert set(np.unique(faces)) <= set(moved)
    new = vert.copy()
    new[moved] = positions
    # Every vertex moves less than one grid cell (0.2 m / 8), and the surface stays a sphere.
    cell = 0.2 / cells
    assert np.abs(new[moved] - vert[moved]).max() < cell * np.sqrt(3)
    radius = np.linalg.norm(new[np.unique(faces)], axis=1)
    assert radius.min() > 0.1 - cell and radius.max() <= 0.1 + 1e-12
    # Faces still point outwards: the winding of the original face is kept.
    centres = new[faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", _normals(new, faces), centres) > 0)


def test_decimation_leaves_a_mesh_coarser_than_the_grid_alone() -> None:
    from capvector.envs.libero.render import decimate_mesh

    vert, face = _sphere_mesh(4)
    kept, faces, moved, positions = decimate_mesh(vert, face, 64)
    np.testing.assert_array_equal(kept, np.arange(len(face)))
    np.testing.assert_array_equal(faces, face)
    np.testing.assert_array_equal(positions, vert[moved])


def test_smoothed_normals_follow_the_surface_and_keep_creases() -> None:
    from capvector.envs.libero.render import decimate_mesh, smooth_normals

    vert, face = _sphere_mesh(48)
    kept, faces, moved, positions = decimate_mesh(vert, face, 8)
    new = vert.copy()
    new[moved] = positions
    radial = new[faces] / np.linalg.norm(new[faces], axis=-1, keepdims=True)  # (K, 3, 3)

    def degrees(normals: np.ndarray) -> float:
        cos = np.clip(np.einsum("kjx,kjx->kj", normals, radial), -1, 1)
        return float(np.degrees(np.arccos(cos)).mean())

    # What decimation alone leaves a face: the normal of the small original face it was.
    original = _normals(vert, face[kept])
    original /= np.linalg.norm(original, axis=1, keepdims=True)
    flat = degrees(np.repeat(original[:, None], 3, axis=1))
    smooth = degrees(smooth_normals(new, faces))
    assert smooth < 3.0 and flat > 3 * smooth, (smooth, flat)
    # A cube's edges are creases: every corner keeps its own face's normal.
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    corner = smooth_normals(cube, tris)
    own = _normals(cube, tris)
    own /= np.linalg.norm(own, axis=1, keepdims=True)
    np.testing.assert_allclose(corner, np.repeat(own[:, None], 3, axis=1), atol=1e-12)


def _model_xml() -> str:
    vert, face = _sphere_mesh(32)
    v = " ".join(map(str, vert.ravel()))
    f = " ".join(map(str, face.ravel()))
    return f"""<mujoco><asset>
      <mesh name="visual" vertex="{v}" face="{f}"/><mesh name="collision" vertex="{v}" face="{f}"/>
    </asset><worldbody><body><freejoint/>
      <geom type="mesh" mesh="visual" group="1" contype="0" conaffinity="0" mass="0"/>
      <geom type="mesh" mesh="collision" group="0"/>
      <geom type="cylinder" size="0.02 0.1" group="1"/>
    </body><camera name="cam" pos="0 -1 0" xyaxes="1 0 0 0 0 1"/>
    <geom type="plane" size="3 3 0.125" pos="0 0 -0.5" group="1"/>
    </worldbody></mujoco>"""


def test_render_model_changes_a_copy_and_only_the_drawn_meshes() -> None:
    from capvector.envs.libero.render import render_model

    model = mujoco.MjModel.from_xml_string(_model_xml())
    before = {name: np.copy(getattr(model, name)) for name in ("mesh_face", "mesh_vert")}
    facenum = model.mesh_facenum.copy()
    drawn = render_model(model, cells=8)
    for name, value in before.items():
        np.testing.assert_array_equal(getattr(model, name), value)
    np.testing.assert_array_equal(model.mesh_facenum, facenum)
    visual, collision = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, n) for n in
                         ("visual", "collision"))  # fmt: skip
    assert drawn.mesh_facenum[visual] < facenum[visual] / 4
    assert drawn.mesh_facenum[collision] == facenum[collision]
    assert drawn.vis.quality.numslices == 12 and model.vis.quality.numslices == 28
    np.testing.assert_array_equal(drawn.geom_size[:, :2], model.geom_size[:, :2])


def test_render_model_smooths_only_the_decimated_meshes_normals() -> None:
    from capvector.envs.libero.render import render_model

    model = mujoco.MjModel.from_xml_string(_model_xml())
    plain, smooth = render_model(model, cells=8), render_model(model, cells=8, smooth=True)
    visual, collision = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, n) for n in
                         ("visual", "collision"))  # fmt: skip
    f0, k = model.mesh_faceadr[visual], plain.mesh_facenum[visual]
    np.testing.assert_array_equal(smooth.mesh_face[f0 : f0 + k], plain.mesh_face[f0 : f0 + k])
    changed = smooth.mesh_facenormal[f0 : f0 + k] != plain.mesh_facenormal[f0 : f0 + k]
    assert changed.mean() > 0.5
    index = smooth.mesh_facenormal[f0 : f0 + k]
    assert index.min() >= 0 and index.max() < model.mesh_normalnum[visual]
    for name in ("mesh_normal", "mesh_facenormal"):  # the source model is left alone
        np.testing.assert_array_equal(getattr(render_model(model, cells=8), name),
                                      getattr(plain, name))  # fmt: skip
    c0, n = model.mesh_faceadr[collision], model.mesh_facenum[collision]
    np.testing.assert_array_equal(
        smooth.mesh_facenormal[c0 : c0 + n], model.mesh_facenormal[c0 : c0 + n]
    )


def test_every_fast_look_is_a_rendering_option() -> None:
    import typing

    from capvector.envs.libero.env import Rendering
    from capvector.envs.libero.render import FAST_LOOKS, FastLook

    fast = {r for r in typing.get_args(Rendering) if r.startswith("fast")}
    assert set(FAST_LOOKS) == fast
    assert FAST_LOOKS["fast"] == FastLook()  # the default look the studies' demos were drawn with


def test_fast_rendering_is_the_default_on_a_software_renderer(monkeypatch) -> None:
    from capvector.envs.libero import render as libero_render

    for name, fast in [
        ("llvmpipe (LLVM 15.0.6, 256 bits)", True),
        ("softpipe", True),
        ("OSMesa", True),
        ("", True),  # no GL to ask: nothing renders either way
        ("NVIDIA GeForce RTX 4090/PCIe/SSE2", False),
        ("AMD Radeon Pro W6800 (radeonsi, navi21, LLVM 15.0.6, DRM 3.49)", False),
    ]:
        monkeypatch.setattr(libero_render, "gl_renderer", lambda name=name: name)
        assert libero_render.fast_rendering_default() is fast, name


def test_bad_rendering_options_name_the_problem() -> None:
    from capvector.envs.libero.env import make_libero_env

    with pytest.raises(UnknownNameError, match="rendering 'fastt'.*did you mean fast"):
        make_libero_env("libero_spatial", 0, rendering="fastt")
    with pytest.raises(CapVectorError, match="RGB images and depth only.*rendering='official'"):
        make_libero_env("libero_spatial", 0, rendering="fast", camera_segmentations="instance")


def _actions(steps: int) -> np.ndarray:
    # The protocol's 10 wait steps, then down to the table, sideways, gripper closing halfway.
    from capvector.envs.libero.env import NUM_WAIT_STEPS, WAIT_ACTION

    t = np.linspace(0, 1, steps)[:, None]
    move = np.zeros((steps, 7))
    move[:, 0] = 0.4 * np.sin(2 * np.pi * t[:, 0])
    move[:, 2] = np.where(t[:, 0] < 0.6, -0.8, 0.8)
    move[:, 6] = np.where(t[:, 0] < 0.5, -1.0, 1.0)
    return np.concatenate([np.tile(WAIT_ACTION, (NUM_WAIT_STEPS, 1)), move])


def _replay(**kwargs) -> dict[str, list]:
    """States, low-dim observations and upright images after every step of two episodes from
    init states 0 and 1 (a hard reset between them)."""
    from capvector.envs.libero.env import initial_states, make_libero_env

    inits = initial_states("libero_spatial", 0)
    env = make_libero_env("libero_spatial", 0, image_size=128, cameras=CAMERAS, **kwargs)
    out: dict[str, list] = {"states": [], "lowdim": [], "images": [], "type": [type(env).__name__]}
    try:
        for episode, steps in ((0, 30), (1, 12)):
            # LIBERO places its fixtures (cabinet, stove) with numpy's global generator on every
            # reset; the init state does not hold them. Same seed, same scene in both envs.
            np.random.seed(episode)
            env.reset()
            env.set_init_state(inits[episode])
            for action in _actions(steps):
                obs, _, _, _ = env.step(action.tolist())
                out["states"].append(env.get_sim_state().copy())
                out["lowdim"].append(
                    np.concatenate([np.ravel(obs[k]) for k in sorted(obs) if k not in KEYS])
                )
                out["images"].append(np.concatenate([obs[k][::-1] for k in KEYS], axis=1))
                assert all(obs[k].shape == (128, 128, 3) and obs[k].dtype == np.uint8 for k in KEYS)
    finally:
        env.close()
    return out


@pytest.fixture(scope="module")
def runs() -> tuple[dict[str, list], dict[str, list]]:
    # One env at a time: a LIBERO env holds ~2.4 GB.
    official = _replay(rendering="official", fast_step=False)
    fast = _replay(rendering="fast", fast_step=True)
    return official, fast


@pytest.mark.slow
def test_fast_env_has_the_states_of_libero_as_shipped(runs) -> None:
    official, fast = runs
    assert official["type"] == ["OffScreenRenderEnv"] and fast["type"] == ["FastRenderEnv"]
    assert np.array_equal(np.array(fast["states"]), np.array(official["states"]))
    assert np.array_equal(np.array(fast["lowdim"]), np.array(official["lowdim"]))
    # The arm did move (by more than 5 cm), in both episodes.
    states = np.array(official["states"])
    assert np.abs(states[29] - states[10]).max() > 0.05
    assert np.abs(states[-1] - states[-3]).max() > 1e-3


@pytest.mark.slow
def test_fast_images_are_close_to_libero_s_own(runs) -> None:
    official, fast = runs
    diff = [np.abs(a.astype(np.int16) - b).mean() for a, b in zip(official["images"], fast["images"], strict=True)]  # fmt: skip
    # Measured: 3.7 grey levels on average (benchmarks/bench_libero_render.py), of which 2.6 is
    # no 4x MSAA and no reflections alone, and 0.6 robosuite's own sampling (its camera images
    # show the state 2 substeps before the one a step returns). A broken mesh or texture, the
    # coarse 8-cell grid (8.4) or an image upside down (> 30) all exceed 6 on average or 8 in
    # any frame.
    assert np.mean(diff) < 6.0 and np.max(diff) < 8.0, (np.mean(diff), np.max(diff))
    flipped = np.abs(official["images"][-1].astype(np.int16) - fast["images"][-1][::-1]).mean()
    assert flipped > 4 * np.max(diff)  # the comparison can tell orientation apart


REFERENCE = Path(__file__).parent / "fixtures" / "libero_render"
"""LIBERO's own images of five scenes, drawn by upstream's stack (robosuite 1.4 / MuJoCo 2.3.7);
how they were made: its PROVENANCE.md."""


def _reference_differences(scenes: list[str], looks: list[str]) -> dict[str, np.ndarray]:
    """Per look, (scene, camera, 2): mean abs diff and share of pixels > 32 levels apart from the
    reference, the fast renderer drawing the reference's state (same init state, fixtures)."""
    import json

    from PIL import Image

    from capvector.envs.libero.env import initial_states, make_libero_env, set_fixture_poses
    from capvector.envs.libero.render import FAST_LOOKS, image_difference, look_renderer

    meta = json.loads((REFERENCE / "scenes.json").read_text())
    out: dict[str, list] = {look: [] for look in looks}
    for scene in scenes:
        entry = meta["scenes"][scene]
        env = make_libero_env(entry["suite"], entry["task"], render=False)
        try:
            env.reset()
            set_fixture_poses(env, {k: np.asarray(v) for k, v in entry["fixtures"].items()})
            env.set_init_state(initial_states(entry["suite"], entry["task"])[entry["init_state"]])
            model, data = env.env.sim.model._model, env.env.sim.data._data
            for look in looks:
                renderer = look_renderer(model, meta["cameras"], meta["size"], FAST_LOOKS[look])
                try:
                    images, _ = renderer.render(data)
                finally:
                    renderer.close()
                out[look].append(
                    [
                        image_difference(
                            np.asarray(Image.open(REFERENCE / f"{scene}_{camera}.png")),
                            images[camera],
                        )
                        for camera in meta["cameras"]
                    ]
                )
        finally:
            env.close()
    return {look: np.array(rows) for look, rows in out.items()}


@pytest.mark.slow
def test_fast_close_is_closer_to_upstream_images() -> None:
    # One of the reference's five scenes (a scene costs an env and two renderers): task 7's, with
    # the stove (its mirror), the plate's stripes and a bowl in both cameras.
    diff = _reference_differences(["libero_spatial_7_0"], ["fast", "fast-close"])
    fast, close = diff["fast"].mean(axis=0), diff["fast-close"].mean(axis=0)  # (camera, measure)
    # Measured here (agentview, wrist): fast 3.67 and 3.68 grey levels, 3.8 and 3.7 % of pixels
    # > 32 levels apart; fast-close 1.47 and 2.08, 1.2 and 2.1 % (all five scenes:
    # benchmarks/bench_libero_render_look.py, docs/evaluation.md). One of fast-close's settings
    # alone (MSAA: 0.71 of fast's wrist difference; reflections, 8 mm cells: 0.84 and 0.87 of
    # agentview's, over the five scenes) misses the 0.65 bound; a broken mesh, texture or image
    # orientation misses the absolute ones.
    assert np.all(close < 0.65 * fast), (close, fast)
    assert np.all(close[:, 0] < 2.5) and np.all((fast[:, 0] > 2.5) & (fast[:, 0] < 5.5)), (
        close,
        fast,
    )
