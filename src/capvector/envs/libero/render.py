"""LIBERO's scenes rendered at a fraction of robosuite's cost on a CPU, with the same physics.

On Mesa's software rasteriser (llvmpipe: machines without a GPU renderer) a LIBERO frame costs
what its triangles cost, not its pixels: a LIBERO-Spatial scene holds ~293k visual mesh faces
(each black bowl 42.5k, the robot's pedestal 33k), so two 128 px cameras take ~180 ms per step
with robosuite's defaults, at 128 px as at 256 px. The fast mode renders the same cameras
differently, and nothing else:

- Visual meshes are decimated by vertex clustering (:func:`decimate_mesh`): each mesh's vertices
  are snapped to a grid of ``cells`` cells along its largest extent, faces that collapse are
  dropped, and every surviving face keeps its own normals and texture coordinates. At 128 px a
  bowl covers a few hundred pixels; the default grid (:data:`FAST_CELLS`) keeps ~2k of its faces.
- The decimated meshes live in a copy of the MuJoCo model used only for drawing
  (:func:`render_model`); physics runs on robosuite's model, untouched, so the states are those of
  the official env to the bit (``tests/test_libero_render.py``). The copy has the same bodies,
  geoms, cameras and lights, so ``mjv_updateScene`` draws it from the physics data as it is.
- Drawn as the project's :class:`~capvector.envs.robosuite.env.CameraRenderer` draws: both cameras into one
  buffer with one readback, no multisampling (robosuite's default is 4 samples), no reflections,
  shadows, skybox or haze, geoms wholly outside a camera's view skipped. The geom groups drawn
  are robosuite's (visual, and the controller's target markers). Reflections cost the most
  after the meshes: LIBERO-Spatial's stove base is a mirror (a box with reflectance 0.5), for
  which robosuite draws the whole scene a second time; without them it looks matte grey.
- Depth, when asked (``camera_depths=True``), is read back in metres with the images, in the same
  call: it costs nothing measurable (``docs/performance.md``).

Decimation is numpy, ~0.2 s for a whole scene, cached in memory per mesh (keyed by a digest of
its vertices and faces, and the grid), so a hard reset (LIBERO rebuilds the model on every
``reset``) only copies the model (~0.3 s) and builds a GL context again (~1.5 s: the scene's
textures, 190 MB). The images differ from robosuite's by ~4 grey levels (of 255) on average,
mostly at edges (anti-aliasing) and on the mirror: ``benchmarks/bench_libero_render.py``
measures both, and :meth:`FastRenderEnv.render` draws the state a step returns, where robosuite's camera
observations show the state 2 substeps (4 ms) earlier (its sampling timer).

How it draws is a look (:class:`FastLook`, presets in :data:`FAST_LOOKS`): ``fast`` as above (the
default), ``fast-close`` with reflections, 4x MSAA and finer decimation of large meshes, less than
half as far from upstream's images at ~2.3x the fast step's cost
(``benchmarks/bench_libero_render_look.py``, ``docs/evaluation.md``).

:func:`fast_rendering_default` decides the default: fast where the GL renderer is a software one
(``MUJOCO_GL=osmesa``, or an EGL/GLX renderer string naming llvmpipe, softpipe, swrast, ...),
robosuite's where a GPU draws (it renders the full scene in milliseconds there).
"""

from __future__ import annotations

import copy
import functools
import hashlib
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from capvector.envs.robosuite.env import CameraRenderer, _gl_context_class
from capvector.errors import CapVectorError, missing_extra, unknown_name

try:
    import mujoco
    import robosuite.macros as macros
    from robosuite.environments.robot_env import IMAGE_CONVENTION_MAPPING
except ImportError as err:
    raise missing_extra("the simulator", "sim", err) from err

__all__ = [
    "FAST_CELLS",
    "FAST_LOOKS",
    "FastLook",
    "FastRenderEnv",
    "decimate_mesh",
    "fast_rendering_default",
    "gl_renderer",
    "image_difference",
    "look_renderer",
    "render_model",
    "smooth_normals",
]

log = logging.getLogger(__name__)

