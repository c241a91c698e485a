"""Zero-shot robustness variants: named perturbations of the scene a policy was trained in.

A variant changes what the policy sees (camera pose, lighting, colours and textures) or which arm
it drives, never the task: the initial state of an episode is still a function of its seed alone,
so a variant's episodes start where the unperturbed ones do and differ only in the perturbation.
The perturbation is drawn anew for every episode from the episode's seed and the variant's name,
so a (variant, seed) pair always looks the same, in any process.

The visual variants run robosuite's own domain-randomisation modders (``robosuite.utils.mjmod``)
with the arguments of its ``DomainRandomizationWrapper`` (``DEFAULT_CAMERA_ARGS``,
``DEFAULT_LIGHTING_ARGS``, ``DEFAULT_COLOR_ARGS``), applied once per episode after the reset as the
wrapper's ``randomize_on_reset`` does; ``camera-strong`` scales the sizes up. Deviations: the
wrapper randomises every camera, we randomise only the cameras the policy renders (the others are
never seen). robosuite 1.5.2's ``TextureModder`` fails on MuJoCo 3 (it reads ``MjModel.tex_rgb``,
which MuJoCo 3 renamed ``tex_data``), so :class:`ColorModder` re-implements its colour path with the
same arguments: each geom's colour (its material's, when it has one) moves ``local_rgb_interpolation``
of the way to a random colour and the material's reflectance/shininess/specular
``local_material_interpolation`` of the way to random values, as ``randomize_local`` does; the
texture bitmaps keep their patterns (tinted by the new material colour) instead of being redrawn as
checker/noise/gradient patterns.

This module's table imports nothing heavy; :class:`SceneRandomizer` imports robosuite when built.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from capvector.errors import unknown_name

if TYPE_CHECKING:
    from capvector.envs.robosuite.env import SimEnv

# robosuite 1.5.2 robosuite/wrappers/domain_randomization_wrapper.py, copied as values (importing
# them would import robosuite): DEFAULT_CAMERA_ARGS, DEFAULT_LIGHTING_ARGS, DEFAULT_COLOR_ARGS.
ROBOSUITE_CAMERA_ARGS: Mapping[str, Any] = MappingProxyType({
    "randomize_position": True, "randomize_rotation": True, "randomize_fovy": True,
    "position_perturbation_size": 0.01, "rotation_perturbation_size": 0.087,
    "fovy_perturbation_size": 5.0,
})  # fmt: skip
ROBOSUITE_LIGHTING_ARGS: Mapping[str, Any] = MappingProxyType({
    "randomize_position": True, "randomize_direction": True, "randomize_specular": True,
    "randomize_ambient": True, "randomize_diffuse": True, "randomize_active": True,
    "position_perturbation_size": 0.1, "direction_perturbation_size": 0.35,
    "specular_perturbation_size": 0.1, "ambient_perturbation_size": 0.1,
    "diffuse_perturbation_size": 0.1,
})  # fmt: skip
ROBOSUITE_COLOR_ARGS: Mapping[str, Any] = MappingProxyType(
    {"local_rgb_interpolation": 0.2, "local_material_interpolation": 0.3}
)
"""The colour arguments :class:`ColorModder` takes (robosuite's: ``randomize_local`` and
``randomize_material`` on, the skybox left out: our renderer does not draw it)."""


@dataclass(frozen=True)
class SceneVariant:
    """A named perturbation: modder arguments for what it changes, None for what it leaves."""

    name: str
    description: str
    camera: Mapping[str, Any] | None = None
    """``robosuite.utils.mjmod.CameraModder`` arguments, over the rendered cameras."""
    lighting: Mapping[str, Any] | None = None
    """``LightingModder`` arguments, over every light."""
    color: Mapping[str, Any] | None = None
    """:class:`ColorModder` arguments, over every visual geom."""
    robot: str | None = None
    """Another arm in place of the task's (the scene and the episode seeds stay)."""
    gripper: str | None = None
    """The gripper for ``robot`` when its own lacks two finger joints."""

    @property
    def visual(self) -> bool:
        return any(x is not None for x in (self.camera, self.lighting, self.color))


def _scaled(args: Mapping[str, Any], factor: float) -> Mapping[str, Any]:
    return MappingProxyType({k: v * factor if k.endswith("_size") else v for k, v in args.items()})