FAST_CELLS = 16
"""Grid cells along a visual mesh's largest extent (see ``benchmarks/bench_libero_render.py``
for the cost and the image difference of other values)."""
DRAWN_GROUPS = (1, 2)
"""robosuite's offscreen renderer draws groups 1 (visual meshes) and 2 (its controller's target
markers) and hides group 0 (collision geoms): ``MjvOption``'s defaults with
``render_collision_mesh=False``."""
SMOOTH_CREASE_DEGREES = 45.0
"""Faces meeting at more than this angle keep a sharp edge when normals are smoothed."""
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer", "swiftshader")
"""Substrings of ``GL_RENDERER`` (lower case) that name a CPU rasteriser."""


@functools.cache
def gl_renderer() -> str:
    """``GL_RENDERER`` of the OpenGL backend ``MUJOCO_GL`` selects ("" when none can be made)."""
    if os.environ.get("MUJOCO_GL", "egl").lower() == "osmesa":
        return "OSMesa"  # Mesa's off-screen renderer: software by construction
    try:
        context = _gl_context_class()(1, 1)
    except Exception as e:  # no display, no EGL device: nothing renders, fast or not
        log.debug("no GL context to query the renderer: %s", e)
        return ""
    try:
        context.make_current()
        from OpenGL import GL

        name = GL.glGetString(GL.GL_RENDERER)
        return name.decode() if isinstance(name, bytes) else str(name or "")
    finally:
        context.free()


def fast_rendering_default() -> bool:
    """True where OpenGL runs on the CPU (or cannot be queried): the fast mode pays off there."""
    name = gl_renderer().lower()
    return name == "" or name == "osmesa" or any(s in name for s in SOFTWARE_RENDERERS)


def decimate_mesh(
    vert: np.ndarray, face: np.ndarray, cells: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertex clustering on a ``cells``-cell grid along the mesh's largest extent.

    ``vert`` (V, 3) and ``face`` (F, 3) are one mesh's vertices and faces (indices into ``vert``).
    Returns ``kept`` (K,) indices of the faces that survive (three distinct clusters, one face per
    cluster triple and winding), ``faces`` (K, 3) their new vertex indices into ``vert``, and
    ``moved`` (C,) / ``positions`` (C, 3): the one vertex standing for each cluster and the mean of
    its cluster, where it moves to. A face keeps its corners' normals and texture coordinates.
    """
    low = vert.min(axis=0)
    extent = float((vert.max(axis=0) - low).max())
    if extent == 0.0 or len(face) == 0:
        return np.arange(len(face)), face.copy(), np.zeros(0, np.int64), np.zeros((0, 3))
    cell = np.minimum(np.floor((vert - low) * (cells / extent)), cells).astype(np.int64)
    key = (cell[:, 0] * (cells + 1) + cell[:, 1]) * (cells + 1) + cell[:, 2]
    _, moved, cluster = np.unique(key, return_index=True, return_inverse=True)
    cluster = cluster.reshape(-1)
    count = np.bincount(cluster)
    positions = np.stack([np.bincount(cluster, vert[:, j]) for j in range(3)], axis=1)
    positions /= count[:, None]
    corners = cluster[face]
    kept = np.flatnonzero(
        (corners[:, 0] != corners[:, 1])
        & (corners[:, 1] != corners[:, 2])
        & (corners[:, 2] != corners[:, 0])
    )
    # Many faces of a dense patch land on the same three clusters: draw one of them. Rotating
    # each triple to start at its smallest cluster keeps the winding (front and back differ).
    corners = corners[kept]
    start = np.argmin(corners, axis=1)
    rows = np.arange(len(corners))[:, None]
    canonical = corners[rows, (start[:, None] + np.arange(3)) % 3]
    _, first = np.unique(canonical, axis=0, return_index=True)
    kept = kept[np.sort(first)]
    return kept, moved[cluster[face[kept]]], moved, positions


def smooth_normals(
    vert: np.ndarray, faces: np.ndarray, crease_degrees: float = SMOOTH_CREASE_DEGREES
) -> np.ndarray:
    """Per-corner normals of a (decimated) mesh: (K, 3, 3) unit vectors for ``faces`` (K, 3).

    A corner's normal is the area-weighted mean of the normals of the faces around its vertex
    that lie within ``crease_degrees`` of its own face's (smoothing groups, as modelling tools
    compute vertex normals): curved surfaces shade smoothly, a crease such as a box's edge or a
    plate's rim stays sharp. Decimation alone leaves each surviving face the normals of the small
    original face it was, nearly one normal per face, which draws a bowl as facets (issue 61).
    """
    area = np.cross(vert[faces[:, 1]] - vert[faces[:, 0]], vert[faces[:, 2]] - vert[faces[:, 0]])
    length = np.linalg.norm(area, axis=1, keepdims=True)  # twice the face's area
    unit = np.divide(area, length, out=np.zeros_like(area), where=length > 0)
    cos = np.cos(np.radians(crease_degrees))
    # Corners sorted by vertex: each corner visits the corners of its vertex's group, the d-th
    # one in round d (a group holds the few faces around one vertex).
    corner_vertex = faces.ravel()
    corner_face = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(corner_vertex, kind="stable")
    vertex, face = corner_vertex[order], corner_face[order]
    start = np.searchsorted(vertex, vertex, side="left")
    size = np.bincount(vertex)[vertex]
    summed = np.zeros((len(order), 3))
    for d in range(int(size.max(initial=0))):
        rows = np.flatnonzero(d < size)
        other = face[start[rows] + d]
        near = np.einsum("ix,ix->i", unit[other], unit[face[rows]]) >= cos
        summed[rows[near]] += area[other[near]]
    normals = np.empty_like(summed)
    normals[order] = summed
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, norm, out=np.repeat(unit, 3, axis=0), where=norm > 0)
    return normals.reshape(-1, 3, 3)


@dataclass(frozen=True)
class FastLook:
    """How the fast renderer draws a scene (a preset of :data:`FAST_LOOKS`).

    ``cells``: the decimation grid (:func:`decimate_mesh`), refined to cells of at most
    ``cell_size`` metres on large meshes (:func:`render_model`); ``smooth``: normals of the decimated
    surface (:func:`smooth_normals`) instead of the original face's; ``shadows`` and
    ``reflections``: MuJoCo's, as robosuite's renderer draws them (a shadow map per light; the
    stove's mirror draws the scene again); ``msaa_samples``: anti-aliasing (robosuite's: 4).
    Culling (skipping geoms outside a camera's view) is on only with neither shadows nor
    reflections: an arm above the view still casts a shadow into it.
    """

    cells: int = FAST_CELLS
    cell_size: float | None = None
    smooth: bool = False
    shadows: bool = False
    reflections: bool = False
    msaa_samples: int = 0


FAST_LOOKS: dict[str, FastLook] = {
    "fast": FastLook(),
    "fast-close": FastLook(reflections=True, msaa_samples=4, cell_size=0.008),
}
"""The fast renderer's presets by ``rendering`` name (``capvector.envs.libero.env.Rendering``).
``fast`` is the default on a CPU and what the studies' demos were drawn with: changing it changes
every fast-rendered image, so a closer look is a preset of its own (``docs/evaluation.md``
measures each against robosuite's renderer)."""


_DECIMATED: dict[tuple[bytes, int], tuple[np.ndarray, ...]] = {}
"""Decimations by (mesh digest, cells): a hard reset compiles the same meshes again. A scene's
entries take a few MB; LIBERO has a few hundred distinct meshes in all."""


def drawn_meshes(model: mujoco.MjModel, groups: Sequence[int] = DRAWN_GROUPS) -> list[int]:
    """Ids of the meshes that geoms of ``groups`` draw."""
    drawn = np.isin(model.geom_group, groups) & (model.geom_type == mujoco.mjtGeom.mjGEOM_MESH)
    return sorted({int(i) for i in model.geom_dataid[drawn]})


def render_model(
    model: mujoco.MjModel,
    cells: int = FAST_CELLS,
    groups: Sequence[int] = DRAWN_GROUPS,
    *,
    smooth: bool = False,
    cell_size: float | None = None,
) -> mujoco.MjModel:
    """A copy of ``model`` whose drawn meshes are decimated; ``model`` itself is not changed.

    The copy's arrays keep their sizes: each decimated mesh's faces are written to the start of its
    own face range and ``mesh_facenum`` shrinks, which is all that ``mjr_uploadMesh`` reads.
    Built-in shapes are tessellated more coarsely too: cylinders and spheres with 12 slices and 2
    stacks instead of 28 x 16 (LIBERO's table legs: 4 x ~1k triangles), planes as a grid of 0.5 m
    squares (the floor: 48 x 48 squares); neither changes a 128 px image of these scenes.
    ``cell_size`` (metres) refines the grid of large meshes: a mesh gets at least as many cells
    as cells of that size span its largest extent (a stove's burner rings, a plate's rim).
    ``smooth`` gives each decimated mesh the normals of its new surface (:func:`smooth_normals`),
    written over its own normal range where they fit (a mesh decimated to a third of its faces
    or fewer always fits).
    """
    out = copy.copy(model)
    out.vis.quality.numslices = min(out.vis.quality.numslices, 12)
    out.vis.quality.numstacks = min(out.vis.quality.numstacks, 2)
    planes = out.geom_type == mujoco.mjtGeom.mjGEOM_PLANE
    out.geom_size[planes, 2] = np.maximum(out.geom_size[planes, 2], 0.5)
    for i in drawn_meshes(model, groups):
        v0, nv = model.mesh_vertadr[i], model.mesh_vertnum[i]
        f0, nf = model.mesh_faceadr[i], model.mesh_facenum[i]
        vert = np.ascontiguousarray(model.mesh_vert[v0 : v0 + nv], dtype=np.float64)
        face = np.ascontiguousarray(model.mesh_face[f0 : f0 + nf], dtype=np.int32)
        digest = hashlib.blake2b(vert.tobytes() + face.tobytes(), digest_size=16).digest()
        grid = cells
        if cell_size is not None:
            extent = float(np.ptp(vert, axis=0).max()) if nv else 0.0
            grid = max(cells, int(np.ceil(extent / cell_size)))
        if (digest, grid) not in _DECIMATED:
            _DECIMATED[digest, grid] = decimate_mesh(vert, face, grid)
        kept, faces, moved, positions = _DECIMATED[digest, grid]
        out.mesh_vert[v0 + moved] = positions
        k = len(kept)
        out.mesh_face[f0 : f0 + k] = faces
        out.mesh_facenormal[f0 : f0 + k] = model.mesh_facenormal[f0 + kept]
        if model.mesh_texcoordadr[i] >= 0:
            out.mesh_facetexcoord[f0 : f0 + k] = model.mesh_facetexcoord[f0 + kept]
        out.mesh_facenum[i] = k
        if smooth and k < nf:
            normals, index = _smoothed(digest, grid, vert, faces, moved, positions)
            n0 = model.mesh_normaladr[i]
            if len(normals) <= model.mesh_normalnum[i]:
                out.mesh_normal[n0 : n0 + len(normals)] = normals
                out.mesh_facenormal[f0 : f0 + k] = index
    return out


_SMOOTHED: dict[tuple[bytes, int], tuple[np.ndarray, np.ndarray]] = {}


def _smoothed(
    digest: bytes,
    cells: int,
    vert: np.ndarray,
    faces: np.ndarray,
    moved: np.ndarray,
    positions: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """A decimated mesh's distinct smoothed normals (N, 3) and each corner's index (K, 3)."""
    if (digest, cells) not in _SMOOTHED:
        new = vert.copy()
        new[moved] = positions
        corners = smooth_normals(new, faces).reshape(-1, 3).astype(np.float32)
        normals, index = np.unique(corners, axis=0, return_inverse=True)
        _SMOOTHED[digest, cells] = normals, index.reshape(-1, 3).astype(np.int32)
    return _SMOOTHED[digest, cells]


def look_renderer(
    model: mujoco.MjModel,
    cameras: Sequence[str],
    image_size: int,
    look: FastLook,
    *,
    depth: bool = False,
) -> CameraRenderer:
    """A :class:`CameraRenderer` that draws ``model``'s scene as ``look`` says."""
    lit = look.shadows or look.reflections
    return CameraRenderer(
        render_model(model, look.cells, smooth=look.smooth, cell_size=look.cell_size),
        cameras,
        image_size,
        depth=depth,
        msaa_samples=look.msaa_samples,
        cull=not lit,
        geom_groups=DRAWN_GROUPS,
        shadows=look.shadows,
        reflections=look.reflections,
    )


def image_difference(a: np.ndarray, b: np.ndarray, levels: int = 32) -> tuple[float, float]:
    """How far image ``b`` is from ``a`` (both (H, W, 3) uint8): the mean absolute difference in
    grey levels (0-255, over pixels and channels) and the share of pixels whose largest channel
    difference exceeds ``levels`` (issue 61's two measures)."""
    if a.shape != b.shape:
        raise CapVectorError(f"images of shapes {a.shape} and {b.shape} cannot be compared")
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16))
    return float(diff.mean()), float((diff.max(axis=-1) > levels).mean())


class FastRenderEnv:
    """A LIBERO env built without robosuite's renderer, whose observations carry camera images
    drawn by the fast renderer: the keys (``<camera>_image``), shape, dtype and orientation of
    LIBERO's ``OffScreenRenderEnv`` (robosuite's ``IMAGE_CONVENTION``: bottom-up by default).

    ``depth=True`` adds ``<camera>_depth``: (H, W) float32 metres along the optical axis, in the
    images' orientation, read back from the same pass as the images. robosuite's env
    (``camera_depths=True``) gives the raw depth buffer in [0, 1] there, (H, W, 1); its
    ``camera_utils.get_real_depth_map`` turns that into these metres (``tests/test_libero_depth.py``
    compares the two).

    Everything else is the wrapped env's (``env.env``, ``sim``, ``check_success``,
    ``get_sim_state``, ``seed``, ...). The render model follows the physics model across hard
    resets. ``render()`` gives the current images upright, ``{camera: (H, W, 3) uint8}``, and
    ``render_depth()`` the images and depth maps upright.
    """

    def __init__(
        self,
        env: Any,
        cameras: Sequence[str],
        image_size: int,
        *,
        look: FastLook | str = "fast",
        depth: bool = False,
    ) -> None:
        if not cameras:
            raise CapVectorError("FastRenderEnv needs at least one camera")
        self.look_name = look if isinstance(look, str) else "custom"
        if isinstance(look, str):
            if look not in FAST_LOOKS:
                raise unknown_name("fast rendering look", look, FAST_LOOKS)
            look = FAST_LOOKS[look]
        self.env = env
        self.cameras = tuple(cameras)
        self.image_size = image_size
        self.look = look
        self.depth = depth
        self._source: mujoco.MjModel | None = None
        self._renderer: CameraRenderer | None = None
        self._flip = IMAGE_CONVENTION_MAPPING[macros.IMAGE_CONVENTION] == 1  # OpenGL rows

    def __getattr__(self, name: str) -> Any:
        # Only reached for attributes this class lacks; "env" itself is always set in __init__.
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def render(self) -> dict[str, np.ndarray]:
        """The current images, upright (the render model is rebuilt after a hard reset)."""
        return self.render_depth()[0]

    def render_depth(self) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
        """The current images and, with ``depth=True``, depth maps in metres, all upright."""
        model = self.env.env.sim.model._model
        if model is not self._source:
            if self._renderer is not None:
                self._renderer.close()
                self._renderer = None  # a rebuild that raises leaves no closed renderer behind
            self._renderer = look_renderer(
                model, self.cameras, self.image_size, self.look, depth=self.depth
            )
            self._source = model
        # Depth from the same pass as the images: CameraRenderer linearises MuJoCo's depth buffer
        # with the model's clip planes (znear, zfar times the model extent), the metres robosuite's
        # camera_utils.get_real_depth_map computes from its own buffer.
        return self._renderer.render(self.env.env.sim.data._data)

    def _with_images(self, obs: dict[str, Any]) -> dict[str, Any]:
        images, depth = self.render_depth()
        frames = {f"{camera}_image": image for camera, image in images.items()}
        frames.update({f"{camera}_depth": d for camera, d in (depth or {}).items()})
        for key, frame in frames.items():
            obs[key] = np.ascontiguousarray(frame[::-1]) if self._flip else frame
        return obs

    def reset(self) -> dict[str, Any]:
        return self._with_images(self.env.reset())

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, dict[str, Any]]:
        obs, reward, done, info = self.env.step(action)
        return self._with_images(obs), reward, done, info

    def set_init_state(self, init_state: np.ndarray) -> dict[str, Any]:
        return self._with_images(self.env.set_init_state(init_state))

    def regenerate_obs_from_state(self, mujoco_state: np.ndarray) -> dict[str, Any]:
        return self._with_images(self.env.regenerate_obs_from_state(mujoco_state))

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self.env.close()