VARIANTS: dict[str, SceneVariant] = {
    v.name: v
    for v in (
        SceneVariant(
            "camera", "robosuite's camera randomisation: ±1 cm, ±5°, ±5° fovy",
            camera=ROBOSUITE_CAMERA_ARGS,
        ),
        SceneVariant(
            "camera-strong", "camera randomisation at 3× robosuite's sizes: ±3 cm, ±15°, ±15° fovy",
            camera=_scaled(ROBOSUITE_CAMERA_ARGS, 3.0),
        ),
        SceneVariant(
            "lighting", "robosuite's lighting randomisation (position, direction, colour, on/off)",
            lighting=ROBOSUITE_LIGHTING_ARGS,
        ),
        SceneVariant(
            "color", "robosuite's local colour and material randomisation of every visual geom",
            color=ROBOSUITE_COLOR_ARGS,
        ),
        SceneVariant(
            "all", "camera, lighting and colour randomisation together (robosuite's sizes)",
            camera=ROBOSUITE_CAMERA_ARGS, lighting=ROBOSUITE_LIGHTING_ARGS,
            color=ROBOSUITE_COLOR_ARGS,
        ),
        SceneVariant("sawyer", "the Sawyer arm in place of the task's", robot="Sawyer"),
        SceneVariant(
            "ur5e", "the UR5e arm (with the Panda gripper) in place of the task's",
            robot="UR5e", gripper="PandaGripper",
        ),
    )
}  # fmt: skip


def get_variant(name: str) -> SceneVariant:
    """The :class:`SceneVariant` called ``name``, with the known names in the error."""
    try:
        return VARIANTS[name]
    except KeyError:
        raise unknown_name("scene variant", name, VARIANTS) from None


def variant_seed(variant: str, seed: int) -> int:
    """The perturbation's seed: a function of the variant's name and the episode seed only."""
    return (zlib.crc32(variant.encode()) ^ (seed * 2654435761)) % 2**32


class ColorModder:
    """robosuite's ``TextureModder`` colour path with ``randomize_local`` (see the module doc)."""

    def __init__(
        self,
        model: Any,
        random_state: np.random.RandomState,
        local_rgb_interpolation: float,
        local_material_interpolation: float,
    ) -> None:
        self.model = model
        self.random_state = random_state
        self.rgb_step = local_rgb_interpolation
        self.material_step = local_material_interpolation
        self.save_defaults()

    def save_defaults(self) -> None:
        m = self.model
        self._geom_rgba = m.geom_rgba.copy()
        self._mat_rgba = m.mat_rgba.copy()
        self._mat_light = (m.mat_reflectance.copy(), m.mat_shininess.copy(), m.mat_specular.copy())

    def restore_defaults(self) -> None:
        m = self.model
        m.geom_rgba[:] = self._geom_rgba
        m.mat_rgba[:] = self._mat_rgba
        m.mat_reflectance[:], m.mat_shininess[:], m.mat_specular[:] = self._mat_light

    def randomize(self) -> None:
        m = self.model
        materials = sorted({int(i) for i in m.geom_matid if i >= 0})
        plain = np.flatnonzero(m.geom_matid < 0)
        rgb = self.random_state.uniform(0, 1, size=(len(plain) + len(materials), 3))
        t = self.rgb_step
        m.geom_rgba[plain, :3] = (1 - t) * self._geom_rgba[plain, :3] + t * rgb[: len(plain)]
        m.mat_rgba[materials, :3] = (1 - t) * self._mat_rgba[materials, :3] + t * rgb[len(plain) :]
        t = self.material_step
        for values, default in zip(
            (m.mat_reflectance, m.mat_shininess, m.mat_specular), self._mat_light, strict=True
        ):
            draw = self.random_state.uniform(0, 1, size=len(materials))
            values[materials] = (1 - t) * default[materials] + t * draw


class SceneRandomizer:
    """Applies a visual variant to one :class:`SimEnv`; call :meth:`apply` after every reset."""

    def __init__(self, sim: SimEnv, variant: SceneVariant) -> None:
        from robosuite.utils.mjmod import CameraModder, LightingModder

        self.sim = sim
        self.variant = variant
        self._random = np.random.RandomState(0)
        mj = sim.env.sim
        self.modders: list[Any] = []
        if variant.camera is not None:
            self.modders.append(
                CameraModder(mj, self._random, camera_names=list(sim.cameras), **variant.camera)
            )
        if variant.lighting is not None:
            self.modders.append(LightingModder(mj, self._random, **variant.lighting))
        if variant.color is not None:
            self.modders.append(ColorModder(mj.model._model, self._random, **variant.color))

    def apply(self, seed: int) -> None:
        """Restore the defaults, then draw this episode's perturbation from ``seed``."""
        self._random.seed(variant_seed(self.variant.name, seed))
        for modder in self.modders:
            modder.restore_defaults()
        for modder in self.modders:
            modder.randomize()
        self.sim.env.sim.forward()  # camera poses in data follow the model's new cam_pos/quat

    def restore(self) -> None:
        for modder in self.modders:
            modder.restore_defaults()
        self.sim.env.sim.forward()
